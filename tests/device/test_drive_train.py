"""The drive train in the loop: backlash outside it, stiction, the power chain against the emulator, the
emulator's drawn plant and its encoder, and the gate on a whole scenario."""

import dataclasses
import json
import math
import random

import numpy as np
import pytest

from controllers.encoder import target_counts
from twin.cli import main
from twin.formats.scenario import Scenario
from twin.link import protocol as P
from twin.link.emulator import Emulator, EmulatorOptions, drawn_options
from twin.link.faults import FaultOptions
import mujoco

from twin.sim.plant import (
    RIPPLE_PERIOD,
    HingeDraw,
    Plant,
    PlantOptions,
    PlantRanges,
    as_twin,
    draw_plant,
)
from twin.device.mjcf import load_model, motor_attributes
from twin.sim.gate import GateRefused, check_move, check_scenario, enforce
from twin.sim.response import move_report, step_metrics
from twin.sim.twin import Twin

ZIGZAG_DEG = [90.0, -90.0, 90.0, -90.0, 90.0, -90.0]  # 90 deg on every hinge, the row free of itself


def test_the_flap_wanders_in_the_backlash_while_the_encoder_is_still(spec):
    """A hand pushes flap 5 one way, then the other, gently (below the gearbox's static friction; gravity off,
    so the push alone loads it): the flap crosses the dead zone, the motor and its encoder do not move, so the
    firmware sees nothing."""
    twin = Twin(spec)
    twin.model.opt.gravity[:] = 0
    twin.reset(np.full(spec.n_hinges, 0.5 * spec.rad_per_count))  # mid-count: the encoder reads a clean count
    k = 5
    dof = twin.hinges.dadr[k]
    positions, counts = [], []
    for push in (0.003, -0.003, 0.003):
        twin.data.qfrc_applied[dof] = push  # N*m on the flap; the loop writes only the gear joints' entries
        trace = twin.hold(0.3)
        positions.append(trace.true_angle[-100:, k].mean())
        counts.append(trace.counts[:, k])
    twin.data.qfrc_applied[dof] = 0.0
    swing = abs(positions[1] - positions[0])
    assert 0.9 * spec.backlash <= swing <= 1.3 * spec.backlash  # across the dead zone, pressed into its ends
    assert abs(positions[2] - positions[0]) < 0.1 * spec.backlash
    seen = np.concatenate(counts)
    assert np.all(seen == seen[0])  # the encoder never moved


def test_static_friction_holds_below_it_and_slides_above_it(spec):
    """At zero duty (IDLE: the core brakes, and a shorted winding resists only motion), a torque on the flap
    between the Coulomb and the static friction leaves the hinge where it is (past its backlash); one above
    the static friction starts it, and it keeps turning, slowed by the winding. (No cogging: its detents hold
    too, which is not what is tested here.)"""
    spec = spec.replace(cogging=0.0)
    moved = {}
    for torque in (0.6 * spec.gear_stiction, 1.3 * spec.gear_stiction):
        twin = Twin(spec)
        twin.model.opt.gravity[:] = 0
        twin.firmware.clear_fault()  # IDLE: zero duty, braked
        twin.data.qfrc_applied[twin.hinges.dadr[0]] = torque
        trace = twin.hold(0.5)
        moved[torque] = abs(trace.true_angle[-1, 0])
    low, high = moved
    assert spec.gear_friction < low < spec.gear_stiction < high
    assert moved[low] < spec.backlash / 2 + math.radians(0.2)  # LuGre creeps a little below the static friction
    assert moved[high] > math.radians(6)


def test_zero_volts_from_flat_hinge_2_falls_slowly_braked(spec):
    """docs/device.md "Stiction": 0 V from flat. Braked (the firmware's zero duty in every state),
    hinge 2 carries 0.026 N*m of flaps, above the gearbox's static friction (0.008 N*m): it falls, slowed by
    back-EMF through the back-driven gearbox, to about -65 deg in 2 s (the previous model: -70 deg); the
    outer hinges (0.002 N*m) hold. (Coasting, the drive model's other decay, it would drop to the hanging
    pose within half a second: tests/device/test_motor.py checks coast at the winding.)"""
    braked = Twin(spec)
    braked.firmware.estop()
    fall = np.degrees(braked.hold(2.0).true_angle)
    assert -80 < fall[-1, 2] < -50 and fall[999, 2] > fall[-1, 2]
    assert np.abs(fall[-1, [0, 5]]).max() < 0.5


