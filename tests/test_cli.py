"""The command line, run as a user runs it."""

import json

import pytest

from cli import vrscroll


def test_simulate_json_and_trace(tmp_path):
    out = vrscroll("simulate", "60", "-45", "0", "30", "90", "-100", "--json", "--trace", str(tmp_path / "t.csv"))
    assert out.returncode == 0, out.stderr
    report = json.loads(out.stdout)
    assert report["settled"] and len(report["hinges"]) == 6
    assert {"settle_time_s", "overshoot_deg", "steady_state_error_counts", "peak_current_A"} <= set(report["hinges"][0])
    assert (tmp_path / "t.csv").exists()


def test_simulate_bad_angle_is_a_clear_error():
    out = vrscroll("simulate", "60", "-45", "0", "30", "90", "130")
    assert out.returncode == 2
    assert "hinge 5: target 130.00 deg is outside the hinge range +-112.5 deg" in out.stderr
    assert "Traceback" not in out.stderr
    out = vrscroll("simulate", "1", "2")
    assert out.returncode == 2 and "expected 6 hinge targets" in out.stderr


def test_model_check_and_help():
    assert vrscroll("model", "--check").returncode == 0
    for cmd in ("simulate", "model"):
        out = vrscroll(cmd, "--help")
        assert out.returncode == 0 and "usage" in out.stdout


@pytest.mark.parametrize("variant", ["full", "refined"])
def test_demo_approximates_validates_simulates_and_draws(tmp_path, variant):
    png, js = tmp_path / "demo.png", tmp_path / "demo.json"
    out = vrscroll("demo", "--variant", variant, "--png", str(png), "--json", str(js))
    assert out.returncode == 0, out.stdout + out.stderr
    report = json.loads(js.read_text())
    assert report["approximation"]["variant"] == variant
    assert report["gate"]["passed"]
    assert report["approximation"]["msd_mm"] < 2.0  # the cylinder is followed closely
    assert report["morph"]["msd_after_morph_mm"] < report["approximation"]["msd_mm"] + 1.0
    assert png.stat().st_size > 10_000


def test_user_error_is_one_line_under_python_dash_m():
    """`python -m twin.cli` runs the module as __main__; its UserError must still be caught (no traceback)."""
    r = vrscroll("approximate", "--shape", "cube", "--start", "1,2")
    assert r.returncode == 2
    assert "Traceback" not in r.stderr and "expected six finite numbers" in r.stderr
