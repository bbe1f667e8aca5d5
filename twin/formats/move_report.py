"""A move report's rows in a command's JSON (`vrscroll simulate --json`'s and `demo --json`'s "hinges", `tune
--json`'s "before" and "after"): one object a hinge, units in the keys (deg, s, counts, A)."""

from __future__ import annotations

import math

from twin.records.move_report import MoveReport


def move_rows(report: MoveReport) -> list[dict]:
    """Per hinge: hinge, target_deg, final_deg, settle_time_s (NaN: not settled), overshoot_deg,
    steady_state_error_deg, steady_state_error_counts, peak_current_A (rounded for reading)."""
    return [{"hinge": k,
             "target_deg": round(math.degrees(report.target[k]), 3),
             "final_deg": round(math.degrees(report.final[k]), 3),
             "settle_time_s": round(float(report.settle_time[k]), 4),
             "overshoot_deg": round(math.degrees(report.overshoot[k]), 3),
             "steady_state_error_deg": round(math.degrees(report.steady_state_error[k]), 3),
             "steady_state_error_counts": round(float(report.steady_state_error_counts[k]), 2),
             "peak_current_A": round(float(report.peak_current[k]), 3)}
            for k in range(len(report.target))]
