"""hilbench.rig.emulation: one simulated plant behind every emulated device of a real-rig config."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from hilbench.errors import ConfigError
from hilbench.rig.config import load_rig
from hilbench.rig.emulation import start_emulators
from hilbench.rig.rig import Rig

REPO = Path(__file__).resolve().parents[2]
CANOPEN = REPO / "configs" / "templates" / "gmm-modbus-canopen.toml"
KEYENCE = REPO / "configs" / "templates" / "gmm-modbus-keyence.toml"


@pytest.fixture
def running():
    started = []

    def start(path, **changes):
        config = load_rig(path)
        if changes:
            config = dataclasses.replace(config, **changes)
        emu = start_emulators(config)
        started.append(emu)
        return emu

    yield start
    for emu in started:
        emu.close()


def test_settings_point_every_device_at_a_local_emulator(running):
    emu = running(CANOPEN)
    assert set(emu.emulators) == {"aio", "lvdt"}
    # the configured host 192.168.1.50:502 and bus can0 are never touched: a free local port, a virtual bus
    assert emu.settings["aio"]["url"].startswith("tcp://127.0.0.1:") and not emu.settings["aio"]["url"].endswith(":502")
    assert emu.settings["lvdt"]["interface"] == "virtual" and emu.settings["lvdt"]["channel"].startswith("hilbench-emulate-")
    config = emu.config_for_emulators()
    assert config.devices["aio"]["url"] == emu.emulators["aio"].url
    assert config.devices["lvdt"]["channel"] == emu.settings["lvdt"]["channel"]
    assert config.devices["lvdt"]["node_id"] == 5  # everything else as configured
    assert emu.config.devices["aio"]["url"] == "tcp://192.168.1.50:502"  # the original is left alone
    described = emu.describe()
    assert described["devices"]["aio"]["driver"] == "modbus-aio"


def test_one_world_the_modbus_output_moves_what_the_sensor_reads(running):
    emu = running(KEYENCE)
    assert emu.settings["laser"] == {"url": emu.emulators["laser"].url}
    with Rig(emu.config_for_emulators()) as rig:
        commands = emu.world.commands
        laser, aio = rig.devices_by_name["laser"], rig.devices_by_name["aio"]
        readings = []
        for amps in (0.2, 0.4, 0.6, 0.8, 1.0):  # the plant's displacement grows with the current
            aio.write(-amps)
            readings.append(laser.read()["output"])
        assert emu.world.commands == commands + 5  # one plant sample per AO write
        assert readings == sorted(readings, reverse=True) and readings[0] - readings[-1] > 1.0
        assert laser.read()["output"] == pytest.approx(emu.world.read("output"), abs=0.1)  # 0.1 um display
        assert aio.read()["current"] == pytest.approx(-1.0, abs=1e-3)
        aio.write(0.0)


def test_the_world_is_the_configs_plant_sample_rate_sensors_and_seed(running):
    emu = running(CANOPEN)
    plant = emu.world.plant
    assert plant.sample_rate_hz == 1000.0 and plant.seed == 1
    assert plant.sensors["output"].noise_std == 0.05 and "current" in plant.sensors


def test_a_config_without_a_plant_cannot_be_emulated(running):
    config = load_rig(CANOPEN)
    with pytest.raises(ConfigError, match=r"needs a \[plant\] table"):
        start_emulators(dataclasses.replace(config, plant={}))


def test_a_failing_start_closes_the_emulators_already_started(running, monkeypatch):
    from drivers import keyence_lk

    started = []
    real = keyence_lk.DRIVER.emulator

    def broken(settings, world):
        raise OSError("no pty left")

    import drivers.modbus_aio as modbus

    original = modbus.DRIVER.emulator

    def tracking(settings, world):
        emu = original(settings, world)
        started.append(emu)
        return emu

    monkeypatch.setattr(modbus, "DRIVER", dataclasses.replace(modbus.DRIVER, emulator=tracking))
    monkeypatch.setattr(keyence_lk, "DRIVER", dataclasses.replace(keyence_lk.DRIVER, emulator=broken))
    with pytest.raises(OSError, match="no pty left"):
        start_emulators(load_rig(KEYENCE))
    (aio,) = started
    assert not aio._thread.is_alive()  # the Modbus server started first was stopped again
    assert real is not broken


def test_close_is_idempotent_and_stops_every_emulator(running):
    emu = running(CANOPEN)
    aio = emu.emulators["aio"]
    emu.close()
    emu.close()
    assert emu.emulators == {} and not aio._thread.is_alive()


def test_write_config_overrides_a_base_table_and_makes_a_local_extends_absolute(running, tmp_path):
    """A user's rig file that extends a template beside it and sets no url of its own: the written copy
    (in another folder) gets an overriding device table and still finds its base."""
    folder = tmp_path / "mine"
    folder.mkdir()
    (folder / "base.toml").write_text(KEYENCE.read_text(encoding="utf-8"), encoding="utf-8")
    mine = folder / "rig.toml"
    mine.write_text('# my rig\n[rig]\nname = "mine"\nextends = "base"\n\n[devices.laser]\nbaud = 38400\n',
                    encoding="utf-8")
    emu = running(mine)
    out = emu.write_config(tmp_path / "elsewhere.toml")
    text = out.read_text(encoding="utf-8")
    assert "# my rig" in text and f'extends = "{(folder / "base.toml").resolve()}"' in text
    assert f'[devices.laser]\nbaud = 38400\nurl = "{emu.settings["laser"]["url"]}"' in text
    assert f'[devices.aio]\nurl = "{emu.settings["aio"]["url"]}"' in text  # the base's table, overridden
    written = load_rig(out)
    assert written.devices["aio"]["url"] == emu.settings["aio"]["url"] and written.devices["aio"]["unit_id"] == 1
    assert written.devices["laser"]["baud"] == 38400 and written.devices["laser"]["url"].startswith("/dev/")


def test_a_shared_can_bus_reaches_a_driver_opened_like_another_process_would(monkeypatch):
    """shared_can: the CANopen node on udp_multicast (group and port of its own), read by a fresh driver."""
    from drivers.canopen_sensor import DRIVER
    from hilbench.rig import emulation

    emu = start_emulators(load_rig(CANOPEN), shared_can=True)
    try:
        point = emu.settings["lvdt"]
        assert point["interface"] == "udp_multicast" and point["channel"] == emulation.UDP_MULTICAST_GROUPS[0]
        emu.world.command(0.0)
        device = DRIVER.open({**emu.config.devices["lvdt"], **point})
        try:
            assert set(device.read()) == {"output"}
        finally:
            device.close()
    finally:
        emu.close()
    # a host where the IPv6 group cannot be opened falls back to IPv4; where none opens, one line says so
    monkeypatch.setattr(emulation, "UDP_MULTICAST_GROUPS", ("not-a-group", "239.255.72.66"))
    assert emulation._shared_can_bus()["channel"] == "239.255.72.66"
    monkeypatch.setattr(emulation, "UDP_MULTICAST_GROUPS", ("not-a-group",))
    with pytest.raises(ConfigError, match="no python-can udp_multicast bus can be opened here"):
        emulation._shared_can_bus()
