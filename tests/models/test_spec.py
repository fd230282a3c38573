"""Spec validation: every option typed and bounded; sizes bounded by the estimated memory of a fit."""

from __future__ import annotations

import pytest

from hilbench.models.model import Model
from hilbench.models.spec import SpecError, check_fit_memory, fit_memory, parse_size, regressor_size, set_memory_limit


@pytest.mark.parametrize("spec, named", [
    ("pi(n=2.5)", "2.5"), ("pi(n=abc)", "abc"), ("pi(n=0)", "n=0"), ("pi+delay(seconds=-1)", "seconds=-1"),
    ("pi+delay(seconds=nan)", "nan"), ("pi+creep(form=sideways)", "sideways"), ("pi+asymmetry(order=9)", "order=9"),
    ("pi(m=3)", "'m'"), ("pi(n=1,n=2)", "'n'"), ("pi(n=16", "pi(n=16"), ("pj", "'pj'"),
])
def test_bad_specs_are_refused_naming_the_value(spec, named):
    with pytest.raises(SpecError) as exc:
        Model(spec)
    assert named in exc.value.line() and "\n" not in exc.value.line()


def test_valid_specs_keep_their_canonical_form():
    assert Model("pi(n=16)+creep").spec == "pi(n=16)+creep"
    assert Model("pi+dynamics(natural_frequency_hz=3200,zeta=0.28)").spec == \
        "pi+dynamics(natural_frequency_hz=3200,zeta=0.28)"


def test_columns_counted_as_the_components_build_them():
    m = Model("pi(n=16)+asymmetry+creep(n=2)")
    assert regressor_size(m.base, m.effects) == (1 + 16 + 3 + 2, 2)
    m = Model("pmpi(n=10)")
    assert regressor_size(m.base, m.effects) == (1 + 10 + 2, 9)


def test_memory_grows_with_the_square_of_the_operators_and_refuses_beyond_the_limit():
    small, big = Model("pi(n=16)"), Model("pi(n=100000)")
    assert fit_memory(small.base, small.effects, 10_000, 7_000) < 50e6
    assert fit_memory(big.base, big.effects, 10_000, 7_000) > 3 * 8 * 1e10  # the normal equations alone
    set_memory_limit("1GB")
    try:
        with pytest.raises(SpecError) as exc:
            check_fit_memory(big.base, big.effects, 10_000, 7_000, big.spec)
        assert "limit of 1 GB" in exc.value.line() and "GB of memory" in exc.value.line()
        assert check_fit_memory(small.base, small.effects, 10_000, 7_000, small.spec) > 0
    finally:
        set_memory_limit(None)


@pytest.mark.parametrize("text, n", [("4GB", 4 * 1024**3), ("512MiB", 512 * 1024**2), ("2e9", 2_000_000_000),
                                     ("1.5 KB", 1536)])
def test_sizes(text, n):
    assert parse_size(text) == n
