"""When the two leading effects are re-judged on a finer base (:mod:`hilbench.diagnosis.resolution`,
decision 0060): the finer spec, and the conditions under which no refit is made at all. The check's
effect on whole diagnoses is asserted by randomized cases 4223 and 4711 (tests/diagnosis/test_random_cases.py)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from hilbench.diagnosis import thresholds as T
from hilbench.diagnosis.resolution import _tie_on_the_finer_base, check_resolution, finer_spec
from hilbench.diagnosis.verdict import Candidate

N = 2000


@pytest.mark.parametrize(("spec", "finer"), [
    ("pi", f"pi(n={10 * T.RESOLUTION_FACTOR})"),
    ("pi1+saturation(form=knee)+creep", f"pi1(n={10 * T.RESOLUTION_FACTOR})+saturation(form=knee)+creep"),
    ("mpi", f"mpi(n={10 * T.RESOLUTION_FACTOR})"),
    ("pd(n_dead_zone=2)+delay", f"pd(n={10 * T.RESOLUTION_FACTOR},n_dead_zone=2)+delay"),
    ("pi(n=16)+asymmetry", None),  # the user chose the resolution
    ("pmpi+delay", f"pmpi(n={10 * T.PMPI_RESOLUTION_FACTOR})+delay"),  # one searched eta per operator: 2x
    ("pmpi(n=12)+dynamics", None),
    ("duhem-d", None),
    ("linear", None),
])
def test_finer_spec(spec: str, finer: str | None) -> None:
    assert finer_spec(spec) == finer


def _candidate(effect: str, validation_rmse: float, train_rmse: float, band: float = 1.0,
               fast_error: bool = False) -> Candidate:
    rng = np.random.default_rng(len(effect))
    e = rng.normal(0.0, 1.0, N)
    e *= validation_rmse / np.sqrt(np.mean(e**2))
    run = SimpleNamespace(key="test", simulated=e, data=SimpleNamespace(output=np.zeros(N)),
                          validation=np.ones(N, dtype=bool))
    fitted = SimpleNamespace(spec=f"pi+{effect}", runs=[run], metrics={"train": {"rmse": train_rmse}})
    evidence: dict = {"noise_band": band}
    if fast_error:
        evidence["ranked_by_fast_error"] = {"over": "dynamics"}
    return Candidate(effect=effect, spec=f"pi+{effect}", significant=True, expected_gain=0.5,
                     explanation=f"{effect} helps", evidence=evidence, fitted=fitted)  # type: ignore[arg-type]


class _NoFits:
    """Stands for the dataset: any refit would read ``runs`` or be called, and fail the test."""

    @property
    def runs(self):  # pragma: no cover - reached only when the check wrongly refits
        raise AssertionError("the check refitted where it should not")


BASE = SimpleNamespace(spec="pi")


@pytest.mark.parametrize(("leader", "rival", "base"), [
    # the leader's refit trains within the noise band: nothing structured left for the resolution
    (_candidate("saturation", 1.0, train_rmse=0.9), _candidate("asymmetry", 1.1, train_rmse=1.5), BASE),
    # the rival's mean square is more than TIE_MEAN_SQUARE_RATIO x the leader's: a decisive lead
    (_candidate("saturation", 1.0, train_rmse=3.0), _candidate("asymmetry", 1.5, train_rmse=3.0), BASE),
    # a base whose resolution the check does not change
    (_candidate("dynamics", 1.0, train_rmse=3.0), _candidate("delay", 1.1, train_rmse=3.0), SimpleNamespace(spec="duhem-d")),
    # on pmpi only a delay and a lag are checked whatever their margins, not other close leaders
    (_candidate("saturation", 1.0, train_rmse=3.0), _candidate("creep", 1.1, train_rmse=3.0), SimpleNamespace(spec="pmpi")),
    # a delay the fast error put first on pmpi (decision 0066): the finer base does not overrule it
    (_candidate("delay", 1.0, train_rmse=3.0, fast_error=True), _candidate("dynamics", 0.8, train_rmse=3.0),
     SimpleNamespace(spec="pmpi")),
    # a pmpi base whose n the user set
    (_candidate("dynamics", 1.0, train_rmse=0.9), _candidate("delay", 3.0, train_rmse=0.9), SimpleNamespace(spec="pmpi(n=10)")),
])
def test_no_refit_when_the_resolution_cannot_matter(leader, rival, base) -> None:
    cands = [leader, rival]
    check_resolution(_NoFits(), base, cands, noise=0.5, kw={})  # type: ignore[arg-type]
    assert cands == [leader, rival]
    assert "resolution_check" not in leader.evidence and "ranked_by_resolution" not in rival.evidence


def test_no_refit_without_a_significant_single_rival() -> None:
    leader = _candidate("saturation", 1.0, train_rmse=3.0)
    pair = _candidate("asymmetry+creep", 1.05, train_rmse=3.0)
    pair.evidence["pair"] = ["asymmetry", "creep"]
    weak = _candidate("asymmetry", 1.1, train_rmse=3.0)
    weak.significant = False
    cands = [leader, pair, weak]
    check_resolution(_NoFits(), BASE, cands, noise=0.5, kw={})  # type: ignore[arg-type]
    assert cands == [leader, pair, weak]


def test_the_finer_base_reorders_a_lead_owed_to_the_resolution(tmp_path) -> None:
    """Randomized case 4223: an even v^6 on a play rig whose heaviest operators sit between two of the
    base's ten thresholds. Saturation leads at 10 operators (validation 0.227 against 0.247 um); both
    refitted on 30, the even term validates far lower (0.112 against 0.176 um) and goes first, the
    record naming the specs and the four validation errors (decision 0060). Case 4711 (an even v^4)
    showed it until the suite pinned numpy's and OpenBLAS's kernels (tests/conftest.py): on the pinned
    kernels asymmetry leads 4711 on ten operators already, and the check only confirms it."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
    import diagnosis_cases as DC

    from hilbench.diagnosis.diagnose import diagnose

    case = DC.draw_case(4223)
    assert case.hidden == ["asymmetry"] and case.forms["asymmetry"] == "even-6"
    paths, kw = DC.write_case(case, tmp_path)
    d = diagnose(paths, case.spec, **kw)
    first = d.effects[0]
    assert first.effect == "asymmetry" and first.significant
    record = first.evidence["ranked_by_resolution"]
    assert record["over"] == "saturation"
    assert all(s.startswith(f"pi(n={10 * T.RESOLUTION_FACTOR})+") for s in record["specs"])
    coarse, fine = record["validation_rmse"], record["finer_validation_rmse"]
    assert coarse["saturation"] < coarse["asymmetry"]  # the lead the coarse base gave
    assert fine["asymmetry"] < (1.0 - T.MIN_GAIN) * fine["saturation"]
    assert record["training_rmse"] > record["noise_band"]
    assert "base's resolution" in first.explanation


