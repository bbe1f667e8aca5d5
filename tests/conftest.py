import os
import shutil
import tempfile

# The whole test run caches (firmware builds, fields, decompositions) in a folder of its own, never the
# user's ~/.cache/vrscroll: set before the project is imported (test modules build the C core when
# collected), inherited by every command a test starts, removed when the run ends. One folder for the run,
# so the core and the fields are built once per run, not once per test.
CACHE = tempfile.mkdtemp(prefix="vrscroll-test-cache-")
os.environ["VRSCROLL_CACHE"] = CACHE

import pytest  # noqa: E402

from twin.link.emulator_process import EmulatorProcess  # noqa: E402

from twin.device.spec import load_spec  # noqa: E402


@pytest.fixture(scope="session")
def spec():
    return load_spec()


# The plant the link and HIL tests' emulator has unless a test says otherwise: fixed, not drawn (it is the
# emulator's default before plants were drawn within ranges); a test's own options come after and win.
FIXED_PLANT = ("--speed-scale", "0.95", "--friction-scale", "1.25", "--damping-scale", "1.2", "--armature-scale", "1",
               "--backlash-deg", "0.5", "--latency-ms", "1", "--backdrive-scale", "1")


@pytest.fixture
def emulator(tmp_path):
    """start(*cli_options) -> a device emulator process on a real pty (FIXED_PLANT unless the options say
    otherwise), its zero confirmed at power-on; all are stopped after the test."""
    started = []

    def start(*args):
        e = EmulatorProcess(tmp_path / f"emulator{len(started)}.jsonl", *FIXED_PLANT, "--zeroed", *args)
        started.append(e)
        return e

    yield start
    for e in started:
        e.stop()


@pytest.fixture(autouse=True)
def in_own_folder(tmp_path, monkeypatch):
    """Every test runs in its own folder: what a command writes by default (simulate.png, demo.png, a session
    log) lands there, never in the repository."""
    monkeypatch.chdir(tmp_path)


@pytest.fixture(autouse=True)
def device_profiles(tmp_path, monkeypatch):
    """Every test gets its own, empty profiles folder: never the user's ~/.config/vrscroll/devices."""
    folder = tmp_path / "devices"
    monkeypatch.setenv("VRSCROLL_DEVICES", str(folder))
    return folder


def pytest_sessionfinish(session, exitstatus):
    shutil.rmtree(CACHE, ignore_errors=True)
