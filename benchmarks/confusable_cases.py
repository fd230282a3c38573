"""Cases of the two confusable pairs of issue 62, drawn per seed like ``diagnosis_cases.draw_case``.

    from confusable_cases import draw_confusable, CONFUSABLE
    case = draw_confusable(3, "saturation-asymmetry")    # an output knee on a play (Preisach-like) base
    paths, kwargs = diagnosis_cases.write_case(case, folder)

Each kind fixes the hidden effect, its form, the base families and the drive's segment kinds;
everything else (strength, base, program, split, sensor) is drawn as ``draw_case`` draws it, from a
stream of its own (seed n here is not case n there, nor seed n of another kind):

* ``saturation-asymmetry``: a soft saturation of the output with the algebraic knee
  ``s(z) = z / (1 + |z|^p)^(1/p)`` (not the plant's tanh) on a bipolar play base (``pi``). The issue's
  miss: asymmetry ranked first, ``--auto`` removing 1.6-2.3x where saturation would remove more.
* ``saturation-asymmetry-preisach``: the same knee on a Preisach base (the widened suite's relay
  grid, start ``pi``), which flattens by itself once the drive sweeps its relays: the issue's cases
  were on a Preisach-like base.
* ``asymmetry-under-saturation-drive``: the partner, an even polynomial hidden on the same bases and
  drives, so that what tells the pair apart is checked in both directions.
* ``rate-delay``: velocity damping (loop widening growing with the input rate) under multi-tone
  drives only. The issue's miss: ranked as a delay, ``--auto`` ending at 2.1-2.2x.
* ``delay-multitone``: the partner, a delay (amplifier or sensor) under the same drives.
"""

from __future__ import annotations

import diagnosis_cases as DC
import numpy as np

#: kind -> (hidden effects, fixed forms, base families, segment kinds or None for draw_case's mix)
CONFUSABLE: dict[str, tuple[list[str], dict[str, str], tuple[str, ...], tuple[str, ...] | None]] = {
    "saturation-asymmetry": (["saturation"], {"saturation": "output-knee"}, ("play",), None),
    "saturation-asymmetry-preisach": (["saturation"], {"saturation": "output-knee"}, ("preisach",), None),
    "asymmetry-under-saturation-drive": (["asymmetry"], {}, ("play",), None),
    "rate-delay": (["rate-dependence"], {"rate-dependence": "velocity-damping"}, DC.FAMILIES, ("multitone",)),
    "delay-multitone": (["delay"], {}, DC.FAMILIES, ("multitone",)),
}


def draw_confusable(seed: int, kind: str) -> DC.Case:
    """A case of :data:`CONFUSABLE` ``kind`` from its seed (module docstring)."""
    if kind not in CONFUSABLE:
        raise ValueError(f"confusable kind: {kind!r}, expected one of {', '.join(CONFUSABLE)}")
    hidden, forms, families, segments = CONFUSABLE[kind]
    rng = np.random.default_rng([20240611, 62, 2, sorted(CONFUSABLE).index(kind), seed])
    suite = "widened" if set(families) - set(DC.FAMILIES) else "classic"  # a base only the widened suite has
    return DC._draw(rng, seed, list(hidden), dict(forms), suite, families=families, segments=segments)


if __name__ == "__main__":  # a quick look at some draws
    import sys

    kind = sys.argv[1] if len(sys.argv) > 1 else "saturation-asymmetry"
    for s in range(int(sys.argv[2]) if len(sys.argv) > 2 else 10):
        c = draw_confusable(s, kind)
        print(s, c.label, c.family, c.spec, c.sample_rate_hz, len(c.runs), c.samples(),
              {k: round(v, 1) for k, v in c.snr.items()}, c.strength)
