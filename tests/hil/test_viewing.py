"""Looking rather than reading: a recorded run as a video and a contact sheet rendered off-screen, a Rerun
recording read back with Rerun's own reader, `compare` on two runs, the HIL report's figures, and one settle
time for one move whoever reports it."""

import json
import math
import os
import re
import subprocess
import sys

import av
import mujoco
import numpy as np
import pytest
import trimesh

from cli import vrscroll as vrscroll_process
from conftest import FIXED_PLANT
from rerun_read import read_rrd
from twin.cli import main as vrscroll
from twin.device.mjcf import load_model
from twin.formats.run import read_run
from twin.formats.scenario import read_scenario, scenario_of_steps, write_scenario
from twin.hil.compare import METRICS, compare
from twin.hil.mirror import mirror
from twin.hil.record import run_hil
from twin.link.emulator_process import EmulatorProcess
from twin.link.serial_link import Link
from twin.live.morph import TwinMorpher
from twin.sim.gate import check_move
from twin.sim.response import move_settle_time, settle_time
from viz.render import FPS, SIZE, DeviceCamera, frame_times
from viz.viewer import MIN_PLAYED_S, TWIN_ALPHA, pair_model, run_frames, slowmo_for

TWO_STEPS = scenario_of_steps("two", [(0.0, [20, 10, 5, 5, 10, 20]), (0.6, [-15, 30, -20, 15, 0, -25])], 1.2)


@pytest.fixture(scope="module")
def runs(tmp_path_factory, spec):
    """Two recorded runs of one scenario on the emulator (RUN folders a and b), recorded once for the module
    (the tests only read them)."""
    folder = tmp_path_factory.mktemp("runs")
    emu = EmulatorProcess(folder / "emulator.jsonl", *FIXED_PLANT, "--zeroed")
    try:
        write_scenario(folder / "s.toml", TWO_STEPS)
        with Link(emu.port) as link:
            assert mirror(link, spec, np.zeros(spec.n_hinges), tolerance_deg=30.0).ok
            for name in "ab":
                run_hil(link, spec, read_scenario(folder / "s.toml", spec), folder / name)
    finally:
        emu.stop()
    return folder / "a", folder / "b"


def _no_display(monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)


def test_settle_time_is_when_the_error_last_entered_the_band_and_stayed():
    t = np.arange(0, 1.0, 0.001)
    err = np.where(t < 0.3, 5.0, 0.5)
    err[(t >= 0.5) & (t < 0.6)] = 3.0  # leaves the band again: only the last entry counts
    assert settle_time(t, err, 1.0, 0.1) == pytest.approx(0.6)
    assert math.isnan(settle_time(t[t < 0.65], err[t < 0.65], 1.0, 0.1))  # not yet 0.1 s in the band
    assert settle_time(t[t < 0.7], err[t < 0.7], 1.0, 0.1) == pytest.approx(0.6)  # 0.1 s in the band, counting the tick
    # several channels: all at once, i.e. the latest one
    both = np.stack([err, np.where(t < 0.8, 2.0, 0.0)], axis=1)
    assert settle_time(t, both, 1.0, 0.1) == pytest.approx(0.8)
    assert math.isnan(settle_time(t, np.full_like(t, 2.0), 1.0, 0.1))


def test_one_move_has_one_settle_time_in_the_gate_simulate_the_live_service_and_mirror(spec, emulator, tmp_path):
    targets = np.radians([25.0, -12.0, 30.0, 30.0, -12.0, 25.0])
    gate = check_move(spec, np.zeros(spec.n_hinges), targets)
    ts = gate.settle_time
    assert 0 < ts < 1 and ts == pytest.approx(move_settle_time(spec, gate.prediction.time, gate.prediction.counts,
                                                               gate.prediction.target_counts))
    # the gate's number is the time the hinges entered the band, not when the twin stopped (the hold later)
    assert gate.prediction.duration == pytest.approx(ts + spec.settle_hold, abs=2 * spec.firmware_dt)
    # simulate: the slowest hinge's settle time is the move's
    out = vrscroll_process("simulate", *[repr(float(a)) for a in np.degrees(targets)], "--json", "-",
                           "--plot", tmp_path / "s.png")
    assert out.returncode == 0, out.stderr
    assert max(h["settle_time_s"] for h in json.loads(out.stdout)["hinges"]) == pytest.approx(ts, abs=1e-4)
    # the live service's twin (its `done` carries the outcome's settle time)
    morpher = TwinMorpher(spec)
    morpher.open()
    outcome = morpher.morph(targets, lambda event: None)
    assert outcome.status == "done" and outcome.settle_time == pytest.approx(ts)
    # mirror: the twin's number beside the device's, and the device's is the definition applied to its frames
    with Link(emulator().port) as link:
        assert mirror(link, spec, np.zeros(spec.n_hinges), tolerance_deg=30.0).ok  # from its limp boot pose
        res = mirror(link, spec, targets, tolerance_deg=30.0)
    # the twin's settle time for the move from where the device rests, with the PID integral it holds there
    # (lifted from its boot sag: not the gate's from flat above, whose integral is empty)
    assert res.ok and res.twin_settle_time == pytest.approx(res.report.settle_time)
    tel = res.telemetry
    target = np.rint(tel.target / spec.rad_per_count)
    assert res.settle_time == pytest.approx(move_settle_time(spec, tel.time, tel.counts, target, start=0.0), abs=1e-9)
    assert f"settle time {res.settle_time:.3f} s (twin: {res.twin_settle_time:.3f} s)" in res.message


