"""Field build time and memory against the mesh's face count (issue 22): one torus 200 mm across (tube 60 mm
thick), tessellated ever finer, its fields built on the default 3 mm grid, each size in a process of its own
so that the peak memory (the process's largest resident set, MB) is that build's alone; one core.

    .venv/bin/python benchmarks/bench_fields.py [--faces 5000,20000,80000,200000,500000] [--out results/fields]

Writes OUT/fields.json and OUT/fields.md; prints a line per size.
"""

import argparse
import json
import math
import os
import subprocess
import sys
from pathlib import Path

ONE_CORE = {var: "1" for var in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")}
MAJOR, MINOR = 0.07, 0.03  # m: the torus's radii


def build_one(faces: int) -> dict:
    """Build the fields of a torus of about `faces` faces (2 x sections x tube sections, sections = 2 x tube
    sections) in this process: its face and grid point counts, build time (s) and peak memory (MB)."""
    import resource
    import time

    import trimesh

    from twin.morphpatch.fields import build_fields

    tube = max(3, round(math.sqrt(faces / 4)))
    mesh = trimesh.creation.torus(MAJOR, MINOR, major_sections=2 * tube, minor_sections=tube)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    t0 = time.perf_counter()
    fields = build_fields(mesh, disk_cache=False)
    return {"faces": len(mesh.faces), "grid_points": int(fields.sdf.size), "build_s": round(time.perf_counter() - t0, 2),
            "peak_memory_MB": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024),
            "memory_before_MB": round(before)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--faces", default="5000,20000,80000,200000,500000", help="face counts, comma-separated")
    parser.add_argument("--out", default="results/fields")
    parser.add_argument("--one", type=int, help=argparse.SUPPRESS)  # a child process: build this size, print JSON
    args = parser.parse_args()
    if args.one:
        print(json.dumps(build_one(args.one)))
        return
    rows = []
    for faces in (int(f) for f in args.faces.split(",")):
        out = subprocess.run([sys.executable, __file__, "--one", str(faces)], capture_output=True, text=True,
                             env={**os.environ, **ONE_CORE}, check=True)
        row = json.loads(out.stdout.splitlines()[-1])
        rows.append(row)
        print(f"{row['faces']:8d} faces, {row['grid_points']:,} grid points: build {row['build_s']:6.1f} s, "
              f"peak memory {row['peak_memory_MB']} MB (before the build {row['memory_before_MB']} MB)", flush=True)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "fields.json").write_text(json.dumps(rows, indent=2) + "\n")
    lines = ["| faces | grid points | build s | peak memory MB |", "|---:|---:|---:|---:|"]
    lines += [f"| {r['faces']} | {r['grid_points']} | {r['build_s']} | {r['peak_memory_MB']} |" for r in rows]
    (out / "fields.md").write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
