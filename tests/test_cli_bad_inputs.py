"""Generated bad inputs through the command line: every one is refused the same way.

Hypothesis generates malformed and out-of-range model specs, impossible sizes, rig configs with
wrong, missing and misspelled keys, broken plans, CSV and MAT files, bad --map expressions and
unknown run names, and feeds each through the real entry point (:func:`hilbench.cli.app.run`, the
function behind the ``hilbench`` script: argument parsing, the commands, the error handling). For
every input it asserts exit status 2, exactly one line on stderr that starts with ``error:`` and
names the offending value, no traceback, with --json one JSON document ``{"error", "hint", "exit"}``
on stdout (without it nothing on stdout), no file left half-written, and every recording in the
folder closed with a final status. A few inputs also go through a real ``hilbench`` process.

At least 500 generated inputs run in all (see ``test_zz_counted_at_least_500``).
"""

from __future__ import annotations

import io
import itertools
import json
import os
import string
import subprocess
import sys
from contextlib import redirect_stderr, redirect_stdout
from pathlib import Path

import h5py
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from hilbench.cli.app import run
from hilbench.models.bases import BASES
from hilbench.models.effect_components import EFFECTS
from hilbench.models.spec import as_option
from tests.conftest import MINIMAL_RIG

COUNT = {"n": 0}
#: the generated tests, each of which must refuse at least MIN_REFUSED inputs itself: the count is
#: checked per test, so it holds whichever test worker runs each (a module-wide count does not)
GENERATED = ("test_bad_model_specs", "test_bad_rig_configs", "test_bad_plans", "test_bad_data_files",
             "test_unknown_run_names")
