"""The command line, run as a user runs it."""

import json

import pytest

from cli import vrscroll
from twin.cli import main


def test_simulate_json_and_trace(tmp_path):
    out = vrscroll("simulate", "60", "-45", "0", "30", "90", "-100", "--json", "-",
                   "--trace", str(tmp_path / "t.csv"))
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


@pytest.mark.parametrize("variant", [pytest.param("full", marks=pytest.mark.slow), "refined"])  # full: slow suite
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


@pytest.mark.parametrize("argv, new", [
    (["status", "--port", "/dev/null"], "--serial"),
    (["mirror", "--angles", "0,0,0,0,0,0", "--port", "/dev/null"], "--serial"),
    (["serve", "--port", "/dev/null"], "--serial"),
    (["tune", "--tolerance", "10"], "--tolerance-pct"),
    (["calibrate", "--scenario", "cal.toml"], "vrscroll scenario"),
    (["simulate", "1", "0", "0", "0", "0", "0", "--json"], "--json -"),
    (["simulate", "1", "0", "0", "0", "0", "0", "--max-time", "1"], "--max-time-s"),  # units in option names
    (["tune", "--duration", "1"], "--duration-s"),
    (["mirror", "--angles", "0,0,0,0,0,0", "--serial", "/dev/null", "--settle-limit", "1"], "--settle-limit-s"),
    (["emulate", "--jam-after", "1"], "--jam-after-s"),
    (["emulate", "--drop-after", "1"], "--drop-after-s"),
    (["emulate", "--pack-voltage", "8"], "--pack-voltage-v"),
])
def test_old_spellings_are_refused_naming_the_new(argv, new):
    r = vrscroll(*argv)
    assert r.returncode == 2 and new in r.stderr and "Traceback" not in r.stderr, r.stderr


def test_json_goes_to_a_file_or_to_standard_output(tmp_path, capsys):
    to_file = tmp_path / "r.json"
    assert main(["simulate", "5", "0", "0", "0", "0", "-5", "--json", str(to_file)]) == 0
    assert "device profile:" in capsys.readouterr().out  # the report, and the JSON beside it
    in_file = json.loads(to_file.read_text())
    assert main(["simulate", "5", "0", "0", "0", "0", "-5", "--json", "-"]) == 0
    on_stdout = json.loads(capsys.readouterr().out)  # nothing but the JSON
    assert in_file["hinges"] == on_stdout["hinges"]


def test_lists_are_comma_separated():
    r = vrscroll("evaluate", "--shapes", "cube,teapot", "--starts", "2")
    assert r.returncode == 2 and "'teapot' is not one of" in r.stderr


@pytest.mark.parametrize("start, words", [("1e155,0,0,0,0,0", "at most 100 m"),  # exited 139 once
                                          ("0,0,50,0,1e300,0", "within +-360 deg")])
def test_a_start_beyond_reach_is_refused_before_any_compiled_code(start, words):
    r = vrscroll("approximate", "--shape", "cube", f"--start={start}")
    assert r.returncode == 2 and words in r.stderr and "Traceback" not in r.stderr, r.stderr


@pytest.mark.parametrize("argv, words", [
    (["evaluate", "--starts", "1000000000"], "--starts 1000000000: from 2"),  # 9.1 GB in 30 s once
    (["psychometric", "trials.csv", "--bootstrap", "100000000"], "--bootstrap 100000000: from 0 to 100,000"),
])
def test_sizes_a_user_gives_are_bounded_before_any_work(argv, words, tmp_path):
    r = vrscroll(*argv, cwd=tmp_path)
    assert r.returncode == 2 and words in r.stderr and "Traceback" not in r.stderr, r.stderr


