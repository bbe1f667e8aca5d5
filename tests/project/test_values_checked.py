"""Values nobody checked (issue 40, attacks 7 and 8), each now a one-line refusal: a tuning step too small to leave
the settle band (`tune --step-deg 1e-320` reported every limit kept and wrote gains), a device profile named as the
selection file or a file being written (`device create default` broke selecting any profile), a worker count
nothing could hold (`evaluate --workers 5000` started 5,000 processes)."""

import os

import pytest

from twin.cli import main as vrscroll
from twin.device.profile import check_name, default_name


@pytest.mark.parametrize("step", ["1e-320", "0", "-1e-9", "1.0"])
def test_tune_refuses_a_step_inside_the_settle_band(capsys, step):
    assert vrscroll(["tune", f"--step-deg={step}"]) == 2
    err = capsys.readouterr().err
    assert "must leave the settle band" in err and len(err.splitlines()) == 1, err


@pytest.mark.parametrize("name", ["default", "Default", "default.part", "mine.part", "none"])
def test_a_profile_name_the_profiles_folder_uses_itself_is_refused(capsys, name):
    with pytest.raises(ValueError, match="reserved"):
        check_name(name)
    assert vrscroll(["device", "create", name]) == 2
    assert "reserved" in capsys.readouterr().err
    assert vrscroll(["device", "create", "mine"]) == 0 and vrscroll(["device", "select", "mine"]) == 0
    assert default_name() == "mine"


@pytest.mark.parametrize("command", [["evaluate", "--shapes", "cube", "--starts", "2"], ["sweep", "--example"]])
@pytest.mark.parametrize("workers", [5000, 0, -1])
def test_a_worker_count_beyond_the_cores_is_refused_before_a_process_starts(tmp_path, capsys, command, workers):
    from twin.evaluation.backends import WORKERS_PER_CORE

    if command[0] == "sweep":
        assert vrscroll(["sweep", str(tmp_path / "s.toml"), "--example"]) == 0
        command = ["sweep", str(tmp_path / "s.toml")]
    capsys.readouterr()
    assert vrscroll([*command, "--out", str(tmp_path / "out"), "--workers", str(workers)]) == 2
    err = capsys.readouterr().err
    most = WORKERS_PER_CORE * os.cpu_count()
    assert f"--workers {workers}: from 1 to {most} ({WORKERS_PER_CORE} per core" in err and len(err.splitlines()) == 1
    assert not list((tmp_path / "out").glob("*.jsonl"))
