"""Seeded regressions of the diagnosis: cases of the randomized benchmark (``diagnosis_cases.py``)
that once went wrong, each with what went wrong and the decision that fixed it.

``tests/diagnosis/test_random_cases.py`` runs one case per mechanism (its ``SUITE``); every case here
runs in ``python benchmarks/bench_diagnosis_random.py --regressions``, which reports the ones missed.
What a case must give is what the benchmark counts as a hit: the hidden effect ranked first and
significant (two hidden effects: the first significant candidate names hidden effects only; clean:
nothing significant). The generator is not tuned to the diagnosis, and nothing here is tuned per case.

Verdicts were found to move with the CPU's floating-point kernels (numpy's AVX-512 kernels, OpenBLAS's
SkylakeX kernels) on a few cases (140, 223, 4711); the test suite pins the kernels (tests/conftest.py),
the benchmark runs on the machine's own.
"""

from __future__ import annotations

from typing import NamedTuple


class Regression(NamedTuple):
    seed: int
    hidden: tuple[str, ...]  # () for a clean case
    form: str | None  # the hidden effect's form (single-effect cases)
    id: str


#: one hidden effect: ranked first and significant
SINGLE = [
    Regression(22, ("asymmetry",), "even-2", "22-asymmetry-even2-pi"),
    # the knee cuts only the largest excursions: validation rmse drops 56 %, but the gain sits in few of
    # the 20 blocks and the signed-rank test over blocks failed (p >= 0.01); the sign-flip test of the
    # summed difference finds it (decision 0022)
    Regression(16, ("saturation",), "output-knee", "16-saturation-output-knee-pi"),
    Regression(122, ("creep",), "kelvin-voigt-decades", "122-creep-kelvin-voigt-pi"),
    # a 1.3-sample sensor delay: delay had the larger gain (0.76) but failed the block test while
    # dynamics (0.71) passed it; since runs that sweep their rate are split in interleaved blocks,
    # delay is ranked first and significant
    Regression(175, ("delay",), "sensor", "175-delay-sensor-pi1"),
    Regression(60, ("dynamics",), "resonance-above-drive", "60-dynamics-above-drive-pi1"),
    Regression(165, ("rate-dependence",), "frequency-gain", "165-rate-frequency-gain-pi1"),
    # rates beyond training's in validation: the frequency form keeps its rates at the training's (its
    # polynomials have no physical extrapolation) while the damping form extrapolates (decision 0016)
    Regression(178, ("rate-dependence",), "frequency-gain", "178-rate-frequency-gain-pmpi"),
    # the gain of the whole loop changes with the drive frequency: fitted as copies of every column
    # with their own weights (+-1e4) it trained to the noise and validated 10x worse than the base;
    # as one gain k(f) on the loop (decision 0018) it carries over
    Regression(150, ("rate-dependence",), "frequency-gain", "150-rate-frequency-gain-pmpi"),
    # a frequency gain whose training program holds its fastest sine in one held-back block of the
    # form choice: the polynomials, held at the inner fit's rates, were judged there on rates they
    # never saw and lost to the damping (10x lower validation rmse with them); scored where the inner
    # fit saw the rates they win (decision 0050)
    Regression(2664, ("rate-dependence",), "frequency-gain", "2664-rate-frequency-gain-pi1"),
    # the same with the training's only 25 Hz sine and a junction reading 93 Hz in one held-back block,
    # where the inner fit's width term predicted 4078 um (base 21 um); 39x lower validation rmse with
    # the polynomials (decision 0050)
    Regression(2734, ("rate-dependence",), "frequency-gain", "2734-rate-frequency-gain-pmpi"),
    # a gain linear in the drive frequency on a short record: the cubic polynomials trained at the
    # noise and validated 3x worse than the base; k(f) of order 1 trains as well and validates 69 %
    # better (decision 0063)
    Regression(4763, ("rate-dependence",), "frequency-gain", "4763-rate-frequency-gain-linear-pi"),
    # velocity damping trained on one sine frequency whose amplitude falls 6x: several rates, so
    # testable since decision 0064 (untestable before); 81 % lower validation rmse on a chirp
    Regression(4677, ("rate-dependence",), "velocity-damping", "4677-rate-velocity-damping-one-frequency-pi"),
    Regression(177, ("rate-dependence",), "velocity-damping", "177-rate-velocity-damping-pi1"),
    # velocity damping on a one-sided drive: 44 % lower validation rmse, on the fast stretches only;
    # failed the signed-rank test over 20 blocks, passes the sum test (decision 0022)
    Regression(31, ("rate-dependence",), "velocity-damping", "31-rate-velocity-damping-pi1"),
    # an amplifier delay: dynamics' refit equals delay's on validation, and dynamics' residual pattern
    # (derivatives) contains delay's (rate of change), so it explains more of any residual: the tie
    # stays in gain order, where delay leads
    Regression(7, ("delay",), "amplifier", "7-delay-amplifier-pmpi"),
    # an even term on a one-sided drive: about a drive that never changes sign even and odd patterns
    # look alike and an output saturation (more free parameters) validates equally well (rmse within
    # 1 %, block test p >= 0.01); the tie goes to the candidate with fewer parameters
    Regression(68, ("asymmetry",), "even-2", "68-asymmetry-even2-one-sided-pi1"),
    # the same on a multitone: saturation's odd pattern scored 0.93 against the even 0.69, but on a
    # drive that never changes sign a cubic fits the parabola (parity overlap 0.97), so the patterns
    # do not decide and parsimony does
    Regression(83, ("asymmetry",), "even-4", "83-asymmetry-even4-one-sided-pi1"),
    Regression(107, ("hysteresis",), "one-sided-play", "107-hysteresis-one-sided-linear"),
    # butterfly loops of a Duhem with a dead zone from a linear start: hysteresis as play operators
    # explained 0.2 % and an even polynomial ranked first (37 %); tried in each family of loop shape,
    # the Duhem form validates at the noise (8.32 -> 0.40 um)
    Regression(266, ("hysteresis",), "duhem", "266-hysteresis-duhem-butterfly-linear"),
    # play operators from a linear start, a test run reaching past training's input: PMPI predicted
    # the training run's held-back end better (0.40 against 0.62 um) from a poorer optimum than the
    # play operators' on the rows it fitted (0.61 against 0.55 um), and validated 3x worse than them;
    # a loop family must fit the rows it saw better too
    # Not reproducible across CPUs: on an AVX-512 machine (2026-11-26, the same numpy, scipy and numba)
    # the hysteresis candidate keeps PMPI, trains 0.881 and validates 14.6 % lower (refused as chance
    # extrapolation), and rate-dependence (16.9 %) ranks first; on the machines where it passed the
    # play operators were chosen (above). Which loop family wins rests on fits that the last bits move.
    # Missed today on the kernels the suite pins (2026-12-05, AMD EPYC: numpy's AVX2 kernels with
    # OpenBLAS's SkylakeX or Haswell ones): rate-dependence (16.9 %) ranks first, as on the AVX-512
    # machine above; the suite runs the play form on 4042.
    Regression(223, ("hysteresis",), "play", "223-hysteresis-play-linear"),
    # a warm-up ramp per run under a PMPI base: the base's etas had bent to the missing gain, and the
    # refit started from them (one local search) explained training (88 %) but not validation (5 %);
    # with a second search from the cold scan's best point it validates 60 % lower (decision 0027)
    # Not reproducible across CPUs: with numpy's AVX-512 kernels the PMPI base lands in another optimum
    # (validation 1.855 against 2.871 um with the AVX2 kernels, NPY_DISABLE_CPU_FEATURES=X86_V4) and the
    # temperature refit from it trains as well (87 % against 89 %) but validates 3.5 % lower instead of 74 %.
    Regression(140, ("temperature",), "ramp", "140-temperature-ramp-pmpi"),
    # a temperature cycle under a PMPI base: the refit's searches from the warm point and the cold
    # scan's best point stopped in a poor optimum (training 0.0085 um, validation 0.039 um, block
    # p = 0.021) and pairs with rate-dependence or saturation ranked first; the cold fit's second
    # start reaches 0.0074 / 0.0103 um and a warm refit now runs it too (decision 0029)
    Regression(59, ("temperature",), "cycling", "59-temperature-cycling-pmpi"),
    # a logarithmic creep under a Duhem base, runs in roles: the creep forms fell back to the fixed bank
    # (no training rows to hold back), which trained 30 % better and validated 57 % worse; an inner split
    # of the training run picks creep after the hysteresis (training 0.097 -> 0.017 um, validation
    # 0.110 -> 0.079 um), whose validation gain agrees in explained mean square (decision 0031)
    Regression(26, ("creep",), "logarithmic", "26-creep-logarithmic-duhem"),
    # a logarithmic creep under a Duhem base, one run split by time: the bank and the law on the
    # input validated 20 % lower at best and an even polynomial ranked first; the law on every
    # hysteresis column (creep(form=log-output), decision 0038) validates at the noise (0.143 -> 0.021 um)
    Regression(200, ("creep",), "logarithmic", "200-creep-logarithmic-duhem-one-run"),
    # a drive that saturates before a PMPI base: the output forms of saturation trained 65 % lower and
    # validated 32 % higher (they flatten the loop but cannot move where the operators turn), so
    # nothing was significant; the knee on the drive (saturation(form=hammerstein), decision 0039)
    # is chosen and validates lower
    Regression(805, ("saturation",), "input-knee", "805-saturation-input-knee-pmpi"),
    # a warm-up ramp in each run (train and test runs on their own trajectories): the test run takes
    # the temperature further, so the channel model buys 18 % in training and 77 % on validation
    # (0.168 -> 0.038 um); refused as chance extrapolation until the channel's reach counted (decision 0042)
    Regression(110, ("temperature",), "ramp", "110-temperature-ramp-pi1"),
    # an output knee on a one-sided PI (wide loops): the output forms flatten by the drive, trained
    # at the noise with copies of every column and validated at 6x it, and an even polynomial ranked
    # first; the knee of the model's own hysteresis output (saturation(form=wiener), decision 0043)
    # fits training as well with 12 weights instead of 24 and validates at the noise
    Regression(969, ("saturation",), "output-knee", "969-saturation-output-knee-pi1"),
    # a placed weight on a load cell that the test run loads 1.8x further: training's error is mostly
    # sensor noise (0.069 -> 0.064 um over a 0.057 um floor, 6.6 % of the rmse), validation falls 90 %;
    # refused as chance extrapolation until the check compared the model's error above the noise
    # (40 % of training's mean square above it; decision 0044)
    Regression(1518, ("load",), "placed-weight", "1518-load-placed-weight-pi"),
    # a lag and a resonance on Duhem rigs whose validation error is 1.39x and 1.23x a floor its
    # estimates agree on to 0.03 and 0.24 of its variance: each refit took the error to the floor
    # (p = 1e-4), refused as "nothing left to explain" by a fixed 1.5x the floor until the band was
    # the floor's own uncertainty (decision 0045)
    Regression(2033, ("delay",), "amplifier", "2033-delay-amplifier-duhem-d"),
    Regression(2029, ("dynamics",), "resonance-above-drive", "2029-dynamics-above-drive-duhem-d"),
    # an even v^2 on a one-sided drive whose test run drives 1.23x further than training: v^2..v^4
    # validated 0.175 um and a saturation (0.090) ranked first; v^2 alone validates 0.040 um, and
    # the training rows at the largest drive choose it (decision 0046)
    Regression(2129, ("asymmetry",), "even-2", "2129-asymmetry-even2-one-sided-pi1"),
    # an output knee on a bipolar PI: the knee of the model's output validated at 0.55 um, an even
    # v^2 at 1.04; the block tests could not separate them over 20 blocks (p 0.013) and the even
    # pattern put v^2 first, until a leader leaving under half the other's mean square was no tie
    # (decision 0047)
    Regression(2220, ("saturation",), "output-knee", "2220-saturation-output-knee-pi"),
    # creep as Kelvin-Voigt elements over decades under a PMPI base: the bank validated 14 % lower, but a
    # record a few correlation lengths long fills the 20 blocks of the test barely independently (p 0.07);
    # refitted without interleaved blocks of training, the bank lowers them too (p 1e-4): significant
    # as both tests pass sqrt(P_MAX) (decision 0052)
    Regression(2801, ("creep",), "kelvin-voigt-decades", "2801-creep-kelvin-voigt-pmpi"),
    # a 125 Hz resonance at zeta 0.031 behind a command held sample by sample (the simulated DAC):
    # dynamics with a first-order hold stopped at 123.6 Hz to mimic the half sample, and a pair with
    # a damping that is not there ranked first (86 %); behind a zero-order hold, chosen on training,
    # dynamics alone finds 125.0 Hz and validates 94 % lower (decision 0053)
    Regression(2948, ("dynamics",), "resonance-above-drive", "2948-dynamics-above-drive-zoh-pmpi"),
    # a 0.8-sample sensor delay under pi1 whose test run ends on a staircase: the delay validated 85 %
    # lower, a second-order lag (142 Hz, zeta 0.63) 78 %; the gain sits at the five steps, so the block
    # test gave the delay p 0.011, and the held-back fold of training (two blocks) missed training's
    # steps (3 % lower, p 0.26) while the lag passed and ranked first; cross-validated over five folds
    # the held-back rows hold them (60 % lower, p 1e-4) and the delay is first (decision 0056)
    Regression(4119, ("delay",), "sensor", "4119-delay-sensor-staircase-pi1"),
    # play loops from a linear start, training a power-on step, a hold and the first cycle of a sine:
    # the loop families were judged on an inner fit of the step and the hold, and duhem-d won the
    # held-back cycle and validated worse than the linear base (2.41 against 2.16 um); an inner fit
    # that never turns the input cannot choose a loop shape, so pi stays and validates at 0.093 um
    # (decision 0057)
    Regression(4042, ("hysteresis",), "play", "4042-hysteresis-play-step-and-hold-linear"),
    # logarithmic creep under a PMPI base: creep's refit validates 90 % lower, but the loops fitted
    # without creep miss by more during motion than the drift along any hold, which was 0.19x the rms
    # against the 0.2x required, and rate-dependence ranked first; the drift is 8.5x the noise's
    # standard error and creep's refit removes 92 % of it (decision 0059)
    Regression(4586, ("creep",), "logarithmic", "4586-creep-logarithmic-pmpi"),
    # even terms on play rigs whose operators sit between the base's ten thresholds: a saturation took
    # up the straight segments with its own share and validated 25 % (4711) and 9 % (4223) lower than
    # the even term; on a base of 30 operators the even term validates 5.9x and 1.6x lower and goes
    # first (diagnosis/resolution.py, decision 0060)
    # Not reproducible across CPUs: with numpy's AVX-512 kernels (AMD EPYC, 2026-12-01) the PMPI
    # alternative of the wrong-base check lands in another optimum (training 0.044 against 0.073 um with
    # NPY_DISABLE_CPU_FEATURES=X86_V4, validation 0.074 against 0.264 um), 2.07x below the best single
    # effect, so the base is reported wrong and ranked first; without them asymmetry leads (above).
    Regression(4711, ("asymmetry",), "even-4", "4711-asymmetry-even4-pi"),
    Regression(4223, ("asymmetry",), "even-6", "4223-asymmetry-even6-pi"),
    # an amplifier delay under a PMPI base on an M-play rig: a lag took up part of the base's mismatch
    # as well and validated 0.344 um against the delay's 0.435, so dynamics ranked first; at the
    # input's fastest changes the delay's error is the noise's (first differences 0.263 um against
    # the noise's 0.265) and the lag's 0.315 (p 1e-4), so the delay goes first (decision 0066)
    Regression(4719, ("delay",), "amplifier", "4719-delay-amplifier-fast-error-pmpi"),
    # a cycling temperature moved the output during the training run's leading rest, which was left
    # out as an unknown history; without those rows the temperature model validated at 0.80 um
    # against 0.0096 on the whole run, and nothing was significant. The channel explains the rest's
    # movement, so the rest is data (decision 0073)
    Regression(7736, ("temperature",), "cycling", "7736-temperature-moves-the-rest-pmpi"),
    # a velocity damping trained on one sine rate, with five steps slewed far faster than the loops:
    # rate-dependence was untestable ("one drive frequency at one amplitude") and nothing was
    # significant; the steps' pulses are a second rate (decision 0074): 1.92 -> 0.15 um
    Regression(7708, ("rate-dependence",), "velocity-damping", "7708-damping-seen-at-the-steps-pi1"),
    # a sensor delay of 1.45 samples under a PMPI base on an M-play rig: the delay's refit stopped in
    # a poorer eta optimum (training 0.0119 um) than the lag's (0.0058), and the lag ranked first; from
    # the lag's etas the delay trains at 0.0058 and validates at 0.0065 as the lag does (decision 0075)
    Regression(8277, ("delay",), "sensor", "8277-delay-on-the-lags-etas-pmpi"),
    # an even v^2 on a one-sided drive under pi1: a saturation (25 parameters) validated 6 % below v^2
    # (12); on 30 operators the two validate alike (0.0069 and 0.0070 um, the noise 0.0063), so the
    # lead was the base's resolution and the fewer parameters decide (decision 0076)
    Regression(8500, ("asymmetry",), "even-2", "8500-even-term-tied-on-the-finer-base-pi1"),
    # four play operators between pi's ten even thresholds, and an even v^2: pmpi (its etas move where
    # the operators turn) validated 2.02x below pi+asymmetry and the base was reported wrong; pi at 30
    # operators with the v^2 validates within 1.1x of pmpi, so the lead is resolution (decision 0077)
    Regression(7538, ("asymmetry",), "even-2", "7538-not-another-base-but-a-finer-one-pi"),
]