def test_calibrate_and_serve_refuse_what_cannot_work(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    r = vrscroll("calibrate", str(run), "--generations", "-1", "--population", "0")
    assert r.returncode == 2 and "argument --generations: -1 is not within 1 to 100" in r.stderr
    r = vrscroll("calibrate", str(run), "--holdout", str(run))
    assert r.returncode == 2 and "one of the runs fitted to" in r.stderr
    r = vrscroll("serve", "--listen", "70000")
    assert r.returncode == 2 and "--listen 70000" in r.stderr and "Traceback" not in r.stderr


def test_a_picture_or_file_into_a_folder_is_refused(tmp_path):
    """--png DIR once said it wrote a picture and wrote nothing."""
    r = vrscroll("approximate", "--shape", "cube", "--png", str(tmp_path))
    assert r.returncode == 2 and "is a folder" in r.stderr
    r = vrscroll("simulate", "1", "0", "0", "0", "0", "0", "--trace", str(tmp_path / "nowhere" / "t.csv"))
    assert r.returncode == 2 and "does not exist" in r.stderr


@pytest.mark.parametrize("argv, option", [
    (["simulate", "1", "0", "0", "0", "0", "0", "--max-time-s", "1e9"], "--max-time-s"),  # 10^12 ticks of trace
    (["simulate", "1", "0", "0", "0", "0", "0", "--max-time-s", "nan"], "--max-time-s"),
    (["tune", "--duration-s", "1e9"], "--duration-s"), (["tune", "--population", "0"], "--population"),
    (["tune", "--threads", "-1"], "--threads"), (["calibrate", "run", "--threads", "100000"], "--threads"),
    (["mirror", "--angles", "0,0,0,0,0,0", "--serial", "x", "--tolerance-deg", "-5"], "--tolerance-deg"),
    (["redirect", "a.json", "--sigma-mm", "inf"], "--sigma-mm"),
])
def test_numbers_on_the_command_line_are_finite_and_within_their_range(argv, option):
    r = vrscroll(*argv)
    assert r.returncode == 2 and f"argument {option}" in r.stderr and "not within" in r.stderr, r.stderr


def test_json_holds_null_where_a_number_is_not_defined():
    """A move cut short before it settles: its settle time is not defined, null in JSON (JSON has no NaN)."""
    out = vrscroll("simulate", "60", "0", "0", "0", "0", "0", "--max-time-s", "0.05", "--json", "-")
    assert out.returncode == 1, out.stderr  # the gate's settle check fails: the report is written all the same
    assert "NaN" not in out.stdout and "Infinity" not in out.stdout
    report = json.loads(out.stdout)
    assert report["hinges"][0]["settle_time_s"] is None and not report["settled"]


def test_simulate_exits_1_when_the_gate_fails_as_demo_does():
    out = vrscroll("simulate", "60", "0", "0", "0", "0", "0", "--max-time-s", "0.05", "--json", "-")
    assert out.returncode == 1, out.stderr
    assert json.loads(out.stdout)["gate"]["passed"] is False
    assert vrscroll("simulate", "10", "0", "0", "0", "0", "0", "--json", "-").returncode == 0


def test_a_negative_list_needs_no_equals_sign():
    out = vrscroll("simulate", "10", "0", "0", "0", "0", "0", "--from", "-10,0,0,0,0,5", "--json", "-")
    assert out.returncode == 0, out.stderr
    assert json.loads(out.stdout)["start_deg"] == [-10, 0, 0, 0, 0, 5]


def test_help_shows_json_taking_a_file():
    out = vrscroll("simulate", "--help")
    assert "--json FILE" in out.stdout and "[FILE]" not in out.stdout
    assert "--from=" not in out.stdout  # a negative list needs no equals sign (above): the help says none


@pytest.mark.parametrize("argv, written", [(("sweep", "--example"), "sweep.toml"),
                                           (("psychometric", "--example"), "trials.csv")])
def test_example_as_the_readme_words_it(tmp_path, argv, written):
    out = vrscroll(*argv, cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    assert (tmp_path / written).stat().st_size > 0
    again = vrscroll(*argv, cwd=tmp_path)  # never over a file that is there
    assert again.returncode == 2 and "exists" in again.stderr
    bare = vrscroll(argv[0], cwd=tmp_path)
    assert bare.returncode == 2 and "--example" in bare.stderr and "Traceback" not in bare.stderr


@pytest.mark.parametrize("value, words", [("bogus", "not one of MuJoCo's OpenGL back ends"),
                                          ("osmesa", "OSMesa")])
def test_an_unusable_mujoco_gl_is_one_line_naming_the_choices(value, words):
    import ctypes.util

    if value == "osmesa" and ctypes.util.find_library("OSMesa"):
        pytest.skip("OSMesa is installed here: MUJOCO_GL=osmesa is usable")
    import os

    for argv in (("demo", "--help"), ("status", "--serial", "/dev/null")):
        out = vrscroll(*argv, env={**os.environ, "MUJOCO_GL": value})
        assert out.returncode == 2 and "Traceback" not in out.stderr
        assert words in out.stderr and "egl, osmesa, glfw" in out.stderr and len(out.stderr.splitlines()) == 1


def test_a_closed_pipe_ends_quietly():
    import subprocess

    from twin.paths import cli_command, cli_env

    proc = subprocess.Popen(cli_command("simulate", "10", "0", "0", "0", "0", "0", "--json", "-"),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=cli_env(), text=True)
    proc.stdout.close()  # the reader is gone before the command writes (`| head` that has read enough)
    err = proc.stderr.read()
    assert proc.wait(120) == 141
    assert "Traceback" not in err and "BrokenPipe" not in err and "Exception ignored" not in err
