"""`vrscroll calibrate RUN... --holdout RUN`: fit the twin's plant to recorded HIL runs (docs/tuning-hil-calibration.md)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from twin.cli import UserError
from twin.device.spec import SPEC_PATH, load_spec
from twin.formats.run import read_run
from twin.formats.spec_toml import write_spec_toml
from twin.hil.calibration import calibrate, trace_rmse


def add_arguments(p) -> None:
    p.add_argument("runs", nargs="+", metavar="RUN", help="HIL run folders (vrscroll hil --out) to fit to")
    p.add_argument("--holdout", metavar="RUN", help="a HIL run folder not fitted to: fit error before/after")
    p.add_argument("--out", default="spec.calibrated.toml", help="calibrated spec TOML (default %(default)s)")
    p.add_argument("--max-iter", type=int, default=25, help="Levenberg-Marquardt iterations (default %(default)s)")
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    p.add_argument("--incomplete", action="store_true",
                   help="also fit runs that did not complete (killed or interrupted while recorded): what they "
                        "recorded is used, and each is named (default: such a run is refused)")


def run(args) -> int:
    spec = load_spec()
    try:
        runs = [read_run(r, spec, incomplete=args.incomplete) for r in args.runs]
        holdout = read_run(args.holdout, spec, incomplete=args.incomplete) if args.holdout else None
    except (OSError, ValueError) as exc:
        raise UserError(f"cannot read a HIL run: {exc}" + ("" if args.incomplete or "did not complete" not in str(exc)
                                                            else " (--incomplete uses what it recorded)")) from None
    for r in runs + ([holdout] if holdout else []):
        if r["meta"]["status"] != "complete":
            print(f"note: {r['dir']} did not complete (status {r['meta']['status']!r}); using the "
                  f"{len(r['device']['time_s'])} device frames it recorded", file=sys.stderr)
        if len(r["device"]["time_s"]) < 10:
            raise UserError(f"{r['dir']}: fewer than 10 device frames; nothing to fit")
        if "before" not in r["meta"]:
            raise UserError(f"{r['dir']}: recorded without the device's state before the run; record it again")
    res = calibrate(runs, spec, max_iter=args.max_iter)
    write_spec_toml(args.out, SPEC_PATH, res.values,
                    "calibrated from " + ", ".join(str(Path(r)) for r in args.runs) + " (vrscroll calibrate)",
                    header="Calibrated device spec, written by `vrscroll calibrate` (see docs/tuning-hil-calibration.md).")
    out = {"spec": args.out, "scales": {k: round(v, 4) for k, v in res.scales.items()},
           "values": res.values, "fit_rmse_deg": {"before": round(res.rmse_before, 4),
                                                  "after": round(res.rmse_after, 4)},
           "iterations": res.iterations, "replays": res.evaluations}
    if holdout:
        before, after = trace_rmse(holdout, spec, spec), trace_rmse(holdout, res.spec, spec)
        out["holdout"] = {"run": args.holdout, "rmse_before_deg": before.round(4).tolist(),
                          "rmse_after_deg": after.round(4).tolist(),
                          "overall_before_deg": round(float(np.sqrt(np.mean(before ** 2))), 4),
                          "overall_after_deg": round(float(np.sqrt(np.mean(after ** 2))), 4)}
    if args.json:
        print(json.dumps(out, indent=2))
        return 0
    print(f"fitted in {res.iterations} iterations ({res.evaluations} twin replays); x spec value:")
    for k, v in res.scales.items():
        print(f"  {k:<14} x{v:.3f}  = {res.values[k]:.6g}")
    print(f"fit RMSE (training runs, hinge angles): {res.rmse_before:.3f} deg -> {res.rmse_after:.3f} deg")
    if holdout:
        h = out["holdout"]
        print("held-out RMSE per hinge, deg: before " + " ".join(f"{x:.3f}" for x in h["rmse_before_deg"]))
        print("                              after  " + " ".join(f"{x:.3f}" for x in h["rmse_after_deg"]))
        print(f"held-out RMSE overall (every frame of every hinge), deg: {h['overall_before_deg']:.3f} -> "
              f"{h['overall_after_deg']:.3f}")
    print(f"calibrated spec written to {args.out}")
    return 0