def test_a_finer_base_past_the_memory_limit_leaves_the_order_and_says_so(tmp_path) -> None:
    """The finer base has 3x the columns: where its fit would pass the memory limit the check is
    skipped, the reason recorded, and the diagnosis goes on (not an error for the user)."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
    import diagnosis_cases as DC

    from hilbench.identify.dataset import as_dataset
    from hilbench.models.spec import set_memory_limit

    paths, kw = DC.write_case(DC.draw_case(4711), tmp_path)
    leader = _candidate("saturation", 1.0, train_rmse=3.0)
    rival = _candidate("asymmetry", 1.1, train_rmse=3.0)
    cands = [leader, rival]
    set_memory_limit("1KB")
    try:
        check_resolution(as_dataset(paths), BASE, cands, noise=0.5, kw=kw)  # type: ignore[arg-type]
    finally:
        set_memory_limit(None)
    assert cands == [leader, rival]
    record = leader.evidence["resolution_check"]
    assert record["over"] == "asymmetry" and "memory" in record["skipped"] and "pi(n=30)" in record["skipped"]


def test_a_delay_behind_a_lag_on_pmpi_is_checked_on_a_finer_base_whatever_the_margins(tmp_path) -> None:
    """Randomized case 5744: a 1 ms amplifier delay on an M-play rig under ``pmpi``. On ten operators the
    lag trains at the noise and validates far below the delay (the M-play etas and the lag share the
    reversals' mismatch), so neither the training condition nor the tie would let the check run. On
    twenty operators the delay validates below the lag (decision 0068)."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
    import diagnosis_cases as DC

    from hilbench.identify.dataset import as_dataset
    from hilbench.identify.fitting import fit

    case = DC.draw_case(5744)
    paths, kw = DC.write_case(case, tmp_path)
    data = as_dataset(paths)
    base = fit(data, "pmpi", **kw)
    noise = case.noise_std_um
    lag = _candidate("dynamics", 0.023, train_rmse=noise)
    delay = _candidate("delay", 0.060, train_rmse=2.3 * noise)
    cands = [lag, delay]
    check_resolution(data, base, cands, noise=noise, kw=kw)
    # the check runs whatever the margins, and on the finer base the delay validates below the lag.
    # Whether that reorders the two depends on the gain margin: since the damping search reaches the
    # lightest damping the record resolves (decision 0105) the lag validates 0.0154 against the
    # delay's 0.0140 um there, 9 % apart, under the 10 % a reorder needs; the whole diagnosis ranks
    # the delay first on this case all the same (benchmarks/diagnosis_regressions.py keeps it)
    record = (delay.evidence.get("ranked_by_resolution") or lag.evidence.get("resolution_check"))
    assert record is not None and record["trigger"] == "a delay and a lag on an eta base"
    assert record["finer_validation_rmse"]["delay"] < record["finer_validation_rmse"]["dynamics"]
    if cands[0] is delay:
        assert delay.evidence["ranked_by_resolution"]["over"] == "dynamics"
        assert "base's resolution" in delay.explanation
    assert all(s.startswith(f"pmpi(n={10 * T.PMPI_RESOLUTION_FACTOR})+") for s in record["specs"])


def test_a_finer_base_that_only_worsens_the_leader_does_not_reorder(tmp_path) -> None:
    """Randomized case 7178: a sensor delay and an output knee hidden on a bipolar play rig under
    ``pi``. With the delay unmodelled both leaders train at nine times the noise; on thirty operators
    the saturation validates 30 % worse than on ten and a cubic asymmetry validates below it, but not
    below the saturation's showing on the user's base. The saturation, whose odd pattern the residual
    shows, stays first (decision 0070); before, the asymmetry went first."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
    import diagnosis_cases as DC

    from hilbench.diagnosis.diagnose import diagnose

    case = DC.draw_case(7178)
    assert case.hidden == ["delay", "saturation"] and case.spec == "pi"
    paths, kw = DC.write_case(case, tmp_path)
    d = diagnose(paths, case.spec, **kw)
    first = d.effects[0]
    assert first.effect == "saturation" and first.significant, [(c.effect, c.significant) for c in d.effects]
    record = first.evidence["resolution_check"]
    fine, coarse = record["finer_validation_rmse"], record["validation_rmse"]
    assert record["over"] == "asymmetry"
    # the finer base made the leader worse, and the rival beat only that worse showing
    assert fine["saturation"] > coarse["saturation"]
    assert fine["asymmetry"] < (1.0 - T.MIN_GAIN) * fine["saturation"]
    assert not fine["asymmetry"] < (1.0 - T.MIN_GAIN) * coarse["saturation"]


def _tied(effect: str, n_weights: int, signature: float, train_rmse: float = 1.0) -> Candidate:
    """A candidate for the finer-base tie rule: its weights, its residual pattern on a one-sided
    drive (parity overlap 0.97, where even and odd patterns cannot decide) and its training rmse."""
    c = _candidate(effect, 1.0, train_rmse=train_rmse)
    c.fitted.model = SimpleNamespace(weights=np.zeros(n_weights), shape_params=lambda: [])
    c.evidence.update(signature=signature, parity_overlap=0.97)
    return c


def test_a_tie_on_the_finer_base_goes_to_the_fewer_parameters() -> None:
    """Decision 0076 (randomized seed 8500): a saturation of 25 parameters led an even term of 12 by
    6 % on the user's base, and on the finer base the two validate within 1.2 %: the lead was the
    resolution, and parsimony decides. Not when the rival is PARSIMONY_MARGIN worse there, nor when
    the leader trains PARSIMONY_TRAINING_RATIO times better."""
    leader, rival = _tied("saturation", 24, 0.88), _tied("asymmetry", 12, 0.88)
    assert _tie_on_the_finer_base(leader, rival, 0.00694, 0.00702) == "parsimony"
    assert _tie_on_the_finer_base(leader, rival, 0.00694, 0.00694 * (1.0 + 2 * T.PARSIMONY_MARGIN)) is None
    assert _tie_on_the_finer_base(rival, leader, 0.00694, 0.00702) is None  # the richer one is no tie-winner
    far_better = _tied("saturation", 24, 0.88, train_rmse=1.0 / (T.PARSIMONY_TRAINING_RATIO + 0.1))
    assert _tie_on_the_finer_base(far_better, rival, 0.00694, 0.00702) is None


def test_a_tie_on_the_finer_base_goes_first_to_the_pattern_where_the_drive_tells() -> None:
    leader, rival = _tied("asymmetry", 12, 0.30), _tied("saturation", 24, 0.90)
    for c in (leader, rival):
        c.evidence["parity_overlap"] = 0.05  # a bipolar drive: even and odd patterns are apart
    assert _tie_on_the_finer_base(leader, rival, 1.0, 1.02) == "signature"
    assert _tie_on_the_finer_base(rival, leader, 1.0, 1.02) is None  # the leader's pattern decides for it
