"""One vocabulary of physical effects, declared once (DESIGN.md, "One vocabulary: effects").

The simulated plant, the model library, the diagnosis and the compensators speak of the same
effects by the same names. Each :class:`Effect` says, in one place:

* ``plant_table``: the ``[plant.<table>]`` of a simulated rig that produces it;
* ``component``: the model component (:mod:`hilbench.models.effect_components`) that describes it, and
  ``forms``: the spec variants in which the diagnosis tries it (the data choose among them, by the
  rule ``form_choice``);
* ``requires``: what the data must contain for the effect to be testable (names checked by
  :mod:`hilbench.diagnosis.testability`), ``built_into``: bases that already contain it;
* ``signature``: the residual pattern that is its evidence (:mod:`hilbench.diagnosis.evidence`),
  and ``evidence_check``: a pattern the evidence must show before the effect may be significant.

Adding an effect, or a form of one, is an entry here plus its model component (and plant table);
the diagnosis loops over this registry and branches on no effect name (docs/decisions/0009).
"""

from __future__ import annotations

from dataclasses import dataclass

#: requirements on the data, checked by hilbench.diagnosis.testability
MEMORYLESS_BASE = "memoryless-base"  # the base model has no memory of its own (``linear``)
SEVERAL_RATES = "several-rates"  # drive frequencies, or one frequency's rates, spread by 1.5x or more, in training too
BROADBAND = "broadband"  # several rates or steps; calibrated across validation rates if only there
HOLDS = "holds"  # the input holds still long enough for slow drift to show
VARYING_CHANNEL = "varying-channel"  # an auxiliary channel that moves well beyond its noise


@dataclass(frozen=True)
class Effect:
    name: str
    physics: str  # what it is physically, one line
    plant_table: str | None  # [plant.<table>] of a simulated rig, None when no plant table makes it
    component: str | None  # model component name (base or effect) that describes it
    #: spec parts the diagnosis tries, default the name alone; for an effect that needs a memoryless
    #: base, the bases that replace it
    forms: tuple[str, ...] = ()
    #: "train": the best training fit; "inner-split": held-back training rows at the end of each
    #: training part; "inner-split-both": as "inner-split", and a richer form must fit the rows it
    #: saw better too; "inner-range": held-back training rows at the largest inputs; "inner-blocks":
    #: held-back interleaved blocks of the training rows
    form_choice: str = "train"
    requires: tuple[str, ...] = ()
    built_into: tuple[str, ...] = ()  # bases that already contain the effect
    signature: str | None = None  # residual pattern (hilbench.diagnosis.evidence.SIGNATURES)
    evidence_check: str | None = None  # a pattern the evidence must show (hilbench.diagnosis.evidence)
    papers: str = ""

    def spec_parts(self) -> tuple[str, ...]:
        return self.forms or (self.name,)