MIN_REFUSED = 100
SETTINGS = settings(max_examples=110, deadline=None, derandomize=True,
                    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
_names = itertools.count()


@pytest.fixture(scope="module")
def folder(tmp_path_factory) -> Path:
    """A work folder with a small recording (2 runs) to fit and import into."""
    work = tmp_path_factory.mktemp("bad-inputs")
    status, out, err = invoke(["sweep", "gmm-issf-duhem", "-e", "sine:amplitude=1|2,frequency_hz=2,cycles=2",
                               "-o", str(work / "rec.h5"), "-q", "--json"])
    assert status == 0, err
    return work


def invoke(argv: list[str]) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with redirect_stdout(out), redirect_stderr(err):
        status = run(argv)
    return status, out.getvalue(), err.getvalue()


def _recordings_state(work: Path) -> dict[str, list[tuple[str, str]]]:
    state = {}
    for h5 in sorted(work.glob("*.h5")):
        with h5py.File(h5, "r", swmr=True) as f:
            state[h5.name] = [(name, str(g.attrs.get("status"))) for name, g in f["runs"].items()]
    return state


def refused(work: Path, argv: list[str], offending: str, as_json: bool) -> str:
    """Run ``argv`` and assert the refusal contract; returns the error line."""
    COUNT["n"] += 1
    before = {p.name for p in work.iterdir()}
    recordings = _recordings_state(work)
    status, out, err = invoke([*argv, "--json"] if as_json else argv)
    lines = err.splitlines()
    assert status == 2, (argv, status, err)
    assert "Traceback" not in err and "Traceback" not in out, err
    assert len(lines) == 1 and lines[0].startswith("error: "), (argv, lines)
    assert offending in lines[0], (argv, offending, lines[0])
    if as_json:
        document = json.loads(out)  # exactly one JSON document
        assert set(document) == {"error", "hint", "exit"} and document["exit"] == 2, document
        assert offending in document["error"] or offending in (document["hint"] or "")
    else:
        assert out == "", out
    # no file left behind (half-written or temporary), recordings unchanged and closed with a status
    assert {p.name for p in work.iterdir()} == before, argv
    after = _recordings_state(work)
    assert after == recordings
    assert all(s in ("complete", "aborted", "failed") for runs in after.values() for _, s in runs)
    return lines[0]


# -- model specs --------------------------------------------------------------------------------------

COMPONENTS = {**BASES, **EFFECTS}
identifiers = st.text(string.ascii_lowercase + "_", min_size=1, max_size=10)


def _bad_values(option) -> st.SearchStrategy[str]:
    text = st.sampled_from(["abc", "x1", "true", "1e", "n", "--", "ten"])
    if option.kind == "choice":
        return identifiers.filter(lambda v: v not in option.choices)
    if option.kind == "text":
        return st.nothing()
    bad = [text, st.sampled_from(["nan", "inf", "-inf"])]
    if option.kind == "int":
        # filtered after formatting: 0.9999 prints as "1", a valid integer
        bad.append(st.floats(0.1, 99.9).map(lambda v: f"{v:.3g}").filter(lambda t: float(t) != int(float(t))))
    if option.minimum is not None:
        low = option.minimum
        bad.append(st.floats(low - 1e6, low - 1e-3).map(lambda v: f"{v:.6g}").filter(lambda t: float(t) < low))
        if option.exclusive_minimum or option.kind == "int":
            bad.append(st.just(f"{low:g}" if option.exclusive_minimum else str(int(low) - 1)))
    if option.maximum is not None:
        high = option.maximum
        bad.append(st.floats(high + 1, high * 100 + 1e3).map(lambda v: str(int(v)) if option.kind == "int" else f"{v:.6g}"))
    return st.one_of(bad)


@st.composite
def bad_option_value(draw) -> tuple[str, str]:
    name = draw(st.sampled_from([n for n, c in COMPONENTS.items() if c.options_schema]))
    schema = COMPONENTS[name].options_schema
    key = draw(st.sampled_from(sorted(k for k in schema if as_option(schema[k]).kind != "text")))
    value = draw(_bad_values(as_option(schema[key])))
    part = f"{name}({key}={value})"
    spec = part if name in BASES else f"pi+{part}"
    return spec, value


@st.composite
def bad_spec(draw) -> tuple[str, str]:
    """(spec, the text the error must name)."""
    kind = draw(st.sampled_from(["value", "value", "key", "base", "syntax"]))
    if kind == "value":
        return draw(bad_option_value())
    if kind == "key":
        name = draw(st.sampled_from(sorted(COMPONENTS)))
        key = draw(identifiers.filter(lambda k: k not in COMPONENTS[name].options_schema))
        part = f"{name}({key}=1)"
        return (part if name in BASES else f"pi+{part}"), key
    if kind == "base":
        base = draw(identifiers.filter(lambda b: b not in COMPONENTS))
        return f"{base}+creep", base
    spec = draw(st.sampled_from(["pi(n=16", "pi(n=16))", "pi+", "+pi", "pi(n)", "pi(=3)", "pi+pi", "pi+creep+creep",
                                 "pi(n=1,n=2)", "pi((n=1))", "pi)(", "linear+hysteresis", "creep", "pi(n=)",
                                 "pi+delay(seconds=)", "pi(,)", "pi n=3", "pi;creep"]))
    return spec, spec


@SETTINGS
@given(case=bad_spec(), as_json=st.booleans(), command=st.sampled_from(["fit", "diagnose"]))
def test_bad_model_specs(folder, case, as_json, command):
    spec, offending = case
    refused(folder, [command, str(folder / "rec.h5"), "--model", spec, "-q"], offending, as_json)


@settings(max_examples=40, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(n=st.integers(50_000, 10**12), base=st.sampled_from(["pi", "pi1", "mpi", "pmpi", "pd", "fpmpi", "duhem-d"]),
       as_json=st.booleans())
def test_impossible_sizes_are_refused_with_the_estimate(folder, n, base, as_json):
    line = refused(folder, ["fit", str(folder / "rec.h5"), "--model", f"{base}(n={n})", "-q"], f"n={n}", as_json)
    assert "would need about" in line and "more than the limit of" in line


def test_memory_limit_is_configurable(folder):
    # pi(n=400) on this recording needs a few tens of MB: refused under a 1 MB limit, fitted under the default
    line = refused(folder, ["--memory-limit", "1MB", "fit", str(folder / "rec.h5"), "--model", "pi(n=400)", "-q"],
                   "pi(n=400)", False)
    assert "limit of 1 MB" in line
    status, _, err = invoke(["fit", str(folder / "rec.h5"), "--model", "pi(n=20)", "-q"])
    assert status == 0, err


# -- rig configs -----------------------------------------------------------------------------------------

RIG_KEYS = {"rig": ["name", "sample_rate_hz", "seed"], "actuator": ["driver", "unit", "min", "max", "max_rate", "rest"]}
REQUIRED = {"rig": ["name", "sample_rate_hz"], "actuator": ["unit", "min", "max", "max_rate"]}
ALL_KEYS = {"rig", "actuator", "sensors", "plant", "plan", "devices", "extends", "name", "description", "paper",
            "follows", "choices", "sample_rate_hz", "realtime", "seed", "driver", "device", "kind", "unit", "min",
            "max", "max_rate", "rest", "url", "channel", "source", "scale", "offset", "noise_std", "quantization",
            "range", "out_of_range"}


def _misspell(draw, key: str) -> str:
    i = draw(st.integers(0, len(key) - 1))
    op = draw(st.sampled_from(["drop", "swap", "add"]))
    if op == "drop":
        word = key[:i] + key[i + 1:]
    elif op == "swap" and i + 1 < len(key):
        word = key[:i] + key[i + 1] + key[i] + key[i + 2:]
    else:
        word = key[:i] + draw(st.sampled_from("xqz")) + key[i:]
    return word


@st.composite
def bad_config(draw) -> tuple[str, str]:
    """(config text, the text the error must name)."""
    table = draw(st.sampled_from(sorted(RIG_KEYS)))
    key = draw(st.sampled_from(RIG_KEYS[table]))
    lines = MINIMAL_RIG.splitlines()
    header = lines.index(f"[{table}]")
    end = next(i for i in range(header + 1, len(lines)) if not lines[i].strip())
    at = next((i for i in range(header, end) if lines[i].startswith(f"{key} =")), None)
    kind = draw(st.sampled_from(["misspell", "missing", "type", "range", "top"]))
    if kind == "top":
        word = draw(identifiers.filter(lambda w: w not in ALL_KEYS))
        return f"{word} = 1\n" + MINIMAL_RIG, word
    if at is None:  # key absent from the minimal rig (seed, driver...): add it with a wrong type
        lines.insert(header + 1, f'{key} = [1, "x"]')
        return "\n".join(lines), key
    if kind == "misspell":
        word = _misspell(draw, key)
        if word in ALL_KEYS or word == key or not word:
            word = key + "x"
        lines[at] = lines[at].replace(key, word, 1)
        return "\n".join(lines), word
    if kind == "missing" and key in REQUIRED[table]:
        del lines[at]
        return "\n".join(lines), key
    if kind == "range" and key in ("sample_rate_hz", "max_rate"):
        lines[at] = f"{key} = {draw(st.sampled_from(['0.0', '-1.0', '-1e9']))}"
        return "\n".join(lines), key
    value = draw(st.sampled_from(['"fast"', "true", "[1, 2]", "{ a = 1 }"] if key != "name" and key != "unit"
                                 else ["1", "true", "[1, 2]"]))
    lines[at] = f"{key} = {value}"
    return "\n".join(lines), key


@SETTINGS
@given(case=bad_config(), as_json=st.booleans(), check=st.booleans())
def test_bad_rig_configs(folder, case, as_json, check):
    text, offending = case
    path = folder / f"rig-{next(_names)}.toml"
    path.write_text(text, encoding="utf-8")
    try:
        argv = ["sweep", str(path), "-o", str(folder / "new.h5"), "-q"] + (["--check"] if check else [])
        refused(folder, argv, offending, as_json)
    finally:
        path.unlink()


# -- plans ------------------------------------------------------------------------------------------------


@st.composite
def bad_plan(draw) -> tuple[str | None, str, str]:
    """(plan file text or None for a name, --plan argument, the text the error must name)."""
    kind = draw(st.sampled_from(["name", "kind", "key", "value"]))
    if kind == "name":
        name = draw(st.text(string.ascii_lowercase + string.digits + "-", min_size=1, max_size=12)
                    .filter(lambda n: not n.startswith("-") and n not in ("0", "00", "000", "001", "002", "004")
                            and not any(n in p for p in ("000-rate", "001-char", "002-linear", "002-valid", "004-tra"))))
        return None, name, name
    if kind == "kind":
        word = draw(identifiers.filter(lambda w: w not in ("sine", "triangle", "noise", "step", "chirp", "multitone")))
        return f'[[runs]]\nkind = "{word}"\namplitude = 1.0\n', "", word
    if kind == "key":
        word = draw(identifiers.filter(lambda w: w not in ("amplitude", "frequency_hz", "offset", "phase_deg",
                                                            "cycles", "duration_s", "label", "sweep", "kind")))
        return f'[[runs]]\nkind = "sine"\namplitude = 1.0\nfrequency_hz = 1.0\ncycles = 1\n{word} = 2\n', "", word
    value = draw(st.sampled_from(["-1.0", '"fast"', "0.0", "[1, 2]"]))
    return f'[[runs]]\nkind = "sine"\namplitude = 1.0\nfrequency_hz = {value}\ncycles = 1\n', "", "frequency_hz"


@SETTINGS
@given(case=bad_plan(), as_json=st.booleans())
def test_bad_plans(folder, case, as_json):
    text, name, offending = case
    path = None
    if text is not None:
        path = folder / f"plan-{next(_names)}.toml"
        path.write_text(text, encoding="utf-8")
        name = str(path)
    try:
        refused(folder, ["sweep", "gmm-issf-duhem", "--plan", name, "-o", str(folder / "new.h5"), "-q"], offending,
                as_json)
    finally:
        if path is not None:
            path.unlink()


# -- data files, --map expressions, run names ----------------------------------------------------------------


def _csv_rows(n: int) -> list[str]:
    return [f"{k / 100:.2f},{np.sin(k / 5):.4f},{np.cos(k / 5):.4f}" for k in range(n)]


@st.composite
def bad_source(draw) -> tuple[str, bytes, list[str], str]:
    """(file name, content, extra arguments, the text the error must name)."""
    kind = draw(st.sampled_from(["cell", "ragged", "time", "empty", "mat", "map", "unitless", "run"]))
    rows = _csv_rows(draw(st.integers(3, 30)))
    header = "time[s],input[V],output[µm]"
    if kind == "cell":
        bad = draw(st.sampled_from(["abc", "2.3.4", "--", "x", "nan", "inf", "1e999", "1..2"]))
        i = draw(st.integers(0, len(rows) - 1))
        cells = rows[i].split(",")
        cells[draw(st.integers(1, 2))] = bad
        rows[i] = ",".join(cells)
        return "d.csv", "\n".join([header, *rows]).encode(), [], f"line {i + 2}"
    if kind == "ragged":
        i = draw(st.integers(0, len(rows) - 1))
        rows[i] += ",9"
        return "d.csv", "\n".join([header, *rows]).encode(), [], f"line {i + 2}"
    if kind == "time":
        i = draw(st.integers(1, len(rows) - 1))
        rows[i] = rows[i - 1]
        return "d.csv", "\n".join([header, *rows]).encode(), [], "increasing"
    if kind == "empty":
        content = draw(st.sampled_from([b"", b"\n\n", b"# only a comment\n", header.encode() + b"\n"]))
        return "e.csv", content, [], "e.csv"
    if kind == "mat":
        content = draw(st.binary(min_size=0, max_size=300))
        return "m.mat", content, [], "m.mat"
    if kind == "map":
        expr = draw(st.sampled_from(["=", "x", "1=", "=output", "1=out put", "1=output[", "1=output[]", "1=[um]",
                                     "9=output[um]", "zz=input[V]", "1=output[um]=2"]))
        return "d.csv", "\n".join(["a,b,c", *rows]).encode(), ["--map", expr], expr
    if kind == "unitless":
        return ("d.csv", "\n".join(["t,u,y", *rows]).encode(),
                ["--map", "t=time[s]", "--map", "u=input[V]", "--map", "y=output"], "y=output")
    name = draw(st.sampled_from(["a/b", "", " ", "x" * 101, "run\n2", "../up", "a\\b"]))
    return "d.csv", "\n".join([header, *rows]).encode(), ["--run", name], "run name" if name.strip() else "empty run name"


@SETTINGS
@given(case=bad_source(), as_json=st.booleans(), existing=st.booleans())
def test_bad_data_files(folder, case, as_json, existing):
    name, content, extra, offending = case
    source = folder / f"src-{next(_names)}-{name}"
    source.write_bytes(content)
    offending = offending.replace(name, source.name) if offending == name else offending
    try:
        target = folder / ("rec.h5" if existing else "new.h5")  # append to a recording, or create one
        refused(folder, ["import", str(source), "-o", str(target), "-q", *extra], offending, as_json)
    finally:
        source.unlink()


@SETTINGS
@given(name=st.text(string.ascii_letters + string.digits + "-_:", min_size=1, max_size=12)
       .filter(lambda n: n not in ("1", "2") and "sine" not in n and not n.startswith("-")),
       option=st.sampled_from(["--train", "--test"]), as_json=st.booleans(), command=st.sampled_from(["fit", "plot"]))
def test_unknown_run_names(folder, name, option, as_json, command):
    if command == "plot":
        argv = ["plot", str(folder / "rec.h5"), "--run", name, "-o", str(folder / "p.png")]
    else:
        argv = ["fit", str(folder / "rec.h5"), "--model", "pi(n=4)", option, name, "-q"]
    refused(folder, argv, name, as_json)


@pytest.fixture(autouse=True)
def _each_generated_test_refuses_its_inputs(request):
    before = COUNT["n"]
    yield
    if request.node.name in GENERATED:
        assert COUNT["n"] - before >= MIN_REFUSED, (request.node.name, COUNT["n"] - before)


def test_zz_counted_at_least_500():
    """At least 500 generated inputs run in all: each generated test refuses MIN_REFUSED or more
    (checked as it ends, in whichever process runs it; 110 each today)."""
    assert all(callable(globals().get(name)) for name in GENERATED)
    assert len(GENERATED) * MIN_REFUSED >= 500


# -- the same through a real process ---------------------------------------------------------------------


@pytest.mark.parametrize("argv, offending", [
    (["fit", "{rec}", "--model", "pi(n=abc)"], "n=abc"),
    (["fit", "{rec}", "--model", "pi(n=2.5)"], "2.5"),
    (["fit", "{rec}", "--model", "pi+delay(seconds=-1)"], "seconds=-1"),
    (["fit", "{rec}", "--model", "pi(n=100000)", "-q"], "pi(n=100000)"),
    (["fit", "{rec}", "--bogus"], "--bogus"),
    (["sweep", "gmm-issf-duhem", "--plan", "no-such-plan"], "no-such-plan"),
])
def test_real_process(folder, argv, offending):
    argv = [a.format(rec=folder / "rec.h5") for a in argv]
    env = {**os.environ, "PYTHONWARNINGS": "ignore"}
    for as_json in (False, True):
        proc = subprocess.run([sys.executable, "-m", "hilbench.cli", *argv, *(["--json"] if as_json else [])],
                              capture_output=True, text=True, cwd=folder, env=env, timeout=300)
        lines = proc.stderr.splitlines()
        assert proc.returncode == 2, proc.stderr
        assert lines[-1].startswith("error: ") and offending in lines[-1] and "Traceback" not in proc.stderr
        assert sum(line.startswith("error: ") for line in lines) == 1
        if as_json:
            assert json.loads(proc.stdout)["exit"] == 2
        else:
            assert proc.stdout == ""
