"""The identification experiments and the per-hinge fit (issue 36) on plants nobody chose: the emulator draws
its plant within its stated ranges (each hinge its own values, the cogging, friction ripple and warming
winding the twin leaves out), lying flat on a table; the drawn values are read only to judge.

What is asserted is what the fit achieves on every plant tried (docs/tuning-hil-calibration.md,
"Identification", has the measured figures): every hinge fitted, each value inside its interval, the no-load
speed within 10 % of the drawn value, its 95 % interval holding it and no wider than x1.5. Not met, and asserted
only by the slow twenty-plant test (an expected failure): every hinge's no-load speed within 10 % with 90 % of
the intervals holding it (seeds 1-20: 118 of 120 within 10 %, seed 15's hinge 4 at x1.29, seed 20's hinge 2 at
x1.10); the issue's targets for the friction and the rotor inertia are measured by benchmarks/
bench_calibration.py --identify, not met, and not asserted."""

import json
import math
from pathlib import Path

import numpy as np
import pytest

from twin.cli import main as vrscroll
from twin.formats.profile import select_profile
from twin.hil.identification import (FITTED, HELD, PROFILED, SETTLE_S, SPEEDS, TOP_DEG, VALLEY_COST, VALLEY_GAIN,
                                     WHY, HingeFit, _valley, estimates, experiments, fit_hinge, outboard_first, program,
                                     residual, turned)
from twin.link.drawn_plant import EmulatedDevice, drawn_hinges, emulator_args
from twin.link.serial_link import program_message

SPEED_WIDTH = 1.5  # the no-load speed's 95 % interval at most this wide (high / low): the bound
SPEED_ERROR = 0.10  # the no-load speed within this of the drawn value: the bound


def test_each_experiment_is_a_program_the_device_accepts_from_rest_to_rest(spec):
    """The outermost hinge's and a heavy one's program at each speed, from the table and from a flap left raised:
    one the device accepts (the host's checks are the core's), braked SETTLE_S before and after its drive,
    raising then driving down, its window the table's side of the range up to TOP_DEG; faster programs raise
    harder."""
    top = math.radians(TOP_DEG) / spec.rad_per_count
    for k in (0, 2):
        for start in (0, int(math.radians(30) / spec.rad_per_count)):
            made = [program(spec, k, w, start) for w in SPEEDS]
            assert all(p is not None for p in made)
            for p in made:
                program_message(p.hinge, p.segments, p.window, p.timeout_s)  # ValueError outside the bounds
                (brake0, t0), (up, t_up), (down, t_down), (brake1, t1) = p.segments
                assert brake0 == brake1 == 0.0 and t0 == t1 == SETTLE_S
                assert up > 0 > down and t_up > 0 and t_down > 0
                assert p.window[1] == round(top) and p.window[0] < 0
                assert p.driven_s == pytest.approx(t_up + t_down)
            assert [p.segments[1][0] for p in made] == sorted(p.segments[1][0] for p in made)


@pytest.mark.parametrize("seed, hinges", [(3, (3,)), pytest.param(11, (0,), marks=pytest.mark.slow)])  # (the
# outermost hinge's fit, 35 s, in the slow suite beside the twenty plants; the default suite's second drawn plant
# is the replay test's below)
def test_each_hinge_is_identified_on_a_drawn_plant(spec, seed, hinges):
    """A hinge of a drawn plant (beside the root, lifting three flaps; the outermost, lifting one): every
    program starts from rest, turns within its window (raised, then driven down: the core's guard at the window's
    top never ends it first) and is fitted; its drive down never reaches the table; the fit gives every value
    inside its interval, the no-load speed within 10 % of the drawn value, its interval holding it and no wider
    than x1.5."""
    dev = EmulatedDevice(spec, seed)
    moves, device_s = experiments(dev.run_program, spec, hinges)
    for k in hinges:
        assert len(moves[k]) == len(SPEEDS) == turned(moves[k])
        for m in moves[k]:
            driven_down = (m.duty < 0) & np.isfinite(m.counts)
            assert np.all(m.counts[driven_down] > 0)  # off the table: the descent ends above it
        fit = fit_hinge(moves[k], spec)
        for p in FITTED:
            assert 0 < fit.low[p] <= fit.values[p] <= fit.high[p], p
        truth = dev.truth[k].no_load_speed
        assert fit.low["no_load_speed"] <= truth <= fit.high["no_load_speed"]
        assert fit.high["no_load_speed"] / fit.low["no_load_speed"] <= SPEED_WIDTH
        assert abs(fit.values["no_load_speed"] / truth - 1) <= SPEED_ERROR
    assert 1.0 < device_s < 15.0  # a hinge's experiments: seconds of device time


