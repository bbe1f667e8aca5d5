"""The approximation on shapes nobody tuned it for (twin/evaluation/shape_corpus.py, issue 22): per shape and variant the
mean MSD and HD over seeded starts all round it (exact mesh, mm), whether any anchor crossed the solid, the
default start outside it; the share of each one's touch surface inside the shape and how deep; how many of
full's poses have flaps in contact (the gate refuses them), and full's MSD with its angles unrolled from the tips until
none touch (the pose the device could take); how much worse than full ours is on its worst start, over all starts and
over those where full's flaps are apart; how many poses of full's and ours have a flap through the
target (twin.morphpatch.refinement.flaps_through: a wall, a plate, a tube); ours' time per approximation (median, p99, one core); each shape's field build (s,
peak memory of the process, MB) against its face count.

    PYTHONPATH=$PWD .venv/bin/python benchmarks/bench_corpus.py [--seed 0] [--starts 10] [--out results/corpus]
        [--cached-fields]

--cached-fields reads each shape's fields from the cache ($VRSCROLL_CACHE) where they are there: the fits are the
same, the build column is then the load time (said in the table's heading). Built afresh, the fields of the first
13 shapes took 55 min on the shared 2-core machine at load 13-20 (3-5 min each for the 20 k-face ones).

Writes OUT/corpus.json and OUT/corpus.md; prints the table.
"""

import os

for var in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[var] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
import resource  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import igl  # noqa: E402
import numpy as np  # noqa: E402

from twin.device.flap_collision import collides, flap_boxes  # noqa: E402
from twin.device.spec import load_spec  # noqa: E402
from twin.evaluation.shape_corpus import corpus, crossed, starts  # noqa: E402
from twin.morphpatch.approximation import VARIANTS, approximate, pose_from_mm_deg, root_pose  # noqa: E402
from twin.morphpatch.fields import build_fields  # noqa: E402
from twin.morphpatch.default_start import default_start  # noqa: E402
from twin.morphpatch.refinement import flaps_through, uncurled  # noqa: E402
from twin.morphpatch.surface_metrics import match  # noqa: E402