def test_a_recorded_run_as_a_video_and_a_contact_sheet_without_a_display(runs, spec, monkeypatch, capsys):
    _no_display(monkeypatch)
    a, _ = runs
    assert vrscroll(["view", str(a)]) == 0
    out = capsys.readouterr().out
    assert f"video {a / 'view.mp4'}" in out
    run = read_run(a, spec)
    t, rows = run_frames(run, spec)
    # progress while the frames render (a run of seconds took a minute, silent): each line counts up to the last
    done = [int(m) for m in re.findall(r"rendered (\d+)/(?:\d+) frames", out)]
    total = int(round((t[-1] - t[0]) * FPS)) + 1
    assert len(done) >= 5 and done == sorted(done) and done[-1] == total and f"/{total} frames" in out
    with av.open(str(a / "view.mp4")) as video:
        stream = video.streams.video[0]
        assert stream.average_rate == FPS
        frames = [f.to_ndarray(format="rgb24") for f in video.decode(stream)]
    # the run's duration at the video's frame rate, device and twin side by side
    assert len(frames) == int(round((t[-1] - t[0]) * FPS)) + 1
    assert frames[0].shape == (SIZE[0], 2 * SIZE[1], 3)
    # the frames differ as the flaps move
    change = [np.abs(frames[i + 1].astype(int) - frames[i]).mean() for i in range(len(frames) - 1)]
    assert max(change) > 0.5 and np.abs(frames[-1].astype(int) - frames[0]).mean() > 1.0
    # the device's pixels are where the model puts them: each flap's centre, projected through the camera,
    # is drawn (not background) in both panels, and the background where no flap is stays dark
    cam = DeviceCamera(spec)
    data = mujoco.MjData(cam.model)
    n = spec.n_hinges
    for i, when in ((0, t[0]), (len(frames) - 1, t[-1])):
        angles = [np.interp(when, t, rows[:, k]) for k in range(2 * n)]
        cam.render(angles[:n])
        data.qpos[cam.qadr] = np.asarray(angles[:n])[None]
        mujoco.mj_kinematics(cam.model, data)
        for f in range(n + 1):
            r, c = cam.pixel(data.geom(f"flap{f}_visual").xpos)
            for panel in (0, 1):
                assert frames[i][r, c + panel * SIZE[1]].max() > 60, (i, f, panel)
        assert frames[i][5, 5].max() < 20
    cam.close()
    assert (a / "view.png").stat().st_size > 20_000
    # with a display, the viewer shows both devices in one place, the twin's translucent
    model = pair_model(spec)
    assert model.njnt == 2 * load_model(spec).njnt
    twin_geoms = [i for i in range(model.ngeom) if model.body(model.geom_bodyid[i]).name.startswith("twin/")]
    assert twin_geoms and all(model.geom_rgba[i, 3] == pytest.approx(TWIN_ALPHA) for i in twin_geoms)


def test_a_rerun_recording_holds_the_device_and_the_runs_traces(runs, spec, tmp_path, capsys):
    a, _ = runs
    assert vrscroll(["view", str(a), "--rerun", str(tmp_path / "a.rrd")]) == 0
    columns = read_rrd(tmp_path / "a.rrd")
    run = read_run(a, spec)
    for k in range(spec.n_hinges):
        for source, rec in (("device", run.device), ("twin", run.twin)):
            got = np.array(columns[(f"/hinge{k}/angle_deg/{source}", "Scalars:scalars")]).ravel()
            assert np.allclose(got, np.degrees(rec.angle[:, k]), atol=1e-6)
            assert np.allclose(np.array(columns[(f"/hinge{k}/current_A/{source}", "Scalars:scalars")]).ravel(),
                               rec.current[:, k], atol=1e-6)
            assert (f"/hinge{k}/duty/{source}", "Scalars:scalars") in columns
        diff = np.array(columns[(f"/hinge{k}/difference_deg", "Scalars:scalars")]).ravel()
        assert np.allclose(diff, np.degrees(run.device.angle[:, k] - np.interp(run.device.time, run.twin.time,
                                                                               run.twin.angle[:, k])), atol=1e-6)
        assert np.allclose(columns[(f"/hinge{k}/angle_deg/device", "time")], run.device.time - run.device.time[0])
    for source in ("device", "twin"):
        for f in range(spec.n_hinges + 1):
            moves = np.array(columns[(f"/world/{source}/flap{f}_visual", "Transform3D:translation")])
            assert len(moves) == int(round((run.device.time[-1] - run.device.time[0]) * FPS)) + 1
    # the root flap stays; the outer flaps move as the hinges turn
    outer = np.array(columns[("/world/device/flap0_visual", "Transform3D:translation")])
    assert np.ptp(outer, axis=0).max() > 0.005


