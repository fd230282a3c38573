"""Tests for hilbench.recording.importers: CSV, plain .mat and dSPACE .mat into recordings."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import h5py
import numpy as np
import pytest
import scipy.io

from hilbench.errors import DataError, UserError
from hilbench.recording.importers import import_files, load_source, parse_mapping
from tests.conftest import require_real_data
from hilbench.recording.hdf5 import Recording




def _write(path: Path, text: str) -> Path:
    path.write_text(text, encoding="utf-8")
    return path


def _good_csv(path: Path, n: int = 20, rate: float = 100.0) -> Path:
    t = np.arange(n) / rate
    rows = ["time[s],input[V],output[um],temperature[degC]"]
    rows += [f"{ti:.6f},{np.sin(ti):.6f},{2 * np.sin(ti):.6f},{25 + ti:.3f}" for ti in t]
    return _write(path, "\n".join(rows) + "\n")


def _csv_with_rows(path: Path, header: str, rows: list[str]) -> Path:
    return _write(path, "\n".join([header, *rows]) + "\n")


def _dspace_mat(path: Path, n: int = 50, names: list[str] | None = None) -> Path:
    """A .mat file shaped like a dSPACE ControlDesk capture: X.Data (time), Y(i).Name / .Data."""
    names = names or ['"Model Root"/"M\x1aling"/"In1"', '"Model Root"/"M\x1aling_delay"/"In1"', '"Model Root"/"Pådrag"/"In1"']
    t = np.arange(n) / 1000.0
    y = np.zeros((1, len(names)), dtype=[("Name", "O"), ("Type", "O"), ("Data", "O"), ("Unit", "O")])
    for i, name in enumerate(names):
        y[0, i]["Name"] = name
        y[0, i]["Type"] = 5.0
        y[0, i]["Data"] = (i + 1) * np.sin(2 * np.pi * 10 * t)
        y[0, i]["Unit"] = np.zeros((0, 0))
    capture = {"X": {"Name": "", "Data": t}, "Y": y, "Capture": {"DateTime": "06/08/2014 11:29:18"}}
    scipy.io.savemat(path, {"cap": capture})
    return path


def _assert_refused(exc: pytest.ExceptionInfo[DataError], *parts: str) -> None:
    message = str(exc.value)
    assert "\n" not in message
    for part in parts:
        assert part in message, f"{part!r} not in {message!r}"


# -- good CSV ------------------------------------------------------------------------------------


def test_csv_with_header_and_units(tmp_path: Path) -> None:
    src = _good_csv(tmp_path / "sweep.csv", n=20, rate=100.0)
    out = tmp_path / "rec.h5"
    names = import_files([src], out)
    assert names == ["0001-sweep"]
    rec = Recording(out)
    run = rec.run("sweep")
    assert run.channels[:3] == ["time", "input", "output"]
    assert run.units == {"time": "s", "input": "V", "output": "um", "temperature": "degC"}
    assert run.sample_rate_hz == pytest.approx(100.0)
    assert run.n_samples == 20
    assert run.status == "complete"
    np.testing.assert_allclose(run.channel("temperature")[-1], 25 + 19 / 100.0, atol=1e-3)
    digest = hashlib.sha256(src.read_bytes()).hexdigest()
    assert run.excitation["kind"] == "imported"
    assert run.excitation["source"] == "sweep.csv"
    assert run.excitation["sha256"] == digest
    assert run.attrs["source"] == "sweep.csv"
    assert run.attrs["experiment"] == "import"


def test_csv_default_units_without_unit_in_header(tmp_path: Path) -> None:
    src = _csv_with_rows(tmp_path / "plain.csv", "time,input,output", ["0,1,2", "0.5,2,3", "1.0,3,4"])
    run = load_source(src)
    assert run.units == {"time": "s", "input": "", "output": "um"}
    assert run.sample_rate_hz == pytest.approx(2.0)


def test_csv_mapping_renames_by_name_and_sets_units(tmp_path: Path) -> None:
    src = _csv_with_rows(
        tmp_path / "bench.csv", "t[s],voltage,displacement[mm],load", ["0,0,0,1", "0.01,1,0.1,2", "0.02,2,0.2,3"]
    )
    run = load_source(src, mapping={"t": "time", "voltage": "input[V]", "displacement": "output"})
    assert list(run.data) == ["time", "input", "output", "load"]
    assert run.units == {"time": "s", "input": "V", "output": "mm", "load": "N"}
    np.testing.assert_allclose(run.data["output"], [0, 0.1, 0.2])
    assert run.excitation["channels"]["output"] == "displacement"


def test_csv_mapping_drops_a_column_with_dash(tmp_path: Path) -> None:
    src = _csv_with_rows(tmp_path / "c.csv", "time,input,output,comment", ["0,1,2,start", "1,2,3,x"])
    assert "comment" not in load_source(src, mapping={"comment": "-"}).data


def test_headerless_csv_by_index_drops_empty_and_ignores_unmapped(tmp_path: Path) -> None:
    # The layout of the real piezo CSV: empty pandas index column, time, displacement, voltage.
    src = _write(tmp_path / "raw.csv", ",0,-1.5,0,7\n,0.0002,-1.4,1.5,7\n,0.0004,-1.3,3.0,7\n")
    run = load_source(src, mapping={"1": "time[s]", "2": "output[um]", "3": "input[V]"})
    assert list(run.data) == ["time", "input", "output"]  # col 0 empty: dropped; col 4 unnamed: ignored
    np.testing.assert_allclose(run.data["input"], [0, 1.5, 3.0])
    np.testing.assert_allclose(run.data["output"], [-1.5, -1.4, -1.3])
    assert run.sample_rate_hz == pytest.approx(5000.0)


def test_headerless_csv_without_mapping_lists_columns(tmp_path: Path) -> None:
    src = _write(tmp_path / "raw.csv", ",0,-1.5,0\n,0.1,-1.4,1.5\n")
    with pytest.raises(DataError) as exc:
        load_source(src)
    _assert_refused(exc, "raw.csv", "missing column 'input'", "0 (empty)", "2 (-1.5)", "--map SRC=input")


def test_no_time_column_uses_rate(tmp_path: Path) -> None:
    src = _csv_with_rows(tmp_path / "u.csv", "input,output", ["1,2", "2,3", "3,4", "4,5"])
    run = load_source(src, rate_hz=200.0)
    np.testing.assert_allclose(run.data["time"], [0, 0.005, 0.010, 0.015])
    assert run.sample_rate_hz == 200.0


def test_time_in_ms_is_converted_to_s(tmp_path: Path) -> None:
    src = _csv_with_rows(tmp_path / "ms.csv", "time[ms],input,output", ["0,1,2", "1,2,3", "2,3,4"])
    run = load_source(src)
    np.testing.assert_allclose(run.data["time"], [0, 0.001, 0.002])
    assert run.units["time"] == "s"
    assert run.sample_rate_hz == pytest.approx(1000.0)


def test_semicolon_delimited_csv(tmp_path: Path) -> None:
    src = _csv_with_rows(tmp_path / "eu.csv", "time;input;output", ["0;1;2", "0.1;2;3"])
    np.testing.assert_allclose(load_source(src).data["output"], [2, 3])


def test_jittered_time_gives_the_mean_rate(tmp_path: Path) -> None:
    # Time stamps that jitter in the last digit, as in dSPACE and the real piezo CSV.
    t = np.arange(101) * 1e-4
    t[1:-1] += np.where(np.arange(1, 100) % 3 == 0, 2e-8, -1e-8)
    rows = [f"{float(ti)!r},0,0" for ti in t]
    run = load_source(_csv_with_rows(tmp_path / "j.csv", "time,input,output", rows))
    assert run.sample_rate_hz == pytest.approx(10000.0, rel=1e-9)


def test_run_names_and_append_to_existing_recording(tmp_path: Path) -> None:
    out = tmp_path / "rec.h5"
    first = import_files([_good_csv(tmp_path / "a.csv")], out)
    second = import_files(
        [_good_csv(tmp_path / "b.csv"), _good_csv(tmp_path / "c.csv")], out, run_names=["up", "down"], experiment="sweep"
    )
    assert first == ["0001-a"]
    assert second == ["0002-up", "0003-down"]
    rec = Recording(out)
    assert [r.name for r in rec] == ["0001-a", "0002-up", "0003-down"]
    assert rec.run("up").attrs["experiment"] == "sweep"
    assert rec.run("down").excitation["source"] == "c.csv"


def test_run_names_length_must_match(tmp_path: Path) -> None:
    out = tmp_path / "rec.h5"
    with pytest.raises(DataError) as exc:
        import_files([_good_csv(tmp_path / "a.csv")], out, run_names=["x", "y"])
    _assert_refused(exc, "2 run names for 1 files")
    assert not out.exists()


# -- bad CSV: one line naming file, line, column, value; no output file --------------------------


def _refused(tmp_path: Path, src: Path, *parts: str, **kwargs: object) -> None:
    out = tmp_path / "out.h5"
    with pytest.raises(DataError) as exc:
        import_files([src], out, **kwargs)  # type: ignore[arg-type]
    assert isinstance(exc.value, UserError)
    _assert_refused(exc, *parts)
    assert not out.exists()
    assert [p.name for p in tmp_path.iterdir() if p.suffix != src.suffix] == []  # no temporary left


def test_refuses_non_number(tmp_path: Path) -> None:
    rows = [f"{i / 10},{i},{i}" for i in range(5)] + ["0.5,5,abc"]
    src = _csv_with_rows(tmp_path / "data.csv", "time,input,output", rows)
    _refused(tmp_path, src, "data.csv: line 7, column 'output': 'abc' is not a number")


def test_refuses_non_number_in_mapped_column_names_source_and_channel(tmp_path: Path) -> None:
    src = _csv_with_rows(tmp_path / "data.csv", "time,volt,disp", ["0,1,2", "0.1,x1,3"])
    _refused(tmp_path, src, "line 3, column 'volt' (mapped to 'input'): 'x1' is not a number",
             mapping={"volt": "input", "disp": "output"})


def test_refuses_empty_cell(tmp_path: Path) -> None:
    src = _csv_with_rows(tmp_path / "gap.csv", "time,input,output", ["0,1,2", "0.1,,3", "0.2,3,4"])
    _refused(tmp_path, src, "gap.csv: line 3, column 'input': empty cell")


def test_refuses_nan(tmp_path: Path) -> None:
    src = _csv_with_rows(tmp_path / "nan.csv", "time,input,output", ["0,1,2", "0.1,2,nan"])
    _refused(tmp_path, src, "nan.csv: line 3, column 'output': 'nan' is not a finite number")


def test_refuses_missing_output_with_column_list_and_hint(tmp_path: Path) -> None:
    src = _csv_with_rows(tmp_path / "data.csv", "time,input,foo", ["0,1,2", "0.1,2,3"])
    _refused(tmp_path, src, "data.csv: missing column 'output' (columns: 'time', 'input', 'foo'); map one with --map SRC=output")


def test_refuses_time_not_increasing(tmp_path: Path) -> None:
    times = ["0.0", "0.1", "0.2", "0.3", "0.4", "0.5", "0.6", "0.7", "0.8", "0.3", "0.2"]
    rows = [f"{t},1,2" for t in times]
    src = _csv_with_rows(tmp_path / "data.csv", "time,input,output", rows)
    _refused(tmp_path, src, "data.csv: time is not strictly increasing at line 11 (0.3 after 0.8)")


def test_refuses_repeated_time(tmp_path: Path) -> None:
    src = _csv_with_rows(tmp_path / "rep.csv", "time,input,output", ["0,1,2", "0.1,1,2", "0.1,1,2"])
    _refused(tmp_path, src, "rep.csv: time is not strictly increasing at line 4 (0.1 after 0.1)")


def test_refuses_missing_file(tmp_path: Path) -> None:
    _refused(tmp_path, tmp_path / "nofile.csv", "nofile.csv: file not found")


def test_refuses_unsupported_extension(tmp_path: Path) -> None:
    src = _write(tmp_path / "data.xlsx", "time,input,output\n0,1,2\n")
    _refused(tmp_path, src, "data.xlsx: unsupported file type '.xlsx'", ".csv", ".mat")


def test_refuses_ragged_row(tmp_path: Path) -> None:
    src = _csv_with_rows(tmp_path / "rag.csv", "time,input,output", ["0,1,2", "0.1,2"])
    _refused(tmp_path, src, "rag.csv: line 3: 2 cells, expected 3")


def test_refuses_no_time_and_no_rate(tmp_path: Path) -> None:
    src = _csv_with_rows(tmp_path / "u.csv", "input,output", ["1,2", "2,3"])
    _refused(tmp_path, src, "u.csv: no time column", "--rate")


def test_refuses_rate_that_contradicts_time(tmp_path: Path) -> None:
    src = _good_csv(tmp_path / "t.csv", rate=100.0)
    _refused(tmp_path, src, "t.csv: the time column gives 100 Hz but the rate given is 1000 Hz", rate_hz=1000.0)


def test_refuses_bad_rate(tmp_path: Path) -> None:
    src = _csv_with_rows(tmp_path / "u.csv", "input,output", ["1,2", "2,3"])
    _refused(tmp_path, src, "--rate: sample rate must be a positive number of Hz, got 0", rate_hz=0.0)


def test_refuses_mapped_empty_column(tmp_path: Path) -> None:
    src = _write(tmp_path / "raw.csv", ",0,1,2\n,0.1,2,3\n")
    _refused(tmp_path, src, "raw.csv: column 0 (time) has no values", mapping={"0": "time", "2": "input", "3": "output"})


def test_refuses_unknown_time_unit(tmp_path: Path) -> None:
    src = _csv_with_rows(tmp_path / "fort.csv", "time[fortnights],input,output", ["0,1,2", "1,2,3"])
    _refused(tmp_path, src, "fort.csv: time unit 'fortnights' not understood", "ms")


def test_refuses_unknown_mapping_key(tmp_path: Path) -> None:
    src = _good_csv(tmp_path / "k.csv")
    _refused(tmp_path, src, "k.csv: --map key 'volts' matches no column", "'input'", mapping={"volts": "input"})


def test_refuses_two_columns_for_one_channel(tmp_path: Path) -> None:
    src = _csv_with_rows(tmp_path / "dup.csv", "time,input,output,disp", ["0,1,2,3", "1,2,3,4"])
    _refused(tmp_path, src, "dup.csv: two columns give channel 'output'", mapping={"disp": "output"})


def test_refuses_empty_file(tmp_path: Path) -> None:
    _refused(tmp_path, _write(tmp_path / "empty.csv", "\n\n"), "empty.csv: no data")


def test_bad_second_source_writes_nothing(tmp_path: Path) -> None:
    good = _good_csv(tmp_path / "good.csv")
    bad = _csv_with_rows(tmp_path / "bad.csv", "time,input,output", ["0,1,2", "0.1,2,zz"])
    out = tmp_path / "rec.h5"
    with pytest.raises(DataError) as exc:
        import_files([good, bad], out)
    _assert_refused(exc, "bad.csv: line 3, column 'output': 'zz'")
    assert not out.exists()


def test_bad_source_leaves_existing_recording_unchanged(tmp_path: Path) -> None:
    out = tmp_path / "rec.h5"
    import_files([_good_csv(tmp_path / "good.csv")], out)
    before = out.read_bytes()
    bad = _csv_with_rows(tmp_path / "bad.csv", "time,input", ["0,1", "0.1,2"])
    with pytest.raises(DataError, match="missing column 'output'"):
        import_files([_good_csv(tmp_path / "good2.csv"), bad], out)
    assert out.read_bytes() == before


def test_refuses_output_that_is_not_a_recording(tmp_path: Path) -> None:
    out = tmp_path / "other.h5"
    with h5py.File(out, "w") as f:
        f.attrs["format"] = "something-else"
    before = out.read_bytes()
    with pytest.raises(DataError, match="not a hilbench recording"):
        import_files([_good_csv(tmp_path / "good.csv")], out)
    assert out.read_bytes() == before


# -- parse_mapping ---------------------------------------------------------------------------------


def test_parse_mapping_accepts_names_units_and_drop() -> None:
    assert parse_mapping(["Y(3)=input[V]", " 1 = output [um] ", "displacement=output2", "c=-"]) == {
        "Y(3)": "input[V]",
        "1": "output[um]",
        "displacement": "output2",
        "c": "-",
    }


@pytest.mark.parametrize(
    ("items", "expected"),
    [
        (["noequals"], "expected SRC=CHANNEL"),
        (["=output"], "expected SRC=CHANNEL"),
        (["a="], "expected SRC=CHANNEL"),
        (["a=out put"], "'out put' is not a channel name"),
        (["a=output[um"], "is not a channel name"),
        (["a=input", "a=output"], "'a' is mapped twice"),
        (["a=output", "b=output[um]"], "'a' and 'b' are both mapped to 'output'"),
    ],
)
def test_parse_mapping_refuses_malformed(items: list[str], expected: str) -> None:
    with pytest.raises(DataError) as exc:
        parse_mapping(items)
    _assert_refused(exc, "--map", expected)


# -- MATLAB ----------------------------------------------------------------------------------------


def test_mat_plain_variables_selected_and_renamed(tmp_path: Path) -> None:
    src = tmp_path / "loop.mat"
    scipy.io.savemat(src, {"time": np.arange(5) / 10.0, "u": np.arange(5.0), "y": np.arange(5.0) * 2,
                           "other": np.ones(7), "fs": 10.0})
    run = load_source(src, mapping={"u": "input[V]", "y": "output[nm]"})
    assert list(run.data) == ["time", "input", "output"]  # `other` not selected, `time` kept as time base
    assert run.units == {"time": "s", "input": "V", "output": "nm"}
    np.testing.assert_allclose(run.data["output"], [0, 2, 4, 6, 8])
    assert run.sample_rate_hz == pytest.approx(10.0)
    assert run.excitation["format"] == "mat"


def test_mat_plain_variables_with_canonical_names_need_no_mapping(tmp_path: Path) -> None:
    src = tmp_path / "canon.mat"
    scipy.io.savemat(src, {"input": np.arange(4.0), "output": np.arange(4.0) + 1})
    run = load_source(src, rate_hz=50.0)
    np.testing.assert_allclose(run.data["time"], [0, 0.02, 0.04, 0.06])


def test_mat_refuses_unequal_lengths(tmp_path: Path) -> None:
    src = tmp_path / "len.mat"
    scipy.io.savemat(src, {"input": np.arange(4.0), "output": np.arange(5.0)})
    _refused(tmp_path, src, "len.mat: channels differ in length", "input", rate_hz=10.0)


def test_mat_refuses_garbage(tmp_path: Path) -> None:
    src = tmp_path / "junk.mat"
    src.write_bytes(b"this is not a mat file at all" * 10)
    _refused(tmp_path, src, "junk.mat: not a readable MATLAB .mat file")


def test_dspace_by_index_and_by_name(tmp_path: Path) -> None:
    src = _dspace_mat(tmp_path / "20_hz.mat", n=50)
    by_index = load_source(src, mapping={"Y(3)": "input[V]", "Y(1)": "output[um]"})
    by_name = load_source(src, mapping={"Pådrag": "input[V]", "Måling": "output[um]", "Måling_delay": "delayed[um]"})
    for run in (by_index, by_name):
        assert run.sample_rate_hz == pytest.approx(1000.0)
        np.testing.assert_allclose(run.data["time"], np.arange(50) / 1000.0)
        np.testing.assert_allclose(run.data["input"], 3 * np.sin(2 * np.pi * 10 * run.data["time"]))
        np.testing.assert_allclose(run.data["output"], np.sin(2 * np.pi * 10 * run.data["time"]))
        assert run.units["input"] == "V"
        assert run.excitation["format"] == "dspace-mat"
        assert run.excitation["captured"] == "06/08/2014 11:29:18"
    assert "delayed" in by_name.data and "delayed" not in by_index.data  # a mapping selects Y entries


def test_dspace_writes_a_run(tmp_path: Path) -> None:
    out = tmp_path / "rec.h5"
    names = import_files([_dspace_mat(tmp_path / "cap.mat")], out, mapping=parse_mapping(["Y(3)=input[V]", "Y(1)=output[um]"]))
    run = Recording(out).run(names[0])
    assert run.channels == ["time", "input", "output"]
    assert run.units["input"] == "V"
    assert json.loads(run.attrs["excitation"])["channels"] == {"time": "X", "input": "Y(3)", "output": "Y(1)"}


def test_dspace_refuses_y_out_of_range(tmp_path: Path) -> None:
    src = _dspace_mat(tmp_path / "cap.mat")
    _refused(tmp_path, src, "cap.mat: --map key 'Y(4)': the capture has only Y(1)..Y(3)", mapping={"Y(4)": "input"})


def test_dspace_refuses_ambiguous_name(tmp_path: Path) -> None:
    src = _dspace_mat(tmp_path / "cap.mat")
    _refused(tmp_path, src, "cap.mat: --map key 'In1' matches several columns (Y(1), Y(2), Y(3))", mapping={"In1": "input"})


def test_dspace_without_mapping_lists_signals(tmp_path: Path) -> None:
    src = _dspace_mat(tmp_path / "cap.mat")
    _refused(tmp_path, src, "cap.mat: missing column 'input'", "Y(1) 'M?ling'", "Y(3) 'Pådrag'", "--map SRC=input")


def test_dspace_refuses_time_not_increasing(tmp_path: Path) -> None:
    src = tmp_path / "back.mat"
    y = np.zeros((1, 2), dtype=[("Name", "O"), ("Data", "O")])
    y[0, 0]["Name"], y[0, 0]["Data"] = '"Model Root"/"u"/"In1"', np.arange(4.0)
    y[0, 1]["Name"], y[0, 1]["Data"] = '"Model Root"/"y"/"In1"', np.arange(4.0)
    scipy.io.savemat(src, {"cap": {"X": {"Data": np.array([0.0, 0.1, 0.05, 0.2])}, "Y": y}})
    _refused(tmp_path, src, "back.mat: time is not strictly increasing at X.Data(3) (0.05 after 0.1)",
             mapping={"Y(1)": "input", "y": "output"})


# -- real data (skipped when ../shared/data/real is absent) ----------------------------------------


def test_real_piezo_stack_csv(tmp_path: Path) -> None:
    src = require_real_data() / "piezo-stack-150V-1Hz" / "hysteresis_v_150_1hz.csv"
    out = tmp_path / "real.h5"
    names = import_files([src], out, mapping=parse_mapping(["1=time[s]", "2=output[um]", "3=input[V]"]))
    run = Recording(out).run(names[0])
    assert run.n_samples == 50001
    assert run.sample_rate_hz == pytest.approx(5000.0, rel=1e-6)
    assert run.channels == ["time", "input", "output"]
    y, u = run.channel("output"), run.channel("input")
    assert y.min() == pytest.approx(-19.7, abs=0.2) and y.max() == pytest.approx(19.7, abs=0.2)
    assert u.min() == pytest.approx(-150.0, abs=1.0) and u.max() == pytest.approx(150.0, abs=1.0)
    assert run.excitation["sha256"] == hashlib.sha256(src.read_bytes()).hexdigest()


def test_real_dspace_mat(tmp_path: Path) -> None:
    src = require_real_data() / "piezo-dspace-preisach" / "20_hz_no_lp.mat"
    out = tmp_path / "real.h5"
    names = import_files([src], out, mapping=parse_mapping(["Y(3)=input[V]", "Måling=output[um]"]))
    run = Recording(out).run(names[0])
    assert run.n_samples == 40001
    assert run.sample_rate_hz == pytest.approx(10000.0, rel=1e-6)
    u = run.channel("input")
    assert -101.0 <= u.min() <= -85.0 and 85.0 <= u.max() <= 91.0
    y = run.channel("output")
    assert -7.0 < y.min() < -5.0 and 3.0 < y.max() < 4.5


# -- encodings and units ------------------------------------------------------------------------------


@pytest.mark.parametrize("encoding", ["utf-8", "utf-8-sig", "latin-1", "cp1252"])
def test_header_units_with_micro_and_degree_in_any_encoding(tmp_path: Path, encoding: str) -> None:
    header = "time[s],input[V],output[µm],temperature[°C],bridge(kΩ)" if encoding.startswith("utf") else \
        "time[s],input[V],output[µm],temperature[°C],bridge(kohm)"
    src = tmp_path / "enc.csv"
    src.write_bytes((header + "\n0,1,2,20,1\n0.1,2,3,21,1\n0.2,3,4,22,1\n").encode(encoding))
    run = load_source(src)
    assert run.units == {"time": "s", "input": "V", "output": "um", "temperature": "degC", "bridge": "kOhm"}


def test_one_latin1_line_does_not_garble_a_utf8_header(tmp_path: Path) -> None:
    src = tmp_path / "mixed.csv"
    src.write_bytes("time[s],input[V],output[μm]\n".encode() + b"# measured at 20 \xb0C\n0,1,2\n0.1,2,3\n")
    assert load_source(src).units["output"] == "um"


@pytest.mark.parametrize("spelled, normal", [("µm", "um"), ("μm", "um"), ("um", "um"), ("micron", "um"),
                                             ("Micrometre", "um"), ("Âµm", "um"), ("°C", "degC"), ("deg C", "degC"),
                                             ("Â°C", "degC"), ("Ω", "Ohm"), ("Ω", "Ohm"), ("ohms", "Ohm"),
                                             ("µs", "us"), ("mm", "mm"), ("V", "V")])
def test_units_normalised(spelled: str, normal: str) -> None:
    from hilbench.recording.importers import normalize_unit

    assert normalize_unit(spelled) == normal


def test_map_target_unit_normalised_and_time_in_microseconds(tmp_path: Path) -> None:
    src = _csv_with_rows(tmp_path / "m.csv", "a,b,c", ["0,1,2", "100,2,3", "200,3,4"])
    run = load_source(src, mapping={"a": "time[µs]", "b": "input[V]", "c": "output[micron]"})
    assert run.units["output"] == "um" and run.units["time"] == "s"
    assert run.sample_rate_hz == pytest.approx(1e4)


def test_mapped_column_without_a_unit_is_refused(tmp_path: Path) -> None:
    src = _csv_with_rows(tmp_path / "nounit.csv", "t,u,y", ["0,1,2", "0.1,2,3", "0.2,3,4"])
    with pytest.raises(DataError) as exc:
        import_files([src], tmp_path / "out.h5", mapping={"t": "time[s]", "u": "input[V]", "y": "output"})
    assert "nounit.csv: --map y=output: the column has no unit" in str(exc.value)
    assert "--map y=output[um]" in (exc.value.hint or "") and not (tmp_path / "out.h5").exists()


def test_run_names_that_would_nest_groups_are_refused(tmp_path: Path) -> None:
    src = _csv_with_rows(tmp_path / "ok.csv", "time[s],input[V],output[um]", ["0,1,2", "0.1,2,3"])
    _refused(tmp_path, src, "--run: run name 'a/b'", run_names=["a/b"])


@pytest.mark.parametrize("unit", ["µm", "μm", "Âµm", "micron"])
def test_dspace_units_with_micro_normalised(tmp_path: Path, unit: str) -> None:
    src = tmp_path / "units.mat"
    y = np.zeros((1, 2), dtype=[("Name", "O"), ("Data", "O"), ("Unit", "O")])
    y[0, 0]["Name"], y[0, 0]["Data"], y[0, 0]["Unit"] = '"Model Root"/"u"/"In1"', np.arange(4.0), "V"
    y[0, 1]["Name"], y[0, 1]["Data"], y[0, 1]["Unit"] = '"Model Root"/"y"/"In1"', np.arange(4.0), unit
    scipy.io.savemat(src, {"cap": {"X": {"Data": np.arange(4.0) / 100}, "Y": y}})
    run = load_source(src, mapping={"Y(1)": "input", "Y(2)": "output"})
    assert run.units["output"] == "um" and run.units["input"] == "V"


def test_an_aixacct_export_imports_one_run_per_table(tmp_path):
    """The aixACCT TF Analyzer .dat export is reachable from `hilbench import` (one run per Table n)."""
    from tests.conftest import require_real_data

    source = require_real_data() / "pnzt-piezoceramic-aixacct" / "RMN_TRAP_1400V_1000V_CREEP.dat"
    if not source.exists():
        pytest.skip(f"{source} not found")
    out = tmp_path / "creep.h5"
    names = import_files([source], out)
    assert [n.rsplit("-", 1)[1] for n in names] == ["table1", "table2", "table3", "table4"]
    run = Recording(out).run(names[3])
    assert run.units["input"] == "V" and run.units["output"] == "um" and run.n_samples == 5000
    assert abs(run.data()["time"][-1] - 1400.3) < 1.0  # the 1400 s hold
