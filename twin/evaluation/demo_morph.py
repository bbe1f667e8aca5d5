"""`vrscroll demo`'s path, once: approximate a target from a start pose, gate and simulate the morph on the
twin, check the pen redirection the reached shape needs against the perception thresholds, and say each step
as it goes (deg, mm). The pictures are viz.demo_pictures'."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from twin.evaluation.morph_outcome import MorphOutcome, morph_outcome
from twin.formats.move_report import move_rows
from twin.formats.target import approximation_json
from twin.morphpatch.approximation import approximate, measured
from twin.morphpatch.fields import build_fields
from twin.morphpatch.surface_metrics import inside_text, match_json
from twin.records.approximation import Approximation
from twin.records.profile import Profile
from twin.sim.gate import redirection_check


@dataclasses.dataclass(frozen=True)
class DemoMorph:
    """The demo's outcome: the approximation, the morph on the twin (its gate with the redirection's check) and
    the --json document (without the pictures' names)."""

    approx: Approximation
    outcome: MorphOutcome
    doc: dict

    @property
    def failed(self) -> str | None:
        """What failed, in words (the gate's refusals, no pose resting from outside), or None."""
        gate = self.outcome.gate
        return "; ".join(([] if gate.passed else ["the gate refused: " + ", ".join(c.name for c in gate.failed)])
                         + ([] if self.approx.rests is not False else ["no pose resting from outside"])) or None


def demo_morph(profile: Profile, twin, name: str, mesh, start: list, pose: np.ndarray, variant: str, strict: bool,
               say=print) -> DemoMorph:
    """The path on the profile's `twin` (twin.sim.twin.Twin) to the target `name` (mesh) from `pose` (4x4;
    start: as given, x y z mm, roll pitch yaw deg); strict: the redirection beyond the thresholds fails the gate.
    say(line) for each step."""
    spec = profile.spec
    say(f"[1/5] fields of {name} (cached after the first run) ...")
    fields = build_fields(mesh)
    approximate(fields, pose, spec, variant)  # warm-up: loads compiled code
    approx = measured(spec, mesh, approximate(fields, pose, spec, variant))
    say(f"[2/5] {variant} approximated in {approx.time * 1e3:.2f} ms: MSD {approx.msd * 1e3:.2f} mm, "
        f"HD {approx.hd * 1e3:.2f} mm; hinges {np.degrees(approx.angles).round(1).tolist()} deg")
    say(f"      {approx.inside:.0%} of the touch surface inside the target, up to {approx.depth * 1e3:.1f} mm deep"
        + ("" if approx.rests is not False else "; ours found no pose resting on it from outside"))
    say("[3/5] validating and simulating the morph on the twin (firmware PID at 1 kHz) ...")
    outcome = morph_outcome(spec, mesh, fields, approx, twin, profile.gains)
    gate, report, end, redirection = outcome.gate, outcome.report, outcome.end, outcome.redirection
    settle = round(outcome.settle_time, 4)
    final_err = (round(math.degrees(np.abs(report.steady_state_error).max()), 3) if report is not None
                 else float("nan"))
    # the residual mismatch where the twin ended, as the pen redirection must cover it
    gate.checks.append(redirection_check(redirection, strict=strict))
    say(gate.text())
    say(f"      morph settled in {settle:.3f} s (slowest hinge), largest final error {final_err:.2f} deg; "
        f"MSD where the twin ended {end.msd * 1e3:.2f} mm (HD {end.hd * 1e3:.2f} mm); {inside_text(end)}")
    say(f"[4/5] pen redirection over the reached shape: {redirection['share_within']:.1%} of the touch surface "
        f"within {redirection['position_threshold_mm']:g} mm / {redirection['rotation_threshold_deg']:g} deg "
        f"(largest {redirection['largest_offset_mm']:.1f} mm, {redirection['largest_rotation_deg']:.1f} deg)")
    doc = {"device_profile": profile.label, "target": name, "start_mm_deg": start,
           "approximation": approximation_json(approx), "gate": gate.to_dict(), "redirection": redirection,
           "morph": {"settle_time_s": settle, "largest_final_error_deg": final_err,
                     "hinges": move_rows(report) if report is not None else [], **match_json(end, "_after_morph")}}
    return DemoMorph(approx, outcome, doc)