def test_compare_sets_runs_side_by_side_and_the_report_defines_its_metrics(runs, spec, tmp_path, capsys):
    a, b = runs
    png, js = tmp_path / "c.png", tmp_path / "c.json"
    assert vrscroll(["compare", str(a), str(b), "--png", str(png), "--json", str(js)]) == 0
    out = capsys.readouterr().out
    assert "mean settle time device s" in out and png.stat().st_size > 20_000
    doc = json.loads(js.read_text())
    ra = read_run(a, spec)
    expected = compare(spec, ra.device, ra.twin, [t for t, _ in ra.changes])
    assert [r["rmse_deg"] for r in doc["runs"][str(a)]] == [r["rmse_deg"] for r in expected]
    assert set(doc["metrics"]) == {key for key, _, _ in METRICS}
    assert vrscroll(["compare", str(a)]) == 2
    # the HIL report: a readable figure per hinge, every column of its table defined under it
    from viz.hil_report import write_report

    report = write_report(spec, a).read_text()
    for _, label, meaning in METRICS:
        assert f"**{label}**: {meaning}" in report
    with av.open(str(a / "hinge0.png")) as img:  # PyAV reads PNGs too
        frame = next(img.decode(video=0))
        assert frame.width >= 900 and frame.height >= 900


def _no_warning(stderr: str) -> bool:
    """Nothing but progress lines: no warning, no X server complaint, no colour codes."""
    return not any(w in stderr.lower() for w in ("warn", "x server", "\x1b", "error"))


def test_drawing_commands_print_no_warning_without_a_display(tmp_path):
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY", "MUJOCO_GL",
                                                            "VTK_DEFAULT_OPENGL_WINDOW")}
    # a 10 deg move settles in a tenth of a second: --slowmo 3 plays it three times slower (by default it would
    # last MIN_PLAYED_S, 60 frames to render: the default is checked below without rendering)
    sim = subprocess.run([sys.executable, "-m", "twin.cli", "simulate", "10", "0", "0", "0", "0", "0", "--view",
                          "--view-out", str(tmp_path / "v"), "--plot", str(tmp_path / "s.png"), "--slowmo", "3",
                          "--json", str(tmp_path / "s.json")],
                         capture_output=True, text=True, env=env, cwd=tmp_path, timeout=300)
    assert sim.returncode == 0 and _no_warning(sim.stderr), sim.stderr
    assert (tmp_path / "v.mp4").is_file() and (tmp_path / "s.png").is_file()
    assert "slow motion x3)" in sim.stdout
    moved_s = json.loads((tmp_path / "s.json").read_text())["simulated_s"]  # ms rounded: the frames within one
    with av.open(str(tmp_path / "v.mp4")) as video:
        assert video.streams.video[0].average_rate == FPS
        frames = sum(1 for _ in video.decode(video=0))
    assert abs(frames - (moved_s * 3 * FPS + 1)) <= 1.5, (frames, moved_s)
    approx = subprocess.run([sys.executable, "-m", "twin.cli", "approximate", "--shape", "cylinder", "--png",
                             str(tmp_path / "a.png")], capture_output=True, text=True, env=env, cwd=tmp_path,
                            timeout=300)
    assert approx.returncode == 0 and _no_warning(approx.stderr), approx.stderr
    assert (tmp_path / "a.png").stat().st_size > 20_000


@pytest.mark.parametrize("seconds", [0.05, 0.27, 1.0, 5.0])
def test_a_short_move_is_slowed_to_last_the_least_a_person_sees(seconds):
    """A 0.27 s morph made a 9-frame video (issue 39): by default a move shorter than MIN_PLAYED_S is played
    slowed to last that long, a longer one in real time; --slowmo FACTOR says how slow."""
    slowmo = slowmo_for(seconds)
    frames = frame_times(0.0, seconds, FPS * slowmo)
    assert len(frames) == int(round(max(seconds, MIN_PLAYED_S) * FPS)) + 1
    assert frames[-1] == pytest.approx(seconds, abs=0.5 / (FPS * slowmo))  # the move's own times, to its end
    assert slowmo_for(seconds, 4.0) == 4.0


