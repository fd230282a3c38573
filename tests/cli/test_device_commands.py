"""`hilbench devices` and `hilbench emulate` through the real CLI."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import pytest
from typer.testing import CliRunner

from hilbench.cli import app
from hilbench.rig import registry
from hilbench.rig.emulation import UDP_MULTICAST_GROUPS

REPO = Path(__file__).resolve().parents[2]


def _drivers_installed(template: Path) -> bool:
    """False for a template whose driver needs an optional package that is missing (nidaqmx). Read from the
    loaded config: a template that ``extends`` another takes its devices' drivers from it."""
    from drivers.ni_daqmx import nidaqmx_available
    from hilbench.rig.config import load_rig

    drivers = {str(table.get("driver", "")) for table in load_rig(template).devices.values()}
    return "ni-daqmx" not in drivers or nidaqmx_available()


# the real-rig templates this machine can emulate (the NI one needs pip install 'hilbench[nidaqmx]')
TEMPLATES = [t for t in sorted((REPO / "configs" / "templates").glob("*.toml")) if _drivers_installed(t)]
runner = CliRunner()
SHIPPED = {"sim", "pi-gcs", "keyence-lk", "modbus-aio", "canopen-sensor"}


def one_line_error(result, code: int = 2) -> str:
    assert result.exit_code == code, result.output
    assert "Traceback" not in result.output
    errors = [line for line in result.stderr.strip().splitlines() if line.startswith("error: ")]
    assert len(errors) == 1, result.stderr
    return errors[0]


def test_devices_json_lists_the_five_shipped_drivers_with_their_settings():
    result = runner.invoke(app, ["devices", "--json"])
    assert result.exit_code == 0, result.output
    document = json.loads(result.stdout)
    drivers = {d["name"]: d for d in document["drivers"]}
    assert SHIPPED <= set(drivers)
    assert isinstance(document["serial_ports"], list)
    for name in SHIPPED - {"sim"}:
        d = drivers[name]
        assert d["emulator"] is True and d["roles"] and d["transports"] and d["description"], d
        assert d["entry_point"].endswith(":DRIVER") and "error" not in d
        assert d["settings"] and all({"name", "type", "required", "default", "doc"} <= set(s) for s in d["settings"])
    pi = {s["name"]: s for s in drivers["pi-gcs"]["settings"]}
    assert pi["url"]["required"] is True and pi["url"]["type"] == "str"
    assert pi["baud"] == {"name": "baud", "type": "int", "required": False, "default": 115200,
                          "doc": "bit/s (ignored by ptys and sockets)"}
    can = {s["name"]: s for s in drivers["canopen-sensor"]["settings"]}
    assert can["node_id"]["required"] is True and can["interface"]["default"] == "virtual"
    assert drivers["modbus-aio"]["roles"] == ["actuator", "sensor"] and "tcp://" in drivers["modbus-aio"]["transports"]
    assert drivers["sim"]["entry_point"] == "hilbench.sim.backend:DRIVER" and drivers["sim"]["settings"] == []


def test_devices_text_names_every_driver_and_the_serial_ports():
    result = runner.invoke(app, ["devices"])
    assert result.exit_code == 0, result.output
    for name in SHIPPED:
        assert any(line.startswith(f"{name}  (") for line in result.stdout.splitlines()), name
    assert "node_id" in result.stdout and "required" in result.stdout
    assert result.stdout.strip().splitlines()[-1].startswith("serial ports: ")


def test_devices_lists_a_third_party_driver_and_says_why_a_broken_one_cannot_load(monkeypatch):
    from drivers.base import DriverSpec, Setting

    spec = DriverSpec(name="thirdparty", roles=("sensor",), settings=(Setting("port", str, required=True, doc="where"),),
                      open=lambda settings: None, description="a third party's sensor", transports=("serial",))
    monkeypatch.setitem(sys.modules, "tests_thirdparty_driver", type("module", (), {"DRIVER": spec}))
    monkeypatch.setitem(registry.BUILTIN, "thirdparty", "tests_thirdparty_driver:DRIVER")
    monkeypatch.setitem(registry.BUILTIN, "broken", "tests_no_such_module:DRIVER")
    registry.clear_cache()
    try:
        result = runner.invoke(app, ["devices", "--json"])
    finally:
        registry.clear_cache()
    assert result.exit_code == 0, result.output
    drivers = {d["name"]: d for d in json.loads(result.stdout)["drivers"]}
    assert drivers["thirdparty"]["entry_point"] == "tests_thirdparty_driver:DRIVER"
    assert drivers["thirdparty"]["settings"] == [{"name": "port", "type": "str", "required": True, "default": None,
                                                  "doc": "where"}]
    assert drivers["thirdparty"]["emulator"] is False
    assert "cannot be loaded" in drivers["broken"]["error"] and "tests_no_such_module" in drivers["broken"]["error"]


# -- emulate --------------------------------------------------------------------------------------------