#: The effects the diagnosis tries, in DESIGN.md order. Auxiliary channels (temperature, load, ...)
#: are effects too, named by their channel: see :data:`AUX_CHANNEL`.
EFFECTS: dict[str, Effect] = {e.name: e for e in (
    # hysteresis on a memoryless base: one base per family of loop shape, the play operators
    # first (odd loops, nothing but weights to fit); the others must predict held-back training
    # rows better, and the rows they fit too: the M-play's polynomial (one-sided, asymmetric loops), the ISSF-Duhem with a
    # dead-zone (the butterfly loop of an unbiased magnetostrictive actuator, strain even in the
    # current, paper 001), with a Gompertz shape, Bouc-Wen. Play operators cannot make a butterfly
    # at all: their loops are odd (on a butterfly rig: linear 8.32 um, pi 8.31, duhem-d 0.40)
    Effect("hysteresis", "rate-independent memory", "hysteresis", "pi",
           forms=("pi", "pmpi", "duhem-d", "duhem-g", "bouc-wen"), form_choice="inner-split-both",
           requires=(MEMORYLESS_BASE,), signature="direction", papers="all"),
    # asymmetry: v^2 first; v^2..v^4 must predict the training rows at the largest drive better from
    # the rows below them: higher powers fitted over one range swing beyond it, and test runs often
    # drive further (an even v^2 on a one-sided drive: 0.175 against 0.040 um on validation,
    # decision 0046)
    Effect("asymmetry", "loops not centrally symmetric: memoryless polynomial shaping", "asymmetry", "asymmetry",
           forms=("asymmetry(order=2)", "asymmetry"), form_choice="inner-range",
           built_into=("mpi", "pmpi"), signature="even-input", papers="002, 004, 000"),
    # saturation: of the hysteresis output (tanh, or a knee of searched sharpness: copies of the
    # hysteresis columns), or of the drive before the hysteresis (a Hammerstein knee, decision
    # 0039: no columns, the base's thresholds met at other commands); the output forms flatten
    # the loop but cannot move where the operators turn (a drive that flattens before the
    # actuator's memory: validation 32 % worse with them)
    Effect("saturation", "loop flattening at large drive, on the input or on the hysteresis output", "saturation",
           "saturation", forms=("saturation", "saturation(form=knee)", "saturation(form=hammerstein)",
                                 "saturation(form=wiener)"),
           built_into=("fpmpi",), signature="odd-input", papers="000, 001"),
    # rate-dependence: velocity damping first (m and g searched, one weight); the frequency
    # polynomials of 003 (three gains searched, three weights) must fit training better and beat it
    # on held-back blocks spread over the training rows, which hold its rates (decision 0034): on
    # training fit alone they won by their freedom (on a velocity damping: 0.649 against 0.662 um
    # on training, 2.94 against 2.30 um on validation), and held back at the end of training they
    # lost where only the end's rates were judged (as on a frequency gain); the polynomials of
    # order 1 before those of order 3: forms that fit training alike go to the fewest parameters
    # (on a gain linear in f: the cubic validated 3x worse than the base, order 1 69 % better;
    # decision 0063)
    Effect("rate-dependence", "loop width and gain change with the input rate", "rate_dependence",
           "rate-dependence", forms=("rate-dependence(form=damping)", "rate-dependence(form=frequency,order=1)",
                                    "rate-dependence(form=frequency)"),
           form_choice="inner-blocks", requires=(SEVERAL_RATES,), signature="fast-vs-slow", papers="003"),
    # dynamics: the command held linearly between samples (a smooth drive) or sample by sample (a
    # DAC's staircase); which one the rig has is the data's to say, on training rows (decision 0053)
    Effect("dynamics", "linear dynamics after the hysteresis", "dynamics", "dynamics",
           forms=("dynamics", "dynamics(hold=zoh)"),
           requires=(BROADBAND,), signature="derivatives", papers="002, 000"),
    # creep: the fixed log-spaced bank first (nothing searched, weights >= 0: little room to
    # overfit); the logarithmic law (the bank's spectrum flat, one weight), two searched elements,
    # creep after the hysteresis (two searched elements, or the law, one weight per column:
    # decision 0038) must beat it on held-back rows
    Effect("creep", "slow drift after a change of input, spanning decades", "creep", "creep",
           forms=("creep(form=bank)", "creep(form=log)", "creep", "creep(form=output)", "creep(form=log-output)"),
           form_choice="inner-split",
           requires=(HOLDS,), signature="drift-on-holds", evidence_check="drift-on-holds", papers="literature"),
    Effect("delay", "pure time delay of amplifier, sensor or DAQ", "delay", "delay",
           requires=(BROADBAND,), signature="rate-of-change", papers="literature"),
)}

#: An auxiliary channel as an effect: the model's gain and offset follow a recorded channel.
AUX_CHANNEL = Effect("<channel>", "dependence on a measured auxiliary channel", None, None,
                     requires=(VARYING_CHANNEL,), signature="channel", papers="000")

#: Plant tables that are effects by their channel (the plant simulates them, models read the channel).
AUX_PLANT_TABLES = ("temperature", "load")

#: Plant tables that are not effects of the actuator but of the bench around it.
BENCH_PLANT_TABLES = {"amplifier": "amplifier"}


def effect_of_plant_table(table: str) -> str:
    """The effect name of a ``[plant.<table>]`` (``rate_dependence`` -> ``rate-dependence``)."""
    for e in EFFECTS.values():
        if e.plant_table == table:
            return e.name
    if table in AUX_PLANT_TABLES:
        return table
    if table in BENCH_PLANT_TABLES:
        return BENCH_PLANT_TABLES[table]
    raise KeyError(f"no effect has the plant table {table!r}")


def effect(name: str) -> Effect:
    """The registry entry of an effect; an auxiliary channel's name gives :data:`AUX_CHANNEL`."""
    return EFFECTS.get(name, AUX_CHANNEL)