def test_no_off_screen_context_is_one_line_naming_what_to_install(tmp_path):
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    env.update(MUJOCO_GL="egl", MUJOCO_EGL_DEVICE_ID="99")  # an EGL device that is not there
    r = subprocess.run([sys.executable, "-m", "twin.cli", "simulate", "10", "0", "0", "0", "0", "0", "--view",
                        "--view-out", str(tmp_path / "v"), "--plot", str(tmp_path / "s.png")],
                       capture_output=True, text=True, env=env, cwd=tmp_path, timeout=300)
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert "no off-screen OpenGL context" in r.stderr and "libegl1" in r.stderr
    assert not (tmp_path / "v.mp4").exists()


def test_mirror_simulate_and_a_move_on_a_target_write_rerun_recordings(spec, emulator, tmp_path, capsys):
    # mirror: the device's telemetry and the twin's prediction of the one move
    emu = emulator()
    with Link(emu.port) as link:
        assert mirror(link, spec, np.zeros(spec.n_hinges), tolerance_deg=30.0).ok
    out = vrscroll_process("mirror", "--angles", "15,0,-10,-10,0,15", "--serial", emu.port, "--rerun",
                           tmp_path / "m.rrd", "--log", tmp_path / "m.jsonl")
    assert out.returncode == 0, out.stderr
    m = read_rrd(tmp_path / "m.rrd")
    device = np.array(m[("/hinge0/angle_deg/device", "Scalars:scalars")]).ravel()
    twin = np.array(m[("/hinge0/angle_deg/twin", "Scalars:scalars")]).ravel()
    assert abs(device[-1] - 15) < 1.5 and abs(twin[-1] - 15) < 1.5 and abs(device[0]) < 1.5
    assert ("/hinge2/difference_deg", "Scalars:scalars") in m and ("/hinge5/current_A/device", "Scalars:scalars") in m
    # simulate: the twin alone, its angles those of the reported move
    capsys.readouterr()
    assert vrscroll(["simulate", "20", "0", "0", "0", "0", "-20", "--rerun", str(tmp_path / "s.rrd"), "--json", "-",
                     "--plot", str(tmp_path / "s.png")]) == 0
    s = read_rrd(tmp_path / "s.rrd")
    final = [s[(f"/hinge{k}/true_angle_deg/twin", "Scalars:scalars")][-1][0] for k in range(spec.n_hinges)]
    assert final == pytest.approx([h["final_deg"] for h in json.loads(capsys.readouterr().out)["hinges"]], abs=1e-3)
    assert not any(k[0].startswith("/world/device") for k in s)  # no device in a twin's move
    # a move on a target (demo's): the target mesh too, coloured by distance to the device where it ended
    from twin.sim.twin import Twin
    from viz.rerun_log import log_move

    trace = Twin(spec).move_to(np.radians([20.0, 0, 0, 0, 0, -20]), max_time=0.5)
    box = trimesh.creation.box((0.3, 0.3, 0.05), trimesh.transformations.translation_matrix((0.0, 0.0, -0.05)))
    log_move(tmp_path / "d.rrd", spec, trace, box, np.eye(4), np.full(spec.n_flaps, spec.flap_pitch))
    d = read_rrd(tmp_path / "d.rrd")
    colours = np.array(d[("/world/target", "Mesh3D:vertex_colors")][0])  # logged once: one row, a colour per vertex
    assert len(d[("/world/target", "Mesh3D:vertex_positions")][0]) == len(colours) == len(box.vertices)
    assert np.ptp(colours) > 0  # the top corners nearer the device than the bottom ones


def test_a_run_the_device_stopped_names_the_fault_and_can_still_be_watched(emulator, tmp_path, spec, monkeypatch,
                                                                           capsys):
    emu = emulator("--jam-hinge", "2", "--jam-after-s", "0.3")  # hinge 2 jams mid-run: the device's stall check stops it
    write_scenario(tmp_path / "s.toml", TWO_STEPS)
    # (a tolerance no hinge reaches: at the default 5 deg the host's divergence stop comes first, test_mount.py's)
    assert vrscroll(["hil", str(tmp_path / "s.toml"), "--serial", emu.port, "--out", str(tmp_path / "run"),
                     "--tolerance-deg", "90"]) == 2
    err = capsys.readouterr().err
    assert "device stopped itself" in err and "STALL on hinge 2" in err, err
    _no_display(monkeypatch)
    assert vrscroll(["view", str(tmp_path / "run")]) == 0  # what was recorded up to the stop
    assert (tmp_path / "run" / "view.mp4").stat().st_size > 0