#: two hidden effects: the first significant candidate names hidden effects only
TWO_EFFECT = [
    # a resonance near the drive and a temperature ramp in the test run: dynamics explains 95 % of
    # training's rmse and 30 % of validation's, where the ramp's error stays; in mean square it removes
    # half as much there as in training, so the gains agree (decision 0030); delay, one parameter
    # fewer, validates within 5 % but trains 6.5x worse and does not take the lead by parsimony
    Regression(181, ("dynamics", "temperature"), None, "181-dynamics-near-drive-and-temperature-pi1"),
    # an even v^6 term and a sensor delay: asymmetry alone is significant (42 %), the pair with a
    # saturation partner gained more (53 %) and ranked first; a pair now ranks behind its member that
    # is significant alone (decision 0031)
    Regression(89, ("delay", "asymmetry"), None, "89-delay-and-asymmetry-even6-pi"),
    # an amplifier delay of 3 samples and a velocity damping that spikes at slewed steps: the damping
    # alone lands its spikes samples early, the delay alone cannot make them, so no single carries
    # over (the base 66x the noise floor); the delay is paired with every single and the joint search
    # starts from its whole samples (decision 0051): 98 % lower validation rmse
    Regression(2186, ("rate-dependence", "delay"), None, "2186-delay-and-velocity-damping-duhem-g"),
    # the same on a PI base, the damping learning 11 % of training alone: 86 % lower jointly
    Regression(2295, ("delay", "rate-dependence"), None, "2295-delay-and-velocity-damping-pi"),
    # a velocity damping at the test run's 5 steps and creep over decades: the damping validates 51 %
    # lower, all of it in 5 blocks, where sign flips cannot reach p < 1/32; on held-back training
    # blocks it does (p 1e-4), and both tests pass sqrt(P_MAX) (decision 0052)
    Regression(3076, ("rate-dependence", "creep"), None, "3076-velocity-damping-and-creep-pi"),
    # a temperature cycle and a frequency gain under a PMPI base: the temperature validates 12 % lower
    # at p 0.025 on 20 blocks, and p 1e-4 on held-back training blocks (decision 0052)
    Regression(2772, ("temperature", "rate-dependence"), None, "2772-temperature-cycling-and-frequency-gain-pmpi"),
    # a frequency gain and a 0.8-sample sensor delay under a PMPI base at 56 noise floors: the
    # frequency polynomials learned training (25 %) and not validation (2 %), so the usual rule paired
    # them with a creep (3 %), and no single carried over; the delay's pairs join the usual ones and
    # the two jointly validate 80 % lower (decision 0056)
    Regression(4084, ("rate-dependence", "delay"), None, "4084-frequency-gain-and-sensor-delay-pmpi"),
]

