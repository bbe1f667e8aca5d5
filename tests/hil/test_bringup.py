"""`vrscroll bringup` on emulators with each wiring mistake injected: the fault named, the correction stored on
the device (kept across a reset of the whole sketch), the next move right; a dead encoder named and nothing
stored; a reversed encoder told from a reversed motor by a hand's bend."""

import contextlib
import os
import re
import threading
import time

import numpy as np
import pytest

from cli import vrscroll
from random_plant import emulator_args
from twin.hil.bringup import bring_up
from twin.hil.mirror import mirror
from twin.link import protocol as P
from twin.link.emulator import Emulator, EmulatorOptions
from twin.link.faults import FaultOptions
from twin.link.pty_device import open_pty, serve
from twin.link.serial_link import Link
from twin.sim.plant import as_twin


@contextlib.contextmanager
def served(emu):
    """An in-process emulator on a real pty, paced in real time by a thread; yields the port."""
    master, slave, path = open_pty()
    stop = threading.Event()
    thread = threading.Thread(target=serve, args=(emu, master, stop.is_set), daemon=True)
    thread.start()
    try:
        yield path
    finally:
        stop.set()
        thread.join(5)
        os.close(master)
        os.close(slave)


def emulator_with(spec, *wiring, sketch=False):
    return Emulator(spec, EmulatorOptions(plant=as_twin(spec), faults=FaultOptions(latency_ms=0.0, wiring=wiring),
                                          sketch=sketch))


def hand_on(emu, link):
    """hand(k) for an in-process emulator: a person bends flap k up by 20 deg, reads the counts, lets go."""
    def hand(k):
        before = np.asarray(link.get_state().counts)
        emu.hand = (k, emu.plant.angles[k] + np.radians(20))
        time.sleep(0.4)
        moved = np.asarray(link.get_state().counts) - before
        emu.hand = None
        time.sleep(0.2)
        return moved
    return hand


@pytest.mark.parametrize("fault, named", [
    ("crossed:1,3", "hinge 1: encoder input 3, .* encoder cables of hinges 1 and 3 are crossed"),
])
def test_bringup_names_the_fault_stores_the_correction_and_moves_right(emulator, fault, named):
    dev = emulator("--ideal", "--lying-flat", "--wiring-fault", fault)  # as bring-up asks; it re-zeros anyway
    r = vrscroll("bringup", "--serial", dev.port, "--tolerance-deg", "20")
    assert r.returncode == 0, r.stdout + r.stderr
    assert re.search(named, r.stdout), r.stdout
    assert "move     every hinge to 10 deg: settled" in r.stdout and "bring-up done" in r.stdout
    assert "kept on the device (its flash" in r.stdout and "no device profile is selected" in r.stdout
    wiring = [e for e in dev.events("rx") if e["msg"] == "SET_WIRING"][-1]
    assert wiring["encoder"] != [0, 1, 2, 3, 4, 5] or any(wiring["flags"])
    # `zero` now: the device holds bring-up's last targets; it says so (not a fault to clear), and how to let go
    r = vrscroll("zero", "--serial", dev.port)
    assert r.returncode == 2 and "holds the last session's targets" in r.stderr, r.stderr
    assert "once the cause is gone" not in r.stderr
    assert vrscroll("status", "--serial", dev.port, "--estop", "--clear-fault").returncode == 0
    r = vrscroll("zero", "--serial", dev.port)
    assert r.returncode == 0 and "zero confirmed" in r.stdout, r.stderr


@pytest.mark.slow  # 6 s each; the default suite has the lying-flat dead encoder below, whose hinge 3 answers alike
@pytest.mark.parametrize("plant", [["--ideal"], emulator_args(61)], ids=["spec", "drawn"])
def test_lying_flat_the_hinges_that_lift_three_flaps_answer_too(emulator, plant):
    """Lying flat, as bring-up asks, hinges 2 and 3 lift three flaps each way: the first pulse moved them 1-18
    counts, and bring-up called their encoders dead on the spec's plant and on every drawn one tried. Stronger
    pulses follow where no encoder answers: every hinge answers and the wiring is stored."""
    dev = emulator(*plant, "--lying-flat")
    r = vrscroll("bringup", "--serial", dev.port)
    assert r.returncode == 0, r.stderr
    assert "no encoder answered" not in r.stdout + r.stderr
    stored = [e for e in dev.events("rx") if e["msg"] == "SET_WIRING"]
    assert len(stored) == 2 and stored[-1]["encoder"] == [0, 1, 2, 3, 4, 5]
    pulses = [e for e in dev.events("rx") if e["msg"] == "PULSE"]
    stronger = {e["hinge"] for e in pulses if abs(e["duty"]) > abs(pulses[0]["duty"])}  # the outer ones answer
    assert len({e["hinge"] for e in pulses}) == 6 and stronger and stronger <= {2, 3}, stronger  # at the first


