"""CBS with real MuJoCo contact, the start generator and the evaluation runner."""

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh

from twin.morphpatch.approximation import frames, pose_from_mm_deg
from twin.cli import main
from twin.evaluation.cbs import CbsSimulator
from twin.evaluation.lock import folder_lock
from twin.evaluation.target_collision import collision_error, convex_parts
from twin.formats.records import RecordLog
from twin.evaluation.table1 import METHODS, _shape_seed, read_records, run_evaluation, summarize, write_tables
from twin.morphpatch.fields import exact_signed_distance
from twin.morphpatch.resting import DEEP_SHARE_MAX, DEEPEST_MAX
from twin.morphpatch.sampling import touch_surface_points
from twin.morphpatch.shapes import load_shape
from twin.evaluation.starts import MAX_TILT, STANDOFF, approach_starts
from twin.morphpatch.surface_metrics import msd_hd

PENETRATION = 0.002  # m: the deepest a CBS touch-surface sample may sit inside the target


@pytest.mark.parametrize("start", [[0, 0, 230, 0, 0, 0], [5, -5, 240, 12, -10, 0], [-5, 3, 250, -15, 8, 4]])
def test_cbs_on_a_flat_face_rests_on_it(spec, start):
    """From above the cube's top face, level or tilted (tilted, it ended 14.8 mm MSD off before: pressed
    along its tilted normal and fixed there)."""
    cube = load_shape("cube")
    sim = CbsSimulator(spec, cube)
    result = sim.run(pose_from_mm_deg(start))
    msd, _ = msd_hd(spec, cube, result.root_pose, result.angles)  # (HD: a tilted start snaps off centre, and
    assert msd < 1e-3  # the end flap may overhang the face's edge by a few mm, flat)
    assert np.abs(np.degrees(result.angles)).max() < 1.0


def test_cbs_on_a_cylinder_wraps_without_going_through(spec):
    cyl = load_shape("cylinder")
    top = cyl.bounds[1][2] * 1e3
    # the cylinder's axis is along y: the device's row (x) runs around it
    sim = CbsSimulator(spec, cyl)
    result = sim.run(pose_from_mm_deg([0, 0, top + 20, 0, 0, 0]))
    assert np.all(result.angles < 0)  # convex touch surface, the way a cylinder bends it
    flaps = frames(spec, result)
    pts = touch_surface_points(spec, flaps, result.widths)
    depth, _ = exact_signed_distance(cyl, pts)
    assert depth.min() > -PENETRATION
    # the root and both tips end in contact (within 1 mm); flaps between may be held off by the tips,
    # as bending until contact leaves them on a convex target
    for i in (0, spec.root_flap, spec.n_flaps - 1):
        flap_depth, _ = exact_signed_distance(cyl, touch_surface_points(spec, flaps[i:i + 1], result.widths[i:i + 1]))
        assert np.abs(flap_depth).min() < 1e-3, i


def test_cbs_ends_where_the_firmware_stops_it(spec):
    """Table 1's arch start 9: the target throws flap 2 past its range, the firmware faults and refuses the
    next stage's targets, which ended the whole Table 1 run; the device stops where it stands, and CBS too."""
    arch = load_shape("arch")
    sim = CbsSimulator(spec, arch)
    result = sim.run(approach_starts(arch, 50, seed=_shape_seed(0, "arch"))[9])
    assert sim.twin.firmware.faults != 0  # the case this is about
    assert np.all(np.abs(result.angles) <= spec.hinge_limit)


@pytest.mark.slow  # suite time: the default suite stays under 10 min on 2 cores (run with -m slow)
def test_collision_shape_keeps_the_true_shape():
    torus = load_shape("torus")
    parts = convex_parts(torus)
    assert len(parts) > 1  # a single hull would fill the hole
    err = collision_error(torus, parts)
    assert err.mean < 0.5e-3 and max(err.mesh_to_parts_max, err.parts_outside_max) < 5e-3
    hull_err = collision_error(torus, [torus.convex_hull])
    assert hull_err.mesh_to_parts_max > 0.03  # the hull misses the inner ring by centimetres


