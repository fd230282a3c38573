"""Every Python package of the source tree is installed by pyproject.toml."""

from __future__ import annotations

import sys
from pathlib import Path

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

ROOT = Path(__file__).resolve().parents[1]


def test_all_packages_are_declared():
    declared = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    found = set()
    for top in ("hilbench", "drivers"):
        for init in (ROOT / top).rglob("__init__.py"):
            if "__pycache__" not in init.parts:
                found.add(".".join(init.parent.relative_to(ROOT).parts))
    found.add("hilbench.configs")  # configs/ is mapped onto this package
    found.add("hilbench.plans")  # experiments/plans/ too
    assert found <= declared, f"not installed: {sorted(found - declared)}"