def test_lying_flat_a_dead_encoder_beside_the_root_is_named_not_taken_for_a_neighbour(emulator):
    """Hinge 2's encoder dead, lying flat: its strongest pulse lifts three flaps and turns hinge 1's encoder
    from beside. Bring-up names hinge 2 and stores nothing, rather than reading hinge 1's input for both; hinge
    3, which lifts three flaps too, answers on its own input after stronger pulses."""
    dev = emulator("--ideal", "--lying-flat", "--wiring-fault", "encoder-dead:2")
    r = vrscroll("bringup", "--serial", dev.port)
    assert r.returncode == 2
    assert "nothing stored" in r.stderr and "hinge 2 " in r.stderr and "hinge 3" not in r.stderr, r.stderr
    assert re.search(r"hinge 3: encoder input 3, \d+ counts per pulse \(at most \d+\) ok", r.stdout), r.stdout
    pulses = [e for e in dev.events("rx") if e["msg"] == "PULSE" and e["hinge"] == 3]
    assert max(abs(e["duty"]) for e in pulses) > abs(pulses[0]["duty"])
    stored = [e for e in dev.events("rx") if e["msg"] == "SET_WIRING"]
    assert len(stored) == 1 and stored[0]["encoder"] == [0, 1, 2, 3, 4, 5]


def test_a_dead_encoder_is_named_and_nothing_stored(emulator):
    dev = emulator("--ideal", "--wiring-fault", "encoder-dead:5")
    r = vrscroll("bringup", "--serial", dev.port)
    assert r.returncode == 2
    assert "nothing stored: hinge 5: its motor was pulsed and no encoder answered" in r.stderr, r.stderr
    stored = [e for e in dev.events("rx") if e["msg"] == "SET_WIRING"]
    assert len(stored) == 1 and stored[0]["encoder"] == [0, 1, 2, 3, 4, 5]  # only the identity, to measure


@pytest.mark.parametrize("fault", ["encoder-reversed:4", pytest.param("motor-reversed:2", marks=pytest.mark.slow)])
def test_without_a_hand_a_hinge_counting_the_wrong_way_is_named_and_nothing_stored(emulator, fault):
    """Pulses cannot tell a reversed encoder from a reversed motor (the wrong guess leaves the device reporting
    +10 deg for a flap at -10 deg): without --hand bring-up names the hinge, both causes and how to decide, and
    stores nothing."""
    k = fault.split(":")[1]
    dev = emulator("--ideal", "--lying-flat", "--wiring-fault", fault)
    r = vrscroll("bringup", "--serial", dev.port)
    assert r.returncode == 2 and "nothing stored" in r.stderr, r.stdout + r.stderr
    assert f"hinge {k}: positive drive turns encoder input {k} down" in r.stderr and "--hand" in r.stderr
    stored = [e for e in dev.events("rx") if e["msg"] == "SET_WIRING"]
    assert len(stored) == 1 and stored[0]["flags"] == [0] * 6  # only the identity, to measure


def test_a_hand_tells_a_reversed_encoder_from_a_reversed_motor_and_the_flap_then_moves_the_right_way(spec):
    emu = emulator_with(spec, "encoder-reversed:4")
    with served(emu) as port, Link(port, hinges=spec.n_hinges) as link:
        checks = bring_up(link, spec, hand_on(emu, link), say=lambda line: None)
        assert [(c.encoder_reversed, c.motor_reversed) for c in checks][4] == (True, False)
        assert not any(c.encoder_reversed or c.motor_reversed for i, c in enumerate(checks) if i != 4)
        link.confirm_zero()
        flat = emu.plant.angles.copy()
        result = mirror(link, spec, np.radians([0, 0, 0, 0, 10, 0]), tolerance_deg=20)
        assert result.outcome == "settled"
        assert np.degrees(emu.plant.angles - flat)[4] == pytest.approx(10, abs=2)  # the flap, not just the count


def test_the_sketch_keeps_the_correction_across_a_reset(spec):
    emu = emulator_with(spec, "crossed:0,5", "motor-reversed:3", sketch=True)
    with served(emu) as port, Link(port, hinges=spec.n_hinges) as link:
        bring_up(link, spec, hand_on(emu, link), say=lambda line: None)
        stored = link.get_wiring()
    assert list(stored.encoder) == [5, 1, 2, 3, 4, 0] and stored.flags[3] == P.WIRING_MOTOR_REVERSED
    emu.firmware.reset(P.ResetReason.POWERON)  # off and on: the flash keeps it
    with served(emu) as port, Link(port, hinges=spec.n_hinges) as link:
        assert link.info.wiring_set == 1 and link.info.zero_confirmed == 0
        assert link.get_wiring() == stored


def test_lying_flat_the_flaps_stay_and_status_watch_reads_them_live(emulator):
    """On a table the flaps beside the root do not sag (hanging they fall tens of degrees in seconds); status
    --watch prints the angles five times a second for the seconds asked."""
    dev = emulator("--ideal", "--lying-flat")
    time.sleep(1.0)
    r = vrscroll("status", "--serial", dev.port, "--watch", "0.7")
    assert r.returncode == 0, r.stderr
    lines = [x for x in r.stdout.splitlines() if x.startswith("t=")]
    assert 3 <= len(lines) <= 5
    angles = np.array([[float(a) for a in x.split("s", 1)[1].split("deg")[0].split()] for x in lines])
    assert np.abs(angles).max() < 1.0, r.stdout
