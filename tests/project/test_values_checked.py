"""Values nobody checked (issue 40, attack 8), each now a one-line refusal: a tuning step too small to leave the
settle band (`tune --step-deg 1e-320` reported every limit kept and wrote gains), a device profile named as the
selection file or a file being written (`device create default` broke selecting any profile)."""

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