def test_the_experiments_run_each_side_from_its_outermost_hinge_in(spec):
    """Every hinge between the one run and the root flap is run after it: each hinge's experiments start with the
    flaps inboard of it flat on the table, none left raised (and sinking) by an earlier hinge's programs."""
    order = outboard_first(spec)
    assert sorted(order) == list(range(spec.n_hinges))
    for i, k in enumerate(order):
        inboard = range(k + 1, spec.root_flap) if k < spec.root_flap else range(spec.root_flap, k)
        assert all(order.index(j) > i for j in inboard), (k, order)


def test_a_hinge_whose_searches_end_apart_at_as_good_a_fit_carries_their_spread_and_says_so(spec):
    """The valley part of a hinge's interval: the local searches that end within VALLEY_COST of the best's cost
    lie as far apart as the moves leave the values open, and the interval carries that (x VALLEY_GAIN); a search
    that ends at a worse cost says nothing of it. Where that part is the widest, the value is not identifiable and
    its note says why."""
    m = len(FITTED)
    best, apart, worse = np.zeros(m), np.full(m, 0.6), np.full(m, -0.8)
    valley = _valley([best, apart, worse], [1.0, 1.0 + VALLEY_COST / 2, 1.5], best)
    assert valley == pytest.approx([0.6 * VALLEY_GAIN.get(p, 0.0) for p in FITTED])
    assert not _valley([best, worse], [1.0, 1.5], best).any()
    parts = {p: {"fit": 0.01, "valley": float(v), "left_out": 0.0} for p, v in zip(FITTED, valley)}
    values = {p: getattr(spec, p) for p in FITTED}
    sd = {p: math.sqrt(sum(v ** 2 for v in parts[p].values())) for p in FITTED}
    fit = HingeFit(2, values, {p: values[p] * math.exp(-1.96 * sd[p]) for p in FITTED},
                   {p: values[p] * math.exp(1.96 * sd[p]) for p in FITTED}, sd, parts,
                   {q: (1.0, 0.7, 1.6) for q in HELD}, 0.21, 100, 10)
    wide = {p: sd[p] > math.log(1.15) / 1.96 for p in FITTED}  # (its valley the widest part then)
    assert any(wide.values())
    for p, e in estimates(fit, spec, 0.15).items():
        assert e.identifiable is not wide[p]
        assert (WHY["valley"] in e.note) is wide[p]


def test_the_replays_place_the_hinges_run_before_where_the_device_left_them(spec):
    """Hinge 0's programs leave its flap off the table; hinge 1, run next, turns that flap too. Its moves carry
    where hinge 0 stood, and the twin's replay at the drawn values, placing it there, follows the device to the
    encoder's floor. (Round 4's programs left hinge 0 at 63-84 deg, where a replay with it flat missed the device
    by 0.31-0.42 rad/s rms against 0.23-0.26 placed, seeds 5, 8, 13; the turning programs leave it at 8-15 deg,
    where the two are alike: 0.231-0.249 flat, 0.232-0.246 placed.)"""
    dev = EmulatedDevice(spec, 13)
    moves, _ = experiments(dev.run_program, spec, hinges=(0, 1))
    left = dev.emulator.plant.counts[0] * spec.rad_per_count
    assert left > math.radians(5)  # raised, not on the table
    assert all(m.others[0] == pytest.approx(left, abs=spec.rad_per_count) for m in moves[1])
    drawn = {p: getattr(dev.truth[1], p) / getattr(spec, p)
             for p in ("no_load_speed", "gear_friction", "rotor_inertia", "gear_damping", "backdrive_efficiency")}
    assert np.sqrt(np.mean(residual(spec, 1, drawn, moves[1])[0] ** 2)) < 0.3