def emulated_settle(spec, opt, targets, seconds) -> np.ndarray:
    """The emulated device stepped to targets in process (the firmware's bytes in, its counts out): each
    hinge's settle time, s, from its counts and the firmware's settle band."""
    emu = Emulator(spec, opt)
    goal = target_counts(spec, targets)
    emu.receive(P.encode(P.SetTargets(tuple(int(c) for c in goal)), 1))
    counts = []
    for i in range(int(round(seconds / spec.firmware_dt))):
        if i and i % 100 == 0:
            emu.receive(P.encode(P.Heartbeat(), i // 100 + 1))
        emu.step()
        counts.append(emu.counts.copy())
    time_s = np.arange(len(counts)) * spec.firmware_dt
    return np.array([step_metrics(time_s, c, g, spec.settle_band, hold=spec.settle_hold).settle_time
                     for c, g in zip(np.array(counts).T, goal)])


def test_six_hinges_settle_later_on_a_low_pack_as_the_twin_predicts_for_the_emulator(spec):
    """Six hinges stepped together share the pack: on 6.6 V it sags below the 6 V the firmware asks for while
    they accelerate, and the move is slower than on a full 8.4 V pack (by a few ms: once the hinges turn,
    their current and the sag fall). The emulator (its own plant process, the command's latency) settles
    later on 6.6 V, and within 15 % of the twin's prediction on each pack (settle times averaged over the
    hinges)."""
    targets = np.radians(ZIGZAG_DEG)
    got = {}
    for volts in (spec.pack_low_voltage, spec.pack_full_voltage):
        pack = spec.replace(supply_voltage=volts)
        report = move_report(pack, Twin(pack).move_to(targets, max_time=1.5, stop_when_settled=False))
        predicted = np.mean(report.settle_time)
        opt = EmulatorOptions(plant=dataclasses.replace(as_twin(spec), pack_voltage=volts),
                              faults=FaultOptions(latency_ms=1.0), zeroed=True)
        measured = emulated_settle(spec, opt, targets, 1.5).mean()
        assert measured == pytest.approx(predicted, rel=0.15), volts
        got[volts] = measured
    assert got[spec.pack_low_voltage] > got[spec.pack_full_voltage]


def test_the_emulators_plant_is_drawn_within_its_ranges_logged_and_seeded(spec, tmp_path):
    """Each seed draws a different plant and latency within the ranges, the same again for the same seed; the
    drawn values are in the emulator's log (and nowhere the twin reads); a range of one value fixes it."""
    ranges = PlantRanges()
    draws = [draw_plant(ranges, random.Random(seed)) for seed in range(20)]
    for plant, latency in draws:
        for field in ("speed_scale", "friction_scale", "damping_scale", "armature_scale", "backlash_deg"):
            lo, hi = getattr(ranges, field)
            assert lo <= getattr(plant, field) <= hi
        assert 0 <= latency <= 3
    assert len({p.speed_scale for p, _ in draws}) == 20
    assert draw_plant(ranges, random.Random(4)) == draws[4]
    fixed = draw_plant(PlantRanges(speed_scale=(1.1, 1.1)), random.Random(0))[0]
    assert fixed.speed_scale == 1.1
    with pytest.raises(ValueError, match="backlash_deg"):
        PlantRanges(backlash_deg=(0.5, 0.1))
    log = tmp_path / "emu.jsonl"
    opt = drawn_options(ranges, FaultOptions(), seed=7)
    Emulator(spec, opt, log_path=str(log)).close()
    start = json.loads(log.read_text().splitlines()[0])
    assert start["options"]["plant"]["speed_scale"] == opt.plant.speed_scale
    assert start["plant"]["no_load_speed"] == pytest.approx(spec.no_load_speed * opt.plant.speed_scale)
    assert start["options"]["faults"]["latency_ms"] == opt.faults.latency_ms


def test_the_emulators_hinges_differ_and_keep_effects_the_twin_does_not_model(spec, tmp_path):
    """Each drawn plant's hinges have their own speed, friction, damping and armature about the shared draw,
    within the range, and every hinge a friction ripple above zero (an effect the twin does not model), its
    cogging and its winding's temperature; each hinge's values are in the emulator's log."""
    ranges = PlantRanges()
    for seed in range(10):
        plant, _ = draw_plant(ranges, random.Random(seed), n_hinges=spec.n_hinges)
        assert len(plant.hinges) == spec.n_hinges
        scales = np.array([[h.speed, h.friction, h.damping, h.armature] for h in plant.hinges])
        assert np.all((scales >= 0.85) & (scales <= 1.15)) and np.ptp(scales[:, 0]) > 0.01
        assert all(0.05 <= h.ripple <= 0.2 and 0.01 <= h.cogging <= 0.05 and 25 <= h.winding_c <= 45
                   for h in plant.hinges)
    log = tmp_path / "emu.jsonl"
    opt = drawn_options(ranges, FaultOptions(), seed=3)
    Emulator(spec, opt, log_path=str(log)).close()
    hinges = json.loads(log.read_text().splitlines()[0])["hinges"]
    speed = [h["no_load_speed"] / (spec.no_load_speed * opt.plant.speed_scale) for h in hinges]
    assert speed == pytest.approx([h.speed for h in opt.plant.hinges], rel=1e-9)


def _coast(plant, ticks):
    """Ticks with every driver coasting (no current): what moves the flaps is gravity and the plant alone."""
    off, coast = np.zeros(plant.spec.n_hinges, np.float32), np.zeros(plant.spec.n_hinges, np.uint8)
    for _ in range(ticks):
        plant.sense()
        plant.actuate(off, coast)


def test_one_hinges_own_motor_moves_that_hinge_only(spec):
    """Hinge 0's motor alone made slower (its speed x0.7): driven alike, hinge 0 turns less far than on the
    plant whose hinges are all the same; hinge 5, on the other chain, turns (nearly) the same."""
    pwm, brake = np.full(spec.n_hinges, 0.6, np.float32), np.ones(spec.n_hinges, np.uint8)
    angles = []
    for first in (HingeDraw(), HingeDraw(speed=0.7)):
        plant = Plant(spec, PlantOptions(hinges=(first,) + (HingeDraw(),) * (spec.n_hinges - 1)), random.Random(0))
        for _ in range(100):  # 0.1 s: past the start, where a slower motor's larger torque constant pulls harder
            plant.sense()
            plant.actuate(pwm, brake)
        angles.append(plant.angles)
    # (hinge 5 the same but for the shared pack: hinge 0 draws less current, the bus sags less; measured with the
    # windings at their drawn temperature: x0.81 at 0.1 s, x0.86 at 60 ms)
    assert angles[1][0] < 0.85 * angles[0][0] and angles[1][5] == pytest.approx(angles[0][5], rel=2e-3)


def test_cogging_ripple_and_a_warming_winding_are_in_the_plant(spec):
    """Cogging: at rest, the torque on the motor depends on its angle as MuJoCo's dcmotor `cogging` has it (its
    drawn share of the stall torque, the spec's cogging_periods a turn, its phase); turning a whole period within
    a tick, none is left (averaged over the turn, not aliased). Ripple: a moving gearbox's extra friction is the
    drawn share of its Coulomb friction, with the final gear's mesh. The winding: at its power-on temperature, then
    warmer while the motor is held at stall."""
    draw = HingeDraw(cogging=0.04, cogging_phase=1.1, ripple=0.15, ripple_phase=0.3, winding_c=30.0)
    plant = Plant(spec, PlantOptions(hinges=(draw,) * spec.n_hinges), random.Random(0))
    m, d, k = plant.model, plant.data, 2
    g, q = plant.hinges.gear_dof[k], plant.hinges.gear_qadr[k]
    s = plant.hinge_specs[k]
    stall = s.motor_constant * s.supply_voltage / s.drive_resistance  # N*m at the motor
    assert d.act[m.actuator_actadr[k]] == 5.0  # K above the ambient (25 deg C): the winding at 30 deg C
    d.qpos[q], d.qvel[:], d.ctrl[k] = 0.0, 0.0, s.supply_voltage  # the stalled winding's torque: R x (1 + 0.393 % x 5)
    mujoco.mj_forward(m, d)
    assert d.actuator_force[k] == pytest.approx(stall / (1 + 0.00393 * 5.0), rel=0.01)
    # MuJoCo's own cogging, on a model of this motor with the dcmotor's attribute (the plant's own is 0)
    mine = load_model(spec, motors=[motor_attributes(s.replace(cogging=0.04, cogging_phase=1.1))] * spec.n_hinges)
    theirs = mujoco.MjData(mine)
    coast = np.zeros(spec.n_hinges, np.uint8)
    for motor_angle in np.linspace(0, 2 * np.pi / s.cogging_periods, 9):
        d.qpos[q], d.qvel[:], d.ctrl[:] = motor_angle / s.gear_ratio, 0.0, 0.0
        mujoco.mj_forward(m, d)
        assert d.actuator_force[k] == pytest.approx(0.0, abs=1e-12)  # (the dcmotor's cogging is not the plant's)
        plant.actuate(np.zeros(spec.n_hinges, np.float32), coast)  # the torque applied over this tick
        theirs.qpos[mine.jnt_qposadr[mine.actuator_trnid[k, 0]]] = motor_angle / s.gear_ratio
        mujoco.mj_forward(mine, theirs)
        assert d.qfrc_applied[g] == pytest.approx(theirs.actuator_force[k] * s.gear_ratio, abs=1e-3 * stall)
    d.qpos[q], d.qvel[:] = 0.3, 0.0
    d.qvel[g] = 2 * np.pi / (s.cogging_periods * spec.firmware_dt * s.gear_ratio)  # a period a tick
    mujoco.mj_forward(m, d)
    plant.actuate(np.zeros(spec.n_hinges, np.float32), coast)
    ripple = -0.15 * s.gear_friction * math.sin(2 * math.pi * 0.3 / RIPPLE_PERIOD + 0.3)
    assert d.qfrc_applied[g] == pytest.approx(ripple, abs=1e-3 * stall * s.gear_ratio)  # no cogging left
    plant.hold_hinge(k, 0.0)
    pwm, brake = np.zeros(spec.n_hinges, np.float32), np.ones(spec.n_hinges, np.uint8)
    pwm[k] = 1.0
    for _ in range(2000):  # 2 s at stall against the held flap
        plant.sense()
        plant.hold_hinge(k, 0.0)
        plant.actuate(pwm, brake)
    assert d.act[m.actuator_actadr[k]] > 5.5


def test_missed_encoder_edges_accumulate(spec):
    """The emulated encoder misses edges now and then, as a counter does at speed: the count falls behind the
    shaft by the edges missed so far, in the direction of travel, and never comes back by itself."""
    plant = Plant(spec.replace(cogging=0.0), PlantOptions(encoder_miss=0.02), random.Random(1))  # (no detent's bounce)
    pwm = np.zeros(spec.n_hinges, np.float32)
    pwm[5] = 0.5
    brake = np.ones(spec.n_hinges, np.uint8)
    lag = []
    for _ in range(300):
        plant.sense()
        plant.actuate(pwm, brake)
        lag.append(plant.missed[5])
    lag = np.array(lag)
    turned = plant.counts[5] + plant.missed[5]
    assert turned > 100 and np.all(np.diff(lag) >= 0)  # only ever more missed, moving forward
    assert 0.005 * turned < lag[-1] < 0.05 * turned


def test_the_gate_refuses_a_reversal_30_ms_after_a_step_naming_the_current_and_the_moment(spec):
    """90 deg on every hinge, then back 30 ms later: each step from rest passes the gate (about 1.4 A), but
    played as one run the reversal meets the hinges at speed, back-EMF adds to the drive, and the gate
    refuses the scenario naming the current, the hinge and the moment."""
    twin = Twin(spec)
    step = np.radians(ZIGZAG_DEG)
    assert check_move(spec, np.zeros(6), step, twin=twin).passed
    assert check_move(spec, step, np.zeros(6), twin=twin).passed
    scenario = Scenario("reversal", np.zeros(6), [0.0, 0.03], [step, np.zeros(6)], 1.0)
    report = check_scenario(spec, scenario, twin=twin)
    assert [c.name for c in report.failed] == ["peak_current"]
    peak = report.failed[0]
    assert peak.value > spec.driver_peak_current
    with pytest.raises(GateRefused, match=r"peak_current 2\.\d+ A over limit 2\.000 A \(hinge \d at t=0\.03\d s\)"):
        enforce(report)
    calm = Scenario("steps", np.zeros(6), [0.0, 1.0], [step, np.zeros(6)], 2.0)
    assert check_scenario(spec, calm, twin=twin).passed  # the same steps, a second apart


@pytest.mark.parametrize("option, value, message", [
    ("--speed-scale", "1.3,0.7", "--speed-scale: range 1.3..0.7 must be finite, low <= high, within 0.1..10"),
    ("--backlash-deg", "abc", "--backlash-deg abc: expected a number or LOW,HIGH"),
    ("--latency-ms", "1,2,3", "--latency-ms 1,2,3: expected a number or LOW,HIGH"),
    ("--encoder-miss", "2", "--encoder-miss 2.0: a probability, 0 to 1"),
])
def test_emulate_refuses_a_bad_range_in_one_line(option, value, message, capsys):
    assert main(["emulate", option, value]) == 2
    assert capsys.readouterr().err.strip() == f"vrscroll emulate: error: {message}"