def test_starts_are_seeded_and_documented():
    mesh = load_shape("arch")
    a, b, c = approach_starts(mesh, 20, seed=3), approach_starts(mesh, 20, seed=3), approach_starts(mesh, 20, seed=4)
    assert np.array_equal(a, b) and not np.allclose(a, c)
    anchors = a[:, :3, 3]
    d, closest = exact_signed_distance(mesh, anchors)
    assert np.all(d > STANDOFF[0] - 1e-6) and np.all(d < STANDOFF[1] + 1e-6)
    normals = (anchors - closest) / d[:, None]
    tilt = np.arccos(np.clip(np.einsum("ij,ij->i", normals, a[:, :3, 2]), -1, 1))
    assert tilt.max() <= MAX_TILT + math.radians(1.0)


@pytest.mark.parametrize("name", ["cube", "torus", "stairs", "curved_stairs"])
def test_starts_come_from_where_a_user_is(name):
    """Above the plane the shape rests on and outside it (before: 6-20 of 50 from beneath the ground)."""
    mesh = load_shape(name)
    anchors = approach_starts(mesh, 50, seed=0)[:, :3, 3]
    assert np.all(anchors[:, 2] > mesh.bounds[0][2])
    assert np.all(exact_signed_distance(mesh, anchors)[0] > 0.0)


def _evaluate_and_resume(out, shapes, n_starts):
    """Evaluate the first shape, cut the log mid-record, evaluate all: every (shape, start, method) once."""
    run_evaluation(out, shapes[:1], n_starts=n_starts, seed=0, workers=2, progress=False)
    log = out / "results.jsonl"
    lines = log.read_text().splitlines()
    log.write_text("\n".join(lines[:-1]) + "\n" + lines[-1][:20])  # interrupted mid-record
    assert len({r["start"] for r in read_records(log)}) == n_starts - 1
    records = run_evaluation(out, shapes, n_starts=n_starts, seed=0, workers=2, progress=False)
    assert len(records) == len(shapes) * n_starts * len(METHODS)
    assert len({(r["shape"], r["start"], r["method"]) for r in read_records(log)}) == len(records)
    for r in records:  # what the twin made of each: the gate's verdicts and the reached shape
        assert r["gate_range_ok"] and r["twin_msd_mm"] >= 0 and 0 <= r["share_within"] <= 1
        assert 0 <= r["inside_percent"] <= 100 and (r["inside_depth_mm"] > 0.5) == (r["inside_percent"] > 0)
    return records


@pytest.mark.slow  # 87 s on 2 cores (cube and cylinder, CBS's convex parts and ours' fields built afresh): the
# default suite reached 540 of its 600 s; the default suite keeps the resume past a cut line on the records
# (test_results_resume_past_a_cut_line_and_count_each_start_once) and the refusal of a second run into a folder
def test_an_interrupted_evaluation_resumes_and_writes_its_tables(tmp_path):
    out = tmp_path / "ev"
    records = _evaluate_and_resume(out, ["cube", "cylinder"], 2)
    md, csv_path = write_tables(summarize(records), out)
    assert "paper MSD" in md.read_text() and "MSD on the twin" in md.read_text() and csv_path.exists()
    assert "inside (deepest mm)" in md.read_text() and "inside_mean_percent" in csv_path.read_text()
    with pytest.raises(ValueError, match="holds a run"):
        run_evaluation(out, ["cube", "cylinder"], n_starts=3, seed=0, workers=1, progress=False)


