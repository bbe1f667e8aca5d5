"""Psychometric fitting: the paper's four curves come back from trials drawn from them."""

import json

import numpy as np
import pytest

from twin.cli import main
from twin.perception.thresholds import detection_rule, paper_fits
from twin.formats.trials import read_trials, write_trials
from twin.perception.psychometric import analyse, counts, curve, detected, fit, simulate_trials, threshold

RULE = detection_rule()
FITS = {f.surface: f for f in paper_fits()}
SCALE = 20  # participants x 20 (240 people x 4 repeats per condition): enough power to place the thresholds


def test_detection_rule_on_hand_made_rows():
    natural = [False, False, True, False, True]
    confidence = [2, 3, 5, 5, 1]
    assert detected(natural, confidence, RULE["min_confidence"]).tolist() == [False, True, False, True, False]


def test_threshold_solver_known_answers():
    assert threshold(-0.08, 3.78, 0.5) == pytest.approx(47.25)
    assert threshold(-0.08, 3.78, 0.75) == pytest.approx((np.log(3) + 3.78) / 0.08)
    assert threshold(-0.08, 3.78, 0.75) == pytest.approx(60.98, abs=0.005)
    assert threshold(-0.04, 3.41, RULE["cdt_level"]) == pytest.approx(85.25)  # curved convex: beyond 50 mm


@pytest.mark.parametrize("surface", FITS)
def test_noise_free_proportions_give_back_a_and_b(surface):
    f = FITS[surface]
    x = np.array(f.conditions)
    n = np.full(len(x), 1e6)
    got = fit(x, n * curve(x, f.a, f.b), n)
    assert got.a == pytest.approx(f.a, abs=1e-3) and got.b == pytest.approx(f.b, abs=1e-3)


@pytest.mark.parametrize("surface", FITS)
def test_trials_from_the_paper_curves_give_back_a_b_and_thresholds(surface, tmp_path):
    f = FITS[surface]
    rows = simulate_trials(f.a, f.b, f.conditions, f.participants * SCALE, f.repeats, np.random.default_rng(1),
                           RULE["min_confidence"])
    write_trials(tmp_path / "trials.csv", rows, f.unit)
    trials = read_trials(tmp_path / "trials.csv")
    [report] = analyse(trials, RULE, resamples=1000, seed=2)
    got, u = report["fit"], f.unit
    assert abs(got[f"a_per_{u}"] - f.a) < 3 * got[f"a_se_per_{u}"]
    assert abs(got["b"] - f.b) < 3 * got["b_se"]
    assert report["bootstrap"]["by"] == "participant"
    lo, hi = min(f.conditions), max(f.conditions)
    for key in ("cdt", "dt"):
        t, true = report["thresholds"][key], threshold(f.a, f.b, RULE[f"{key}_level"])
        # the truth lies in the 95 % bootstrap CI widened by half its width on each side (about 3 SE)
        ci_lo, ci_hi = t[f"ci_{u}"]
        estimate = t[f"value_{u}"] if t["position"] == "inside" else t[f"extrapolated_{u}"]
        assert ci_lo <= estimate <= ci_hi
        assert ci_lo - (ci_hi - ci_lo) / 2 <= true <= ci_hi + (ci_hi - ci_lo) / 2
        if lo <= true <= hi:  # angled surfaces: inside the tested range
            assert t["position"] == "inside" and t[f"extrapolated_{u}"] is None
        else:  # curved surfaces: reported outside, never as a threshold
            assert t["position"] == "above" and t[f"value_{u}"] is None
            assert t["statement"].startswith(f"above the tested range (> {hi:g} {u})")
            assert t["inside_fraction"] < 0.05


def test_each_surface_is_fitted_on_its_own(tmp_path):
    rng = np.random.default_rng(3)
    rows = []
    for name in ("angled convex", "angled concave"):
        f = FITS[name]
        rows += [r | {"surface": name} for r in simulate_trials(f.a, f.b, f.conditions, 12, 4, rng)]
    write_trials(tmp_path / "two.csv", rows, "deg")
    reports = analyse(read_trials(tmp_path / "two.csv"), RULE, resamples=200)
    assert [r["surface"] for r in reports] == ["angled convex", "angled concave"]
    assert [r["trials"] for r in reports] == [288, 288]


def test_no_detection_is_reported_not_fitted(tmp_path):
    path = tmp_path / "calm.csv"
    path.write_text("condition_mm,natural,confidence\n0,yes,5\n25,Natural,4\n50,no,2\n50,TRUE,1\n")
    [report] = analyse(read_trials(path), RULE)
    assert report["fit"]["degenerate"] == "no trial detected" and report["fit"]["a_per_mm"] is None
    assert report["bootstrap"] is None
    for t in report["thresholds"].values():
        assert t["position"] == "above" and t["value_mm"] is None and t["extrapolated_mm"] is None
        assert t["statement"] == "above the tested range (> 50 mm); no trial detected"


