"""The Unity client's transport (clients/unity/VRScrollLive: LiveClient.cs, Datagrams.cs, Json.cs), compiled with
Mono's `mcs` and run under `mono` as a scripted session (clients/unity/tests/ScriptedSession.cs) against the real
service with the emulator as the device. The MonoBehaviour (VRScrollLiveDriver.cs) needs Unity and is not
compiled here.

CI installs mono-mcs and mono-runtime (.ci/run) and sets VRSCROLL_REQUIRE_MONO, so there a missing
compiler fails the test; elsewhere it is skipped with the reason.
"""

import json
import os
import shutil
import subprocess
from pathlib import Path

import pytest

from twin.live.process import ServiceProcess

ROOT = Path(__file__).resolve().parents[2]
SOURCES = ["clients/unity/VRScrollLive/Json.cs", "clients/unity/VRScrollLive/Datagrams.cs",
           "clients/unity/VRScrollLive/LiveClient.cs",
           "clients/unity/tests/ScriptedSession.cs"]


@pytest.fixture(scope="module")
def scripted_session(tmp_path_factory):
    if shutil.which("mcs") is None or shutil.which("mono") is None:
        if os.environ.get("VRSCROLL_REQUIRE_MONO"):
            pytest.fail("mcs and mono are required here (apt-get install mono-mcs mono-runtime)")
        pytest.skip("needs Mono: apt-get install mono-mcs mono-runtime")
    exe = tmp_path_factory.mktemp("unity") / "ScriptedSession.exe"
    build = subprocess.run(["mcs", "-warnaserror", f"-out:{exe}", *SOURCES], cwd=ROOT, capture_output=True, text=True)
    assert build.returncode == 0, build.stdout + build.stderr
    return exe


def test_the_csharp_transport_plays_a_session_against_the_service(scripted_session, emulator, tmp_path):
    emu = emulator()
    with ServiceProcess("--serial", emu.port, "--log", str(tmp_path / "session.jsonl"),
                        stderr_path=tmp_path / "serve.err") as service:
        run = subprocess.run(["mono", str(scripted_session), service.url, "cylinder"], capture_output=True,
                             text=True, timeout=120)
    assert run.returncode == 0, run.stdout + run.stderr
    seen = json.loads(run.stdout.strip().splitlines()[-1])
    assert seen["malformed_error"] == "malformed" and seen["out_of_order_error"] == "out_of_order"
    assert seen["target"] == "cylinder" and seen["approximations"] >= 20
    # frame estimates follow the approximations in their own datagram (protocol 2; at most ESTIMATES_RATE_HZ, for
    # the newest), for a pose it sent to the worker's own port (protocol 3)
    assert seen["estimates"] >= 10 and seen["estimates_answer_an_approximation"] and seen["msd_estimate_mm"] < 5.0
    assert seen["gate_passed"] is True and seen["progress_source"] == "device" and seen["outcome"] == "done"
    assert seen["pens_redirected"] == seen["pens_sent"] == 40
    assert seen["largest_offset_mm"] < 5.0  # pens on the root flap, which the approximation put on the cylinder
    assert seen["status_state"] == "locked"
    assert [e for e in emu.events("rx") if e["msg"] == "SET_TARGETS"]  # the device did move, on the lock


def test_a_client_without_the_token_is_refused_in_csharp_too(scripted_session, tmp_path):
    with ServiceProcess("--token", "s3cret", stderr_path=tmp_path / "serve.err") as service:
        run = subprocess.run(["mono", str(scripted_session), service.url, "cylinder"], capture_output=True,
                             text=True, timeout=60)
    assert run.returncode == 1
    assert "unauthorized" in run.stderr