def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--starts", type=int, default=10)
    parser.add_argument("--out", default="results/corpus")
    parser.add_argument("--cached-fields", action="store_true",
                        help="fields from the cache where there (the build column is then their load time)")
    args = parser.parse_args()
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})
    spec = load_spec()
    boxes = flap_boxes(spec)
    rows, times = [], []
    for name, mesh in corpus(args.seed):
        t0 = time.perf_counter()
        fields = build_fields(mesh, disk_cache=args.cached_fields)
        build = time.perf_counter() - t0
        default = pose_from_mm_deg(default_start(mesh, fields, spec))
        default_out = float(igl.signed_distance(default[None, :3, 3], mesh.vertices, mesh.faces)[0][0])
        row = {"shape": name, "faces": len(mesh.faces), "extent_mm": (mesh.extents * 1e3).round(0).tolist(),
               "field_build_s": round(build, 2),
               "peak_memory_MB": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 0),
               "default_start_outside_mm": round(default_out * 1e3, 1)}
        per = {v: [] for v in VARIANTS}
        crossings = {v: 0 for v in VARIANTS}
        contact = {v: 0 for v in VARIANTS}
        through = {v: 0 for v in VARIANTS}
        full_uncurled, full_apart = [], []  # full_apart: per start, whether full's pose has its flaps apart
        for k, start in enumerate(starts(mesh, args.starts, args.seed * 1000 + len(rows))):
            snapped = root_pose(fields, start, spec)[:3, 3]
            for v in VARIANTS:
                approximate(fields, start, spec, v) if k == 0 else None  # compiled code loaded before timing
                a = approximate(fields, start, spec, v)
                if v == "refined":
                    times.append(a.time)
                per[v].append(match(spec, mesh, a.root_pose, a.angles, a.widths))
                touching = collides(boxes, a.angles, 0.0)
                contact[v] += touching
                through[v] += flaps_through(fields, spec, a.root_pose, a.angles, a.widths) > 0
                if v == "full":  # the pose the device could take: unrolled from its tips until no flaps touch
                    full_uncurled.append(match(spec, mesh, a.root_pose, uncurled(spec, a.angles), a.widths).msd)
                    full_apart.append(not touching)
                crossings[v] += crossed(mesh, start[:3, 3], snapped) or crossed(mesh, snapped, a.root_pose[:3, 3])
        for v in VARIANTS:
            m = np.array(per[v])
            row[v] = {"msd_mm": round(float(m[:, 0].mean() * 1e3), 2), "hd_mm": round(float(m[:, 1].mean() * 1e3), 2),
                      "worst_start_msd_mm": round(float(m[:, 0].max() * 1e3), 2), "crossed": crossings[v],
                      "inside_percent": round(float(m[:, 2].mean() * 100), 1),
                      "inside_depth_mm": round(float(m[:, 3].max() * 1e3), 1), "flaps_in_contact": contact[v],
                      "flaps_through_target": through[v]}
        full, ours = np.array(per["full"])[:, 0], np.array(per["refined"])[:, 0]
        row["ours_below_full"] = round(float(1 - ours.mean() / full.mean()), 3)
        row["full_uncurled_msd_mm"] = round(float(np.mean(full_uncurled) * 1e3), 2)
        row["ours_below_full_uncurled"] = round(float(1 - ours.mean() / np.mean(full_uncurled)), 3)
        row["ours_worse_by_mm"] = round(float((ours - full).max() * 1e3), 2)
        apart = np.array(full_apart)
        row["ours_worse_by_mm_where_full_apart"] = round(float((ours - full)[apart].max() * 1e3), 2) if apart.any() else None
        rows.append(row)
        print(f"{name:16s} faces {row['faces']:6d} build {build:5.1f} s  MSD full {row['full']['msd_mm']:6.2f} "
              f"no_hcevf {row['no_hcevf']['msd_mm']:6.2f} ours {row['refined']['msd_mm']:6.2f} mm "
              f"({row['ours_below_full']:+.0%} below full), worst start {row['ours_worse_by_mm']:+.2f} mm; crossed "
              f"{sum(crossings.values())}; default start {row['default_start_outside_mm']} mm out", flush=True)
    t = np.array(times) * 1e3
    summary = {"seed": args.seed, "starts_per_shape": args.starts, "shapes": len(rows),
               "fields_from_cache": args.cached_fields,
               "ours_time_ms": {"median": round(float(np.median(t)), 2), "p99": round(float(np.percentile(t, 99)), 2)},
               "mean": {v: {"msd_mm": round(float(np.mean([r[v]["msd_mm"] for r in rows])), 2),
                            "hd_mm": round(float(np.mean([r[v]["hd_mm"] for r in rows])), 2)} for v in VARIANTS},
               "shapes_where_ours_is_20pct_below_full": sum(r["ours_below_full"] >= 0.2 for r in rows
                                                           if r["full"]["msd_mm"] > 1.0),
               "shapes_where_ours_is_20pct_below_full_uncurled": sum(r["ours_below_full_uncurled"] >= 0.2 for r in rows
                                                                    if r["full"]["msd_mm"] > 1.0),
               "full_poses_in_flap_contact": sum(r["full"]["flaps_in_contact"] for r in rows),
               "shapes_where_ours_is_worse_by_over_half_a_mm": sum(r["ours_worse_by_mm"] > 0.5 for r in rows),
               "shapes_where_ours_is_worse_by_over_half_a_mm_where_full_apart": sum(
                   (r["ours_worse_by_mm_where_full_apart"] or 0.0) > 0.5 for r in rows),
               "poses_with_a_flap_through_the_target": {v: sum(r[v]["flaps_through_target"] for r in rows)
                                                        for v in VARIANTS},
               "shapes_where_full_is_above_1mm": sum(r["full"]["msd_mm"] > 1.0 for r in rows),
               "anchors_that_crossed": sum(r[v]["crossed"] for r in rows for v in VARIANTS)}
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "corpus.json").write_text(json.dumps({"summary": summary, "shapes": rows}, indent=2) + "\n")
    lines = [f"| shape | faces | {'fields load (cache) s' if args.cached_fields else 'build s'} | full MSD / HD mm | no_hcevf | ours | ours below full | worst start | "
             "worst start, full's flaps apart | full's poses in flap contact | full uncurled MSD | "
             "inside % (deepest mm) full / ours | poses with a flap through the target, full / ours |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        f, o = r["full"], r["refined"]
        lines.append(f"| {r['shape']} | {r['faces']} | {r['field_build_s']} | {f['msd_mm']} / {f['hd_mm']} | "
                     f"{r['no_hcevf']['msd_mm']} / {r['no_hcevf']['hd_mm']} | {o['msd_mm']} / {o['hd_mm']} | "
                     f"{r['ours_below_full']:.0%} | {r['ours_worse_by_mm']:+.2f} mm | "
                     f"{_mm(r['ours_worse_by_mm_where_full_apart'])} | {f['flaps_in_contact']} of "
                     f"{args.starts} | {r['full_uncurled_msd_mm']} | {f['inside_percent']} ({f['inside_depth_mm']}) / "
                     f"{o['inside_percent']} ({o['inside_depth_mm']}) | {f['flaps_through_target']} / "
                     f"{o['flaps_through_target']} of {args.starts} |")
    (out / "corpus.md").write_text("\n".join(lines) + "\n")
    print(json.dumps(summary, indent=2))


def _mm(x) -> str:
    """A signed length in mm for the table, or a dash where there is none."""
    return "–" if x is None else f"{x:+.2f} mm"


if __name__ == "__main__":
    main()