def test_a_jump_from_none_to_all_is_not_estimable():
    got = fit([0, 10, 20, 30], [0, 0, 4, 4], [4, 4, 4, 4])
    assert got.a is None and "between 10 and 20" in got.degenerate


def test_answers_spellings_and_counts(tmp_path):
    path = tmp_path / "t.csv"
    path.write_text("# a comment\nParticipant,Condition_deg,Natural,Confidence\n"
                    "p1,0,Yes,5\np1,0,unnatural,3\n\np1,15,FALSE,4\np1,15,1,2\np1,15,0,1\n")
    trials = read_trials(path)
    assert trials.unit == "deg" and trials.natural.tolist() == [True, False, False, True, False]
    x, n, k = counts(trials.condition, detected(trials.natural, trials.confidence, 3))
    assert x.tolist() == [0, 15] and n.tolist() == [2, 3] and k.tolist() == [1, 1]
    [report] = analyse(trials, RULE, resamples=100)
    assert report["bootstrap"]["by"] == "trials within condition"


HEADER = "condition_mm,natural,confidence\n"


@pytest.mark.parametrize("text, message", [
    ("", "empty file"),
    ("# nothing\n", "empty file"),
    (HEADER, "no trials after the header"),
    ("condition,natural,confidence\n0,yes,1\n", ":1: name the unit of column 'condition'"),
    ("condition_mm,natural\n0,yes\n", ":1: missing column(s) confidence"),
    (HEADER + "0,yes,1\nten,no,4\n", ":3: condition 'ten' is not a number"),
    (HEADER + "0,yes,1\n10,no,6\n", ":3: confidence '6' is not an integer 1-5"),
    (HEADER + "0,yes,0\n", ":2: confidence '0' is not an integer 1-5"),
    (HEADER + "0,maybe,1\n", ":2: natural 'maybe' is not one of"),
    (HEADER + "0,yes\n", ":2: 2 fields, the header has 3"),
    (HEADER + "10,yes,1\n10,no,5\n", "fewer than 2 distinct conditions"),
    ("surface,condition_mm,natural,confidence\ns,0,yes,1\ns,5,no,4\nt,0,yes,1\n",
     "fewer than 2 distinct conditions (surface 't')"),
])
def test_bad_files_are_clear_errors(tmp_path, text, message):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(ValueError) as exc:
        read_trials(path)
    assert str(path) in str(exc.value) and message in str(exc.value)


def test_command_line_end_to_end(tmp_path, capsys):
    data, out = tmp_path / "angled-concave.csv", tmp_path / "out"
    assert main(["psychometric", str(data), "--example", "angled concave"]) == 0
    assert main(["psychometric", str(data), "--out", str(out), "--bootstrap", "300",
                 "--compare-paper", "angled concave"]) == 0
    text = capsys.readouterr().out
    assert "CDT (f = 0.50)" in text and "DT  (f = 0.75)" in text and "paper, angled concave" in text
    result = json.loads((out / "fit.json").read_text())
    [report] = result["surfaces"]
    assert result["unit"] == "deg" and {"a_per_deg", "a_se_per_deg", "b", "b_se"} <= set(report["fit"])
    assert {"value_deg", "ci_deg", "inside_fraction"} <= set(report["thresholds"]["dt"])
    assert result["paper"]["dt_printed_deg"] == 64.87
    assert (out / "psychometric.png").stat().st_size > 10_000

    assert main(["psychometric", str(data), "--json", "-", "--bootstrap", "0"]) == 0
    assert json.loads(capsys.readouterr().out)["surfaces"][0]["bootstrap"] is None

    assert main(["psychometric", str(data), "--compare-paper", "curved convex"]) == 2
    assert "is in mm" in capsys.readouterr().err
    (tmp_path / "bad.csv").write_text("condition_mm,natural,confidence\n0,perhaps,3\n")
    assert main(["psychometric", str(tmp_path / "bad.csv")]) == 2
    err = capsys.readouterr().err
    assert "bad.csv:2: natural 'perhaps'" in err and "Traceback" not in err


@pytest.mark.parametrize("surface", ["curved convex", "curved concave", "angled convex"])
def test_the_plot_is_drawn_for_every_paper_curve(tmp_path, surface):
    """Each paper curve's sample (seed 0) fits and plots; curved convex once broke the error bars (-1e-17)."""
    data, out = tmp_path / "trials.csv", tmp_path / "out"
    assert main(["psychometric", str(data), "--example", surface]) == 0
    assert main(["psychometric", str(data), "--out", str(out), "--bootstrap", "200"]) == 0
    assert (out / "psychometric.png").stat().st_size > 10_000
