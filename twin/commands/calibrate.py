"""`vrscroll calibrate RUN... --holdout RUN`: fit the twin's plant to recorded HIL runs (docs/tuning-hil-calibration.md)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from twin.cli import UserError


def add_arguments(p) -> None:
    p.add_argument("runs", nargs="+", metavar="RUN", help="HIL run folders (vrscroll hil --out) to fit to")
    p.add_argument("--holdout", metavar="RUN", help="a HIL run folder not fitted to: fit error before/after")
    p.add_argument("--out", default="spec.calibrated.toml", help="calibrated spec TOML (default %(default)s)")
    p.add_argument("--max-iter", type=int, default=25, help="Levenberg-Marquardt iterations (default %(default)s)")
    p.add_argument("--json", action="store_true", help="print the result as JSON")


def run(args) -> int:
    from twin.hil.calibration import calibrate, trace_rmse, write_spec
    from twin.hil.runs import load_run
    from twin.device.spec import load_spec

    spec = load_spec()
    try:
        runs = [load_run(r) for r in args.runs]
        holdout = load_run(args.holdout) if args.holdout else None
    except (OSError, KeyError, ValueError) as exc:
        raise UserError(f"cannot read a HIL run: {exc}") from None
    for r in runs + ([holdout] if holdout else []):
        if len(r["device"]["time_s"]) < 10:
            raise UserError(f"{r['dir']}: fewer than 10 device frames; nothing to fit")
        if "before" not in r["meta"]:
            raise UserError(f"{r['dir']}: recorded without the device's state before the run; record it again")
    res = calibrate(runs, spec, max_iter=args.max_iter)
    write_spec(args.out, res.spec, res.values,
               "calibrated from " + ", ".join(str(Path(r)) for r in args.runs) + " (vrscroll calibrate)")
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