def test_emulate_refuses_a_simulated_rig_in_one_line():
    line = one_line_error(runner.invoke(app, ["emulate", "gmm-issf-duhem", "--seconds", "0"]))
    assert "gmm-issf-duhem.toml: a simulated rig" in line


def test_emulate_refuses_a_missing_config_and_misplaced_options(tmp_path):
    assert "no such file" in one_line_error(runner.invoke(app, ["emulate", str(tmp_path / "absent.toml")]))
    if TEMPLATES:
        line = one_line_error(runner.invoke(app, ["emulate", str(TEMPLATES[0]), "-e", "sine:amplitude=1"]))
        assert "--excitation and --output go with --dry-run" in line


@pytest.mark.skipif(not TEMPLATES, reason="no real-rig templates in configs/templates/")
@pytest.mark.parametrize("template", TEMPLATES, ids=[t.stem for t in TEMPLATES])
def test_emulate_prints_where_every_device_of_a_template_listens(template):
    result = runner.invoke(app, ["emulate", str(template), "--seconds", "0.2", "--json"])
    assert result.exit_code == 0, result.output
    document = json.loads(result.stdout)
    from hilbench.rig.config import load_rig

    tables = load_rig(template).devices
    assert set(document["devices"]) == set(tables)
    for name, point in document["devices"].items():
        assert point["driver"] == tables[name]["driver"]
        url = point.get("url", "")
        if url.startswith(("tcp://", "socket://", "grpc://")):
            assert url.split("://")[1].startswith("127.0.0.1:")  # loopback only, never the real device's host
            assert point["tcp"] == url.split("://")[1] and point["port"] == int(url.rsplit(":", 1)[1])
        elif "url" in point:
            assert url.startswith("/dev/") and point["pty"] == url  # a pty
        else:  # a python-can bus other processes on this machine reach, on a UDP port of its own
            assert point["interface"] == "udp_multicast" and point["port"] > 0
            assert point["channel"] in UDP_MULTICAST_GROUPS
        if point["driver"] == "pi-gcs":  # a line-protocol emulator: its pty AND its TCP port, both printed
            assert point["pty"].startswith("/dev/") and point["tcp"].startswith("127.0.0.1:")
            assert point["port"] == int(point["tcp"].rsplit(":", 1)[1]) > 0


@pytest.mark.skipif(not TEMPLATES, reason="no real-rig templates in configs/templates/")
def test_emulate_dry_run_records_through_the_real_drivers(tmp_path):
    out = tmp_path / "dry.h5"
    result = runner.invoke(app, ["emulate", str(TEMPLATES[0]), "--dry-run", "-e",
                                 "sine:amplitude=1,frequency_hz=5,cycles=1", "-o", str(out), "--json"])
    assert result.exit_code == 0, result.output
    dry = json.loads(result.stdout)["dry_run"]
    assert dry["status"] == "complete" and dry["runs"][0]["samples"] > 0
    with h5py.File(out, "r") as f:
        (name,) = list(f["runs"])
        run = f["runs"][name]
        devices = json.loads(run.attrs["devices"])
        assert run.attrs["status"] == "complete"
        assert {d["driver"] for d in devices} <= SHIPPED - {"sim"}
        output = run["output"][:]
    assert output.max() - output.min() > 0  # the emulated plant moved and the real driver read it


# -- emulate --write-config: the template pointed at its emulators, then swept from another process ---------
PI_TEMPLATE = REPO / "configs" / "templates" / "piezo-pi-e727.toml"


NI_TEMPLATE = REPO / "configs" / "templates" / "gmm-ni-9263-9234.toml"
#: templates whose actuator device plays whole runs on its own clock (block mode), and their plans
BLOCK_PLANS = {PI_TEMPLATE: "sine:amplitude=2,offset=5,frequency_hz=5,cycles=2",
               NI_TEMPLATE: "sine:amplitude=1,offset=1.5,frequency_hz=5,cycles=2"}


#: the NI 9215 template is swept and tracked through emulate --write-config in
#: tests/drivers/test_ni_daqmx_track.py, which is this test and more
CROSS_PROCESS = [t for t in TEMPLATES if t.stem != "gmm-ni-9263-9215"]