@pytest.mark.slow
def test_calibrate_serial_writes_each_hinges_values_into_the_profile_and_tune_reads_them(emulator, capsys):
    """`vrscroll calibrate --serial PORT --device NAME --json -` on a drawn plant lying flat over a real pty:
    per hinge value, low, high and identifiable for each profiled parameter (SI), each hinge's no-load speed within
    the issue's 10 % of the drawn value and at least 5 of the 6 intervals holding it, the profile keeping them, and
    `vrscroll tune --device NAME` tuning over each hinge's intervals (pushing nothing where no gains keep the
    limit over them: then naming the limit and the interval that drives the worst case)."""
    emu = emulator("--lying-flat", *emulator_args(4))
    hinges = drawn_hinges(emu)
    assert vrscroll(["calibrate", "--serial", emu.port, "--device", "flat4", "--json", "-"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert [h["hinge"] for h in out["hinges"]] == list(range(6))
    holding = 0
    for h in out["hinges"]:
        for p in PROFILED:
            e = h["parameters"][p]
            assert isinstance(e["identifiable"], bool) and 0 < e["low"] <= e["value"] <= e["high"]
        e, truth = h["parameters"]["no_load_speed"], hinges[h["hinge"]]["no_load_speed"]
        assert abs(e["value"] / truth - 1) <= SPEED_ERROR
        holding += e["low"] <= truth <= e["high"]
    # 95 % intervals: all six hold on only 74 % of plants; 4 or fewer of 6 happen on 3 % of them
    assert holding >= 5, f"{holding} of 6 no-load speed intervals hold the drawn value"
    held = out["holdout"]  # the closed-loop run after the experiments, which no fit saw, kept in the profile
    assert [r["hinge"] for r in held["hinges"]] == list(range(6)) and Path(held["run"], "run.json").exists()
    assert all(0 < r["floor_deg"] <= r["rmse_identified_deg"] + 0.05 for r in held["hinges"]), held
    profile = select_profile("flat4")
    assert profile.mount == "flat"  # as the experiments ran: later commands hold the twin on its table
    assert profile.ranges().hinges == tuple({p: (h["parameters"][p]["low"], h["parameters"][p]["high"])
                                             for p in PROFILED} for h in out["hinges"])
    rc = vrscroll(["tune", "--device", "flat4", "--population", "8", "--generations", "2", "--json", "-"])
    tuned = json.loads(capsys.readouterr().out)
    assert set(tuned["goal"]["ranges"]) == set(PROFILED)
    assert [list(r) for r in tuned["goal"]["hinge_ranges"]] == [list(PROFILED)] * 6
    # where no gains keep the limit over every hinge's intervals, tune says which limit and which interval
    assert rc == 0 or (rc == 1 and tuned["limits_broken"] and tuned["worst_case_range"][0]["parameter"] in PROFILED)


def test_calibrate_serial_refuses_a_profile_that_says_the_device_is_not_lying_flat(capsys):
    assert vrscroll(["device", "create", "hung", "--mount", "hanging"]) == 0
    capsys.readouterr()
    assert vrscroll(["calibrate", "--serial", "/dev/no-such-port", "--device", "hung"]) == 2
    err = capsys.readouterr().err
    assert "lying flat" in err and "--mount flat" in err and len(err.strip().splitlines()) == 1


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="not met: on these 20 plants x 6 hinges (round 4's ninth session, the "
                   "experiments outboard first) 119/120 no-load speeds within 10 % (seed 20's hinge 2 x1.102) and "
                   "119/120 intervals no wider than x1.5 (seed 17's hinge 4, x1.7); with DISCREPANCY calibrated on "
                   "seeds 1-10, 113 of 120 intervals holding the drawn value (56 of the held-out 60), x1.14 wide "
                   "(median) (benchmarks/bench_calibration.py --identify's fits)")
def test_twenty_drawn_plants_every_hinges_no_load_speed(spec):
    """The issue's criteria on 20 drawn plants x 6 hinges, for the value the experiments pin down: the no-load
    speed within 10 % of the drawn value and its 95 % interval no wider than x1.5 on every hinge, the intervals
    holding the drawn value in at least 90 % of cases. (The friction's and the rotor inertia's figures:
    benchmarks/bench_calibration.py --identify.)"""
    held, n, misses = 0, 0, []
    for seed in range(1, 21):
        dev = EmulatedDevice(spec, seed)
        moves, _ = experiments(dev.run_program, spec)
        for k, m in moves.items():
            fit, truth = fit_hinge(m, spec), dev.truth[k].no_load_speed
            v, lo, hi = fit.values["no_load_speed"], fit.low["no_load_speed"], fit.high["no_load_speed"]
            n += 1
            held += lo <= truth <= hi
            if abs(v / truth - 1) > SPEED_ERROR or hi / lo > SPEED_WIDTH:
                misses.append(f"seed {seed} hinge {k}: {v / truth:.3f} x the drawn value, interval x{hi / lo:.3f} wide")
    assert not misses, misses
    assert held >= 0.9 * n, f"{held} of {n} intervals hold the drawn value"
