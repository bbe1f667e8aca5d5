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