@pytest.mark.slow
def test_small_evaluation_keeps_the_papers_order_and_ours_rests_outside(tmp_path):
    """Table 1 on every paper shape, 3 starts each. Full close to CBS (the paper's order). Ours, issue 37's
    bar rather than issue 22's retired goal of lying below full (full lies inside the target, 28 % of its touch
    surface 39 mm deep on the torus): every pose of ours rests on the target from outside (deepest point at
    most 3 mm inside, at most 5 % of the touch surface more than 2 mm inside) or is one its search found no
    resting pose for, which `approximate` refuses (at most a quarter of the starts); ours' MSD is reported
    beside full's, and its inside share and depth beside theirs."""
    shapes = ["cube", "torus", "arch", "cone", "cylinder", "ellipsoid", "stairs", "curved_stairs"]
    out = tmp_path / "ev"
    records = _evaluate_and_resume(out, shapes, 3)
    ours = [r for r in records if r["method"] == "refined"]
    assert all("rests" not in r for r in records if r["method"] != "refined")
    refused = [(r["shape"], r["start"]) for r in ours if not r["rests"]]
    assert len(refused) <= len(ours) // 4, refused
    for r in ours:
        if r["rests"]:
            assert r["inside_depth_mm"] <= DEEPEST_MAX * 1e3, r
            assert r["inside_over_2mm_percent"] <= DEEP_SHARE_MAX * 100, r
    rows = summarize(records)
    mean = {(r["shape"], r["method"]): r for r in rows}
    for shape in shapes:
        assert mean[(shape, "full")]["msd_mean_mm"] < mean[(shape, "cbs")]["msd_mean_mm"] * 1.2, shape
        assert "msd_drop_from_full" in mean[(shape, "refined")], shape  # ours' MSD against full's, in the table
    table = write_tables(rows, out)[0].read_text()
    for shape in shapes:
        line = next(ln for ln in table.splitlines() if ln.startswith(f"| {shape} | refined |"))
        r = mean[(shape, "refined")]
        assert f"{r['msd_mean_mm']:.2f} ± " in line and f"{r['inside_mean_percent']:.1f} % (" in line, line


def test_a_damaged_coacd_cache_file_is_built_again_with_a_notice(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("VRSCROLL_CACHE", str(tmp_path))
    ring = trimesh.creation.annulus(0.02, 0.04, 0.02, sections=8)  # not convex: CoACD splits it
    first = convex_parts(ring)
    [path] = (tmp_path / "coacd").glob("*.npz")
    path.write_bytes(path.read_bytes()[:200])
    capsys.readouterr()
    again = convex_parts(ring)
    assert len(again) == len(first) > 1
    assert f"cache file {path} is damaged" in capsys.readouterr().err
    assert len(convex_parts(ring)) == len(first) and capsys.readouterr().err == ""


def test_a_second_evaluate_into_one_folder_is_refused(tmp_path, capsys):
    """Two runs into one folder once computed and stored every record twice."""
    out = tmp_path / "eval"
    with folder_lock(out, "test"):
        assert main(["evaluate", "--out", str(out), "--shapes", "cube", "--starts", "2"]) == 2
    err = capsys.readouterr().err
    assert "another vrscroll evaluate is writing to this folder" in err and str(out) in err
    assert not (out / "results.jsonl").exists()
    # a holder that dies (here killed) leaves no lock behind: the kernel drops it with the process
    holder = subprocess.Popen(
        [sys.executable, "-c", "import sys, time\nfrom twin.evaluation.lock import folder_lock\n"
         "with folder_lock(sys.argv[1], 'holder'):\n    print('locked', flush=True)\n    time.sleep(60)\n", str(out)],
        cwd=Path(__file__).resolve().parents[2], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        with pytest.raises(ValueError, match=f"pid {holder.pid}"):
            with folder_lock(out, "test"):
                pass
    finally:
        holder.kill()
        holder.wait()
        holder.stdout.close()
    with folder_lock(out, "test"):
        pass


RESULT = {"msd_mm": 1.0, "hd_mm": 2.0, "time_ms": 3.0}  # what summarize takes from each record


def test_results_resume_past_a_cut_line_and_count_each_start_once(tmp_path):
    """A write cut short (a full disk) left half a line; a start was recorded twice, another only in part:
    Table 1 counts each complete start once, and the next record starts on a line of its own."""
    log = tmp_path / "results.jsonl"
    rows = [{"shape": "cube", "start": s, "method": m, **RESULT} for s in (0, 1) for m in METHODS]
    rows += [rows[0]] + [{"shape": "cube", "start": 2, "method": METHODS[0], **RESULT}]  # repeated, partial
    log.write_text("".join(json.dumps(r) + "\n" for r in rows) + '{"shape": "cube", "sta')
    records = read_records(log)
    assert sorted({(r["start"], r["method"]) for r in records}) == sorted((s, m) for s in (0, 1) for m in METHODS)
    assert len(records) == 2 * len(METHODS)  # start 0 once, start 2 not yet complete
    with RecordLog(log) as f:
        f.write({"shape": "cube", "start": 2, "method": METHODS[-1], **RESULT})
    lines = log.read_text().splitlines()
    assert all(json.loads(line) for line in lines)  # the cut line went, nothing was appended onto it
