"""The firmware core's build: the generated header agrees with the protocol table and the spec, the
core compiles with the sketch's warning flags, the host build is cached and fails clearly."""

import ctypes
import re
import subprocess

import pytest

from controllers import core
from twin.device.spec import MAX_HINGES
from twin.link.firmware_header import HEADER_PATH, LAYOUT_PATH, header, layout_header

# what the ESP32-S3 build would complain about: any double, any float narrowed without a cast
SKETCH_FLAGS = ("-std=c99", "-Wall", "-Wextra", "-Werror", "-Wdouble-promotion", "-Wfloat-conversion",
                "-Wconversion", "-pedantic")


def test_committed_header_is_generated_from_protocol_and_spec():
    assert HEADER_PATH.read_text() == header(), "run `vrscroll model --write`"
    assert LAYOUT_PATH.read_text() == layout_header(), "run `vrscroll model --write`"


class _MovedPid(ctypes.Structure):  # vrs_pid with two fields swapped: the same size, every value misread
    _fields_ = [("prev", ctypes.c_int32), ("integral", ctypes.c_float), ("rate", ctypes.c_float)]


class _ShortConfig(ctypes.Structure):  # vrs_config without its last field
    _fields_ = core.Config._fields_[:-1]


@pytest.mark.parametrize("std", ["-std=c99", "-std=c11"])
@pytest.mark.parametrize("mirrored, wrong", [({}, None), ({"vrs_pid": _MovedPid}, "vrs_pid_rate"),
                                            ({"vrs_config": _ShortConfig}, "vrs_config_size")])
def test_a_mirror_that_differs_from_the_c_struct_stops_the_build(tmp_path, std, mirrored, wrong):
    """vrs_layout.h holds each mirrored struct's size and offsets: a ctypes mirror that moved or lost a field
    (here on the host's side) fails to compile, naming the struct and the field; the committed mirrors compile."""
    checks = tmp_path / "vrs_layout.h"
    checks.write_text(layout_header({**core.MIRRORED, **mirrored}))
    source = tmp_path / "check.c"
    source.write_text('#include "vrs_layout.h"\nint vrs_layout_checked(void) { return 0; }\n')
    r = subprocess.run([core.compiler(), std, "-Wall", "-Wextra", "-Werror", "-pedantic" if std == "-std=c99" else "-Wpedantic",
                        f"-I{tmp_path}", f"-I{core.FIRMWARE_DIR}", "-c", str(source), "-o", str(tmp_path / "check.o")],
                       capture_output=True, text=True)
    if wrong is None:
        assert r.returncode == 0, r.stderr
    else:
        assert r.returncode != 0 and wrong in r.stderr


def test_header_changes_with_the_spec(spec):
    text = header(spec.replace(watchdog=0.35, kp=0.07))
    assert "#define VRS_DEVICE_WATCHDOG_MS 350" in text and "#define VRS_DEVICE_KP 0.07f" in text


@pytest.mark.parametrize("source", core.core_sources(), ids=lambda p: p.name)
def test_core_compiles_with_the_sketch_flags(source, tmp_path):
    cc = core.compiler()
    r = subprocess.run([cc, *SKETCH_FLAGS, "-fsingle-precision-constant", f"-I{core.FIRMWARE_DIR}", "-c", str(source),
                        "-o", str(tmp_path / "x.o")], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr


def test_no_double_anywhere_in_the_firmware():
    """The ESP32-S3 FPU is single precision: no double in the core or the sketch, comments aside (the host's
    stand-ins in esp32s3/host/ never run on the board)."""
    for path in [*core.FIRMWARE_DIR.glob("*.[ch]"), *core.FIRMWARE_DIR.glob("esp32s3/*.[hi]*")]:
        code = re.sub(r"/\*.*?\*/|//[^\n]*", "", path.read_text(), flags=re.S)
        assert not re.search(r"\bdouble\b", code), path


def test_build_is_cached_by_sources_and_flags(tmp_path, monkeypatch):
    monkeypatch.setenv("VRSCROLL_CACHE", str(tmp_path))
    first = core.build()
    assert first.parent == tmp_path / "firmware" and first.exists()
    mtime = first.stat().st_mtime_ns
    assert core.build() == first and first.stat().st_mtime_ns == mtime  # not rebuilt
    other = core.build((*core.WARNINGS, "-O0", "-shared", "-fPIC"))
    assert other != first and other.exists()
    assert [p.name for p in (tmp_path / "firmware").iterdir() if not p.name.endswith(".so")] == []  # no leftovers


def test_missing_compiler_is_named(tmp_path, monkeypatch):
    monkeypatch.setenv("VRSCROLL_CACHE", str(tmp_path))
    monkeypatch.setenv("CC", "no-such-cc")
    with pytest.raises(core.FirmwareBuildError, match="needs a C compiler and `no-such-cc` was not found"):
        core.build()


def test_compiler_errors_are_reported(tmp_path, monkeypatch):
    monkeypatch.setenv("VRSCROLL_CACHE", str(tmp_path))
    bad = tmp_path / "bad.c"
    bad.write_text("int f(void) { return; }\n")
    with pytest.raises(core.FirmwareBuildError, match="could not build the firmware core"):
        core.build(extra_sources=[bad])


def test_the_hinge_limit_is_the_cores():
    """The host's MAX_HINGES (twin.device.spec) is the C core's VRS_MAX_HINGES."""
    header = (core.FIRMWARE_DIR / "vrs_core.h").read_text()
    assert int(re.search(r"#define VRS_MAX_HINGES (\d+)", header).group(1)) == MAX_HINGES