@pytest.mark.parametrize("template", CROSS_PROCESS, ids=[t.stem for t in CROSS_PROCESS])
def test_a_template_through_emulate_write_config_passes_sweep_check_and_sweeps(template, tmp_path):
    """`hilbench emulate T --write-config OUT` in one process, `hilbench sweep OUT` in another, as a
    user dry-runs a real-rig template: nothing copied by hand."""
    written = tmp_path / "rig-emulated.toml"
    emulate = subprocess.Popen([sys.executable, "-m", "hilbench.cli", "emulate", str(template), "--json",
                                "--write-config", str(written), "--seconds", "120"],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        while not written.exists() and emulate.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
        assert written.exists(), emulate.stderr.read() if emulate.poll() is not None else "no config written"
        from hilbench.rig.config import load_rig

        config = load_rig(written)
        for table in config.devices.values():
            if "url" not in table:  # CANopen: a udp_multicast bus of its own, reachable from this process
                assert table["interface"] == "udp_multicast" and table["port"] > 0
            elif table["url"].startswith(("socket://", "tcp://", "grpc://")):
                assert table["url"].split("://")[1].startswith("127.0.0.1:")
            else:
                assert table["url"].startswith("/dev/")
        # the PI controller's wave generator paces its runs: --check passes at 2 kHz whatever the round
        # trip; per-sample rigs depend on this machine's round trip (tests/runners/test_rate_check.py)
        late = [] if template in BLOCK_PLANS else ["--allow-late"]
        check = runner.invoke(app, ["sweep", str(written), "--check", "--json", *late,
                                    "-e", BLOCK_PLANS.get(template, "sine:amplitude=1,frequency_hz=5,cycles=1")])
        assert check.exit_code == 0, check.output
        checked = json.loads(check.stdout)
        assert checked["plan_ok"] is True
        assert checked["round_trips"]["mode"] == ("block" if template in BLOCK_PLANS else "fixed-rate")
        out = tmp_path / "swept.h5"
        plan = BLOCK_PLANS.get(template, "sine:amplitude=1,frequency_hz=5,cycles=1")
        swept = runner.invoke(app, ["sweep", str(written), "-e", plan, "-o", str(out), "-q", "--json", *late])
        assert swept.exit_code == 0, swept.output
        assert json.loads(swept.stdout)["status"] == "complete"
        with h5py.File(out, "r") as f:
            (run,) = [f["runs"][name] for name in f["runs"]]
            devices = {d["driver"] for d in json.loads(run.attrs["devices"])}
            output = run["output"][:]
        assert devices == {t["driver"] for t in load_rig(template).devices.values()}
        assert output.max() - output.min() > 1.0  # the emulated plant moved and the real driver read it
    finally:
        emulate.send_signal(signal.SIGINT)  # Ctrl-C: the emulators stop and the command exits 0
        stdout, stderr = emulate.communicate(timeout=30)
    assert emulate.returncode == 0, stderr
    document = json.loads(stdout)
    assert document["written_config"] == str(written)
    assert set(document["devices"]) == set(load_rig(template).devices)


def test_the_pi_and_the_canopen_templates_are_among_them():
    assert PI_TEMPLATE in TEMPLATES and REPO / "configs" / "templates" / "gmm-modbus-canopen.toml" in TEMPLATES


def test_write_config_keeps_the_file_and_changes_only_what_reaches_the_emulators(tmp_path):
    out = tmp_path / "pi.toml"
    result = runner.invoke(app, ["emulate", str(PI_TEMPLATE), "--seconds", "0", "--write-config", str(out), "--json"])
    assert result.exit_code == 0, result.output
    point = json.loads(result.stdout)["devices"]["pi"]
    original = PI_TEMPLATE.read_text(encoding="utf-8").splitlines()
    written = out.read_text(encoding="utf-8").splitlines()[2:]  # after the two header lines
    changed = [(a, b) for a, b in zip(original, written) if a != b]
    assert len(original) == len(written)
    assert changed == [('url = "socket://192.168.168.10:50000"', f'url = "{point["url"]}"')]


@pytest.mark.parametrize("value, message", [
    ("rig.txt", "expected a .toml file name"),
    ("no-such-folder/rig.toml", "does not exist"),
])
def test_write_config_refuses_a_bad_value_in_one_line(value, message, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    line = one_line_error(runner.invoke(app, ["emulate", str(PI_TEMPLATE), "--seconds", "0", "--write-config", value]))
    assert f"--write-config {value}" in line and message in line


def test_write_config_never_overwrites_the_config_it_emulates(tmp_path):
    copy = tmp_path / "mine.toml"
    copy.write_text(PI_TEMPLATE.read_text(encoding="utf-8"), encoding="utf-8")
    line = one_line_error(runner.invoke(app, ["emulate", str(copy), "--seconds", "0", "--write-config", str(copy)]))
    assert "the config being emulated" in line
    assert copy.read_text(encoding="utf-8") == PI_TEMPLATE.read_text(encoding="utf-8")


@pytest.mark.parametrize("old, new, message", [
    ('axis = "1"', 'axis = "1"\nservo_bandwidth_hz = -5.0', "[devices.pi] servo_bandwidth_hz = -5.0: expected a number > 0"),
    ("travel_min_um = 0.0", "travel_min_um = 300.0",
     "[devices.pi] travel_min_um = 300.0 must be below travel_max_um = 200.0"),
])
def test_emulate_refuses_an_emulator_setting_that_cannot_work_in_one_line(old, new, message, tmp_path):
    config = tmp_path / "bad.toml"
    config.write_text(PI_TEMPLATE.read_text(encoding="utf-8").replace(old, new), encoding="utf-8")
    assert message in one_line_error(runner.invoke(app, ["emulate", str(config), "--seconds", "0"]))
