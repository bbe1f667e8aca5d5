import pytest

from twin.link.emulator_process import EmulatorProcess

from twin.device.spec import load_spec


@pytest.fixture(scope="session")
def spec():
    return load_spec()


@pytest.fixture
def emulator(tmp_path):
    """start(*cli_options) -> a device emulator process on a real pty; all are stopped after the test."""
    started = []

    def start(*args):
        e = EmulatorProcess(tmp_path / f"emulator{len(started)}.jsonl", *args)
        started.append(e)
        return e

    yield start
    for e in started:
        e.stop()


@pytest.fixture(autouse=True)
def device_profiles(tmp_path, monkeypatch):
    """Every test gets its own, empty profiles folder: never the user's ~/.config/vrscroll/devices."""
    folder = tmp_path / "devices"
    monkeypatch.setenv("VRSCROLL_DEVICES", str(folder))
    return folder