#: clean cases: nothing significant
CLEAN = [
    # a clean PI actuator with a drifting lab temperature recorded (23.4 -> 24.3 degC) that it does not
    # depend on: the channel was flagged (validation gain 18 %) while validation held only the run's end;
    # with sweeping runs split in interleaved blocks, nothing is flagged
    Regression(17, (), None, "17-clean-play-pi-irrelevant-temperature"),
    # a clean m-play rig under a PMPI base whose fit stops at a poor optimum: every refit's local search
    # moved the base's shape to a better one (training 0.995 -> 0.860) and saturation, then dynamics,
    # got the credit (51 %); judged against the base refitted from their shape, nothing is left
    # (diagnosis/base_polish.py, decision 0024)
    Regression(115, (), None, "115-clean-m-play-pmpi-base-at-a-poor-optimum"),
    # a clean play rig whose creep refit lowered validation 11.5 % (p 1e-4): the residual drifted along holds
    # by 0.25x its rms, but by 1.0x the noise's standard error on a drift, and creep's refit removed 5.5 % of
    # it; a drift within the noise is no drift (decision 0061)
    Regression(4949, (), None, "4949-clean-play-pi-drift-within-the-noise"),
]

#: the polynomial order where validation must extrapolate (decisions 0046, 0069): seed, form, the
#: asymmetry spec expected (tests/diagnosis/test_random_cases.py holds the full rule)
POLYNOMIAL_ORDER = [(2129, "even-2", "asymmetry(order=2)"), (2051, "even-4", "asymmetry"),
                    (6743, "even-4", "asymmetry")]

ALL = SINGLE + TWO_EFFECT + CLEAN


def seeds() -> list[int]:
    """Every regression seed, once, in the order above."""
    return list(dict.fromkeys(r.seed for r in ALL))
