"""Holding: the gearboxes' back-driven efficiency from releases under gravity (e-stopped, windings shorted),
fitted on the twin's own releases and on an emulated device whose value the test draws, kept in the profile."""

import json

import numpy as np
import pytest

from twin.cli import main as vrscroll
from twin.device.spec import load_spec
from twin.formats.profile import select_profile
from twin.hil.holding import Release, fit_backdrive, sag_after_cut, twin_release
from twin.link import protocol as P
from twin.link.drawn_plant import drawn_plant
from twin.link.serial_link import Link
from twin.records.ranges import Ranges
from twin.sim.twin import Twin


def _twin_releases(plant, spec, count=2):
    """Releases from flat made by the twin of `plant`, as the device would report them (500 Hz frames)."""
    t = np.arange(0.0, 0.4, 0.002)
    blank = Release(t, np.zeros((len(t), spec.n_hinges)), np.zeros(spec.n_hinges))
    return [Release(t, twin_release(plant, blank, spec), np.zeros(spec.n_hinges)) for _ in range(count)]


def test_the_fit_finds_the_value_of_a_plant_it_can_represent():
    """Releases of a twin whose gearboxes pass 0.3 (the spec assumes 0.5): with the other parameters known,
    the fit finds 0.3 and calls it identifiable; with the no-load speed known only within +-30 % (the
    braking torque goes with the motor constant squared), the interval widens to hold it, not identifiable."""
    spec = load_spec()
    truth = 0.3
    releases = _twin_releases(spec.replace(backdrive_efficiency=truth), spec)
    fit = fit_backdrive(releases, spec)
    e = fit.estimate
    assert e.value == pytest.approx(truth, rel=0.05) and e.low <= truth <= e.high and e.identifiable, e
    assert e.prior == spec.backdrive_efficiency
    assert fit.sag_deg["twin_after"] == pytest.approx(fit.sag_deg["device"], abs=0.3)
    assert abs(fit.sag_deg["twin_before"][2] - fit.sag_deg["device"][2]) > 3.0  # 0.5 sags visibly faster
    speed = spec.no_load_speed
    wide = fit_backdrive(releases, spec, ranges=Ranges({"no_load_speed": (speed * 0.7, speed * 1.3)}, "test")).estimate
    assert wide.low < e.low and wide.high > e.high and not wide.identifiable
    assert wide.low <= truth <= wide.high and "no_load_speed" in wide.note


def test_unpowered_the_windings_open_whatever_the_firmware_commands(spec):
    """A pack pulled: the PID, still holding its targets, moves nothing, and without the windings' braking the
    hinges that carry three flaps fall faster than braked (after an e-stop) and far from where powered ones hold."""
    powered, cut, braked = (Twin(spec) for _ in range(3))
    held = np.degrees(powered.hold(0.2).true_angle[-1])
    fallen = np.degrees(cut.unpowered(0.2).true_angle[-1])
    braked.firmware.estop()
    slowed = np.degrees(braked.hold(0.2).true_angle[-1])
    assert np.abs(held).max() < 1.0, held
    for k in (2, 3):
        assert fallen[k] < slowed[k] - 5.0 and fallen[k] < -20.0, (fallen, slowed)
    assert sag_after_cut(spec, 0.2, braked=False)[2] == pytest.approx(fallen[2], abs=0.5)  # cut by an e-stop first


def test_holding_on_an_emulated_device_whose_gearboxes_nobody_told_the_twin(emulator, tmp_path, capsys):
    """The emulator draws its back-driven efficiency (and each hinge's motor, cogging, ripple, warming); from an
    uncalibrated profile `vrscroll holding` releases it twice, keeps the fit in the profile, and its interval
    holds the drawn value. The device is left IDLE, not e-stopped."""
    spec = load_spec()
    emu = emulator("--backdrive-scale", "0.6,1.4", "--seed", "11")
    truth = drawn_plant(emu)["backdrive_efficiency"]
    assert truth != spec.backdrive_efficiency
    assert vrscroll(["device", "create", "bench"]) == 0
    out = tmp_path / "holding.json"
    assert vrscroll(["holding", "--serial", emu.port, "--device", "bench", "--tolerance-deg", "30",
                     "--json", str(out)]) == 0
    text = capsys.readouterr().out
    doc = json.loads(out.read_text())
    e = doc["backdrive_efficiency"]
    assert e["low"] <= truth <= e["high"], (truth, e)
    assert len(doc["releases"]) == 2 and doc["sag_deg"]["device"][2] < -3.0  # hinge 2 sagged
    profile = select_profile("bench")
    assert profile.spec.backdrive_efficiency == pytest.approx(e["value"])
    assert profile.holding.parameters["backdrive_efficiency"].value == pytest.approx(e["value"])
    assert "vrscroll holding" in (profile.folder / "spec.toml").read_text()
    assert "after 1 s:" in text and "kept in device profile bench" in text
    # and with the pack pulled (windings open): hinges 2 and 3 fold further in 0.5 s than braked in 1 s
    unpowered, braked = doc["unpowered_from_flat_deg"], doc["braked_from_flat_deg"]
    assert "pack pulled" in text and all(unpowered["0.5"][k] < braked["1"][k] for k in (2, 3)), (unpowered, braked)
    with Link(emu.port) as link:
        assert link.get_state().state == P.State.IDLE
    capsys.readouterr()
    assert vrscroll(["device", "show", "bench"]) == 0
    assert "holding (vrscroll holding, 2 release(s)" in capsys.readouterr().out


@pytest.mark.parametrize("args, message", [
    (["--release-s", "9"], "--release-s"),
    (["--releases", "0"], "--releases"),
    (["--serial", "/dev/no-such-port"], "/dev/no-such-port"),
    (["--mount", "flat"], "--mount hanging"),  # the table holds the flaps up: nothing to release under gravity
    (["--mount", "stand"], "--mount hanging"),  # on its edge gravity loads no hinge
])
def test_holding_refuses_bad_input_naming_it(capsys, args, message):
    argv = ["holding"] + (args if "--serial" in args else args + ["--serial", "/dev/no-such-port"])
    assert vrscroll(argv) == 2
    err = capsys.readouterr().err
    assert message in err.strip().splitlines()[-1] and "Traceback" not in err, err  # argparse's usage, then the error
