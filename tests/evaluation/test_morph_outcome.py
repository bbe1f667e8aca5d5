"""The morph outcome (twin.evaluation.morph_outcome), the one `vrscroll demo`, Table 1 and the sweeps share: on the
real twin, a morph the gate lets through comes to rest near its targets and is measured there; one it refuses
leaves the device flat, with no report and no morph time."""

import math

import numpy as np
import pytest

from twin.evaluation.morph_outcome import morph_outcome
from twin.evaluation.table1 import twin_outcome
from twin.morphpatch.approximation import approximate, pose_from_mm_deg
from twin.morphpatch.fields import build_fields
from twin.morphpatch.shapes import load_shape, side_starts
from twin.morphpatch.surface_metrics import match
from twin.records.approximation import Approximation
from twin.sim.twin import Twin


@pytest.fixture(scope="module")
def cylinder(spec):
    mesh = load_shape("cylinder")
    fields = build_fields(mesh)
    return mesh, fields, approximate(fields, pose_from_mm_deg(side_starts(mesh)[0]), spec, "full")


def test_a_morph_comes_to_rest_where_it_is_measured(spec, cylinder):
    mesh, fields, approx = cylinder
    twin = Twin(spec)
    out = morph_outcome(spec, mesh, fields, approx, twin)
    assert out.gate.passed, out.gate.text()
    assert np.array_equal(out.reached, twin.angles)  # where the twin rests after the move and the hold
    assert np.abs(out.reached - approx.angles).max() < math.radians(2.0)  # near the targets, not at them
    assert out.settle_time == pytest.approx(np.max(out.report.settle_time)) and 0 < out.settle_time < 1.0
    assert out.end == match(spec, mesh, approx.root_pose, out.reached, approx.widths)
    assert 0.0 <= out.redirection["share_within"] <= 1.0


def test_a_refused_morph_leaves_the_device_flat(spec, cylinder):
    """Angles past the hinge range (a record the approximation would never make): the gate refuses the range,
    nothing moves, and Table 1's columns say so rather than make up a morph time."""
    mesh, fields, approx = cylinder
    beyond = Approximation(approx.root_pose, np.full(spec.n_hinges, spec.hinge_limit + 0.1), approx.widths, 0.0,
                          "full")
    out = morph_outcome(spec, mesh, fields, beyond, Twin(spec))
    assert not out.gate.passed and out.gate.prediction is None and out.report is None
    assert np.abs(out.reached).max() < math.radians(0.5) and math.isnan(out.settle_time)
    row = twin_outcome(spec, mesh, fields, Twin(spec), beyond)
    assert row["gate_range_ok"] is False and row["morph_time_s"] is None
    assert row["twin_msd_mm"] == pytest.approx(match(spec, mesh, beyond.root_pose, np.zeros(spec.n_hinges),
                                                     beyond.widths).msd * 1e3, abs=0.05)
