"""The firmware core (controllers/firmware, C99) built for this host and bound with ctypes.

The twin, the batch twin and the emulator run the device's own C code: `library()` compiles
the core's sources with the system C compiler on first use (`cc -std=c99 -Wall -Wextra -Werror
-O2 -shared -fPIC`), caches the shared library under `$VRSCROLL_CACHE/firmware` (default
~/.cache/vrscroll/firmware) keyed by a hash of the sources, flags and compiler, and loads it with
argtypes set (pointers as `c_void_p`, so numba's nopython code can call `vrs_tick` with integer
addresses). `Core` holds one core's state in a numpy byte buffer. Units at this edge: counts,
microseconds of device time, duty in [-1, 1], mA; gains as `controllers.pid.PidGains` (SI).
"""

from __future__ import annotations

import ctypes
import hashlib
import math
import os
import shutil
import subprocess
import tempfile
from pathlib import Path

import numpy as np

from controllers.pid import PidGains
from controllers.program import COAST
from twin.device.spec import MAX_HINGES, DeviceSpec
from twin.errors import UserError
from twin.paths import cache_dir

FIRMWARE_DIR = Path(__file__).resolve().parent / "firmware"
FIRMWARE_VERSION = (0, 4, 0)  # major, minor, patch: reported in HELLO_REPLY and STATE
WARNINGS = ("-std=c99", "-Wall", "-Wextra", "-Werror")
LIBRARY_FLAGS = (*WARNINGS, "-O2", "-shared", "-fPIC")
TX_CHUNK = 4096  # VRS_TX_CAP: everything queued fits in one read


class FirmwareBuildError(UserError):
    """The firmware could not be compiled (no compiler, or it refused the sources): a one-line CLI error."""


class Config(ctypes.Structure):
    """vrs_config (vrs_core.h): the device's fixed figures."""

    _fields_ = [("n_hinges", ctypes.c_uint8), ("loop_rate_hz", ctypes.c_uint16), ("watchdog_ms", ctypes.c_uint16),
                ("max_telemetry_hz", ctypes.c_uint16), ("limit_counts", ctypes.c_int32),
                ("limit_margin_counts", ctypes.c_int32), ("stall_duty", ctypes.c_float),
                ("stall_counts", ctypes.c_int32), ("stall_ms", ctypes.c_uint16), ("overcurrent_ma", ctypes.c_int16),
                ("drive_cap_mv", ctypes.c_uint16), ("fw_version", ctypes.c_uint8 * 3),
                ("stall_current_ma", ctypes.c_uint16), ("continuous_current_ma", ctypes.c_uint16),
                ("overload_ms", ctypes.c_uint16), ("host_away_hold_ms", ctypes.c_uint16)]


class Gains(ctypes.Structure):
    """vrs_gains (vrs_core.h): one hinge's PID gains in SI, as float."""

    _fields_ = [("kp", ctypes.c_float), ("ki", ctypes.c_float), ("kd", ctypes.c_float), ("cutoff_hz", ctypes.c_float),
                ("integral_limit", ctypes.c_float), ("deadband", ctypes.c_float), ("hold_band", ctypes.c_uint16)]


class PidState(ctypes.Structure):
    """vrs_pid (vrs_core.h): one hinge's PID memory."""

    _fields_ = [("prev", ctypes.c_int32), ("rate", ctypes.c_float), ("integral", ctypes.c_float)]


def _program_max_segments() -> int:
    """VRS_PROGRAM_MAX_SEGMENTS, read from the generated header (its one home, twin/link/protocol.py, is a layer
    above this one)."""
    for line in (FIRMWARE_DIR / "vrs_protocol.h").read_text().splitlines():
        if line.startswith("#define VRS_PROGRAM_MAX_SEGMENTS "):
            return int(line.split()[2])
    raise FirmwareBuildError("vrs_protocol.h has no VRS_PROGRAM_MAX_SEGMENTS: run `vrscroll model --write`")


PROGRAM_MAX_SEGMENTS = _program_max_segments()


class ProgramSpec(ctypes.Structure):
    """vrs_program_spec (vrs_core.h): an open-loop program on one hinge (duty in [-1, 1], ms, window in counts; coast:
    bit i, segment i coasts)."""

    _fields_ = [("hinge", ctypes.c_uint8), ("n_segments", ctypes.c_uint8), ("timeout_ms", ctypes.c_uint16),
                ("low", ctypes.c_int32), ("high", ctypes.c_int32), ("duty", ctypes.c_float * PROGRAM_MAX_SEGMENTS),
                ("ms", ctypes.c_uint16 * PROGRAM_MAX_SEGMENTS), ("coast", ctypes.c_uint16)]


class ProgramStatus(ctypes.Structure):
    """vrs_program_status (vrs_core.h): the last program's hinge, end (ProgramEnd), ticks run, samples dropped,
    battery (mV) at its end."""

    _fields_ = [("hinge", ctypes.c_uint8), ("end", ctypes.c_uint8), ("ticks", ctypes.c_uint32),
                ("dropped", ctypes.c_uint32), ("battery_mv", ctypes.c_uint16)]


# the C structs this module mirrors, by their typedef names in vrs_core.h: layout_checks() turns each into
# compile-time checks of its size and every field's offset, so a field added, moved or resized on one side only
# stops the build instead of shifting every value after it
MIRRORED = {"vrs_config": Config, "vrs_gains": Gains, "vrs_pid": PidState, "vrs_program_spec": ProgramSpec,
            "vrs_program_status": ProgramStatus}


def layout_checks(mirrored: dict | None = None) -> str:
    """C source (the body of vrs_layout.h) asserting that each mirrored struct has the size and field offsets,
    in bytes, that its ctypes mirror has on this host: _Static_assert in C11, a negative array size in C99."""
    lines = []
    for name, mirror in (mirrored or MIRRORED).items():
        lines.append(f"VRS_LAYOUT({name}_size, sizeof({name}) == {ctypes.sizeof(mirror)});")
        for field, *_ in mirror._fields_:
            offset = getattr(mirror, field).offset
            lines.append(f"VRS_LAYOUT({name}_{field}, offsetof({name}, {field}) == {offset});")
    return "\n".join(lines)


def program_spec(hinge: int, segments, window_counts, timeout_s: float | None = None) -> ProgramSpec:
    """The core's program for (duty, duration_s) segments (duty controllers.program.COAST: it coasts), a (low,
    high) counts window and a timeout (s; default the segments' sum); ValueError for more segments than the core
    holds (the core checks every other bound)."""
    segments = list(segments)
    if not 1 <= len(segments) <= PROGRAM_MAX_SEGMENTS:
        raise ValueError(f"a program has 1 to {PROGRAM_MAX_SEGMENTS} segments, not {len(segments)}")
    ms = [min(max(round(s * 1000), 0), 0xFFFF) for _, s in segments]
    timeout = sum(ms) if timeout_s is None else round(timeout_s * 1000)
    p = ProgramSpec(hinge=hinge, n_segments=len(segments), timeout_ms=min(max(timeout, 0), 0xFFFF),
                    low=int(window_counts[0]), high=int(window_counts[1]))
    for i, ((d, _), m) in enumerate(zip(segments, ms)):
        p.duty[i], p.ms[i] = 0.0 if d == COAST else float(d), m
        p.coast |= (d == COAST) << i
    return p


def config_from_spec(spec: DeviceSpec) -> Config:
    """The core's config for a device spec (the twin sets watchdog_ms = 0 on the result)."""
    return Config(n_hinges=spec.n_hinges, loop_rate_hz=round(spec.loop_rate), watchdog_ms=round(spec.watchdog * 1000),
                  max_telemetry_hz=round(spec.max_telemetry_rate),
                  limit_counts=math.floor(spec.hinge_limit / spec.rad_per_count),
                  limit_margin_counts=spec.limit_margin, stall_duty=spec.stall_duty, stall_counts=spec.stall_counts,
                  stall_ms=round(spec.stall_time * 1000), overcurrent_ma=round(spec.overcurrent * 1000),
                  drive_cap_mv=round(spec.drive_cap * 1000), fw_version=(ctypes.c_uint8 * 3)(*FIRMWARE_VERSION),
                  stall_current_ma=round(spec.stall_current * 1000),
                  continuous_current_ma=round(spec.continuous_current * 1000),
                  overload_ms=round(spec.overload_time * 1000), host_away_hold_ms=round(spec.host_away_hold * 1000))


def gains_struct(gains) -> ctypes.Array:
    """An array of vrs_gains from a sequence of PidGains."""
    return (Gains * len(gains))(*(Gains(g.kp, g.ki, g.kd, g.derivative_cutoff, g.integral_limit, g.deadband_duty,
                                        g.hold_band) for g in gains))


def pid_gains(g: Gains) -> PidGains:
    """The PidGains a vrs_gains holds (float32 values widened)."""
    return PidGains(g.kp, g.ki, g.kd, g.cutoff_hz, g.integral_limit, g.deadband, g.hold_band)


# ---- building ---------------------------------------------------------------------------

def compiler(variable: str = "CC", default: str = "cc", language: str = "C", package: str = "gcc") -> str:
    """The C compiler: $CC, else cc (or another language's, by its variable); FirmwareBuildError naming it
    where it is missing."""
    name = os.environ.get(variable, default)
    path = shutil.which(name)
    if path is None:
        raise FirmwareBuildError(f"the firmware needs a {language} compiler and `{name}` was not found on PATH: "
                                 f"install one (Debian/Ubuntu: apt install {package}) or set {variable}")
    return path


def core_sources() -> list[Path]:
    return sorted(FIRMWARE_DIR.glob("*.c"))


def cached_build(name: str, suffix: str, key: list[str], inputs: list[Path], make) -> Path:
    """The cached file for `key` (compilers, flags) and `inputs` (their names and bytes), made by
    make(tmp_path) into a temporary name first when missing; FirmwareBuildError from make passes on."""
    h = hashlib.sha256()
    for part in key:
        h.update(part.encode() + b"\0")
    for p in inputs:
        h.update(p.name.encode() + b"\0" + p.read_bytes() + b"\0")
    out = cache_dir("firmware") / f"{name}-{h.hexdigest()[:16]}{suffix}"
    if out.exists():
        return out
    out.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=out.name, dir=out.parent)
    os.close(fd)
    try:
        make(tmp)
        os.replace(tmp, out)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return out


def run_compiler(args: list[str], what: str) -> None:
    """Run a compiler command; FirmwareBuildError with its messages when it fails."""
    r = subprocess.run(args, capture_output=True, text=True)
    if r.returncode != 0:
        raise FirmwareBuildError(f"{args[0]} could not build {what}:\n{r.stderr.strip()}")


def build(flags=LIBRARY_FLAGS, extra_sources=(), name: str = "vrs_core", suffix: str = ".so") -> Path:
    """Compile the core (and extra_sources) with flags into the cache; the cached file if present."""
    cc = compiler()
    sources = [*core_sources(), *map(Path, extra_sources)]
    return cached_build(name, suffix, [cc, *flags], [*sorted(FIRMWARE_DIR.glob("*.h")), *sources],
                        lambda tmp: run_compiler([cc, *flags, f"-I{FIRMWARE_DIR}", "-o", tmp, *map(str, sources)],
                                                 "the firmware core"))


_VP, _U8, _U16, _U32, _I32, _F = (ctypes.c_void_p, ctypes.c_uint8, ctypes.c_uint16, ctypes.c_uint32, ctypes.c_int32,
                                  ctypes.c_float)
_SIGNATURES = {  # name: (argtypes, restype), as vrs_core.h declares them
    "vrs_core_size": ([], ctypes.c_size_t),
    "vrs_init": ([_VP, _VP, _VP, _VP], ctypes.c_int),
    "vrs_rx": ([_VP, _VP, _U32, _U32], None),
    "vrs_tx": ([_VP, _VP, _U32], _U32),
    "vrs_tick": ([_VP, _U32, _VP, _VP, _VP, _VP], None),
    "vrs_set_targets": ([_VP, _VP, _U32], ctypes.c_int),
    "vrs_set_gains": ([_VP, _U8, _VP], ctypes.c_int),
    "vrs_set_telemetry_rate": ([_VP, _U16], ctypes.c_int),
    "vrs_estop": ([_VP], None),
    "vrs_clear_fault": ([_VP], ctypes.c_int),
    "vrs_set_reset_reason": ([_VP, _U8], None),
    "vrs_confirm_zero": ([_VP], ctypes.c_int),
    "vrs_program": ([_VP, _VP], ctypes.c_int),
    "vrs_get_program": ([_VP, _VP], None),
    "vrs_mark_zero_confirmed": ([_VP], None),
    "vrs_get_heat": ([_VP, _VP], None),
    "vrs_get_derated": ([_VP], _U8),
    "vrs_get_state": ([_VP], _U8),
    "vrs_get_faults": ([_VP], _U16),
    "vrs_get_fault_hinge": ([_VP], _U8),
    "vrs_get_targets": ([_VP, _VP], None),
    "vrs_get_gains": ([_VP, _U8, _VP], ctypes.c_int),
    "vrs_get_rx_bad_frames": ([_VP], _U32),
    "vrs_get_telemetry_dropped": ([_VP], _U32),
    "vrs_get_battery_mv": ([_VP], _U16),
    "vrs_pid_memory": ([_VP], _VP),
    "vrs_set_battery_mv": ([_VP, _U16], None),
    "vrs_pwm": ([_VP, _VP], None),
    "vrs_pid_update": ([_VP, _VP, _F, _F, _I32, _I32], _F),
    "vrs_pid_alpha": ([_F, _F], _F),
    "vrs_crc16": ([_VP, _U32], _U16),
    "vrs_encode": ([_U8, _U16, _VP, _U8, _VP, _U32], _U32),
    "vrs_decode": ([_VP, _U32, _VP, _VP, _VP, _VP], ctypes.c_int),
}

_LIBRARY = None


def library() -> ctypes.CDLL:
    """The core built for this host (compiled on first use), with argtypes and restypes set."""
    global _LIBRARY
    if _LIBRARY is None:
        lib = ctypes.CDLL(str(build()))
        for fn, (args, res) in _SIGNATURES.items():
            f = getattr(lib, fn)
            f.argtypes, f.restype = args, res
        _LIBRARY = lib
    return _LIBRARY


class Core:
    """One firmware core: config, gains (PidGains per hinge) and the counts it starts at."""

    def __init__(self, config: Config, gains, counts):
        self.lib = lib = library()
        self.n = config.n_hinges
        if len(gains) != self.n:
            raise ValueError(f"expected gains for {self.n} hinges, got {len(gains)}")
        self._config = config
        self._state = np.zeros(lib.vrs_core_size(), np.uint8)
        self.address = self._state.ctypes.data
        self._counts = np.zeros(MAX_HINGES, np.int32)
        self._current = np.zeros(MAX_HINGES, np.int16)
        self._duty = np.zeros(MAX_HINGES, np.float32)
        self._decay = np.zeros(MAX_HINGES, np.uint8)
        self._tx = ctypes.create_string_buffer(TX_CHUNK)
        self._counts[:self.n] = counts
        table = gains_struct(gains)  # held until the call returns
        if lib.vrs_init(self.address, ctypes.addressof(config), ctypes.addressof(table), self._counts.ctypes.data):
            raise ValueError(f"the firmware core refuses this config or these gains: {config.n_hinges} hinges, "
                             f"loop rate {config.loop_rate_hz} Hz, gains {list(gains)}")

    def rx(self, data: bytes, now_us: int) -> None:
        """Bytes from the host at device time now_us (µs, wraps at 2**32)."""
        self.lib.vrs_rx(self.address, data, len(data), now_us & 0xFFFFFFFF)

    def tx(self) -> bytes:
        """Every byte queued for the host."""
        n = self.lib.vrs_tx(self.address, self._tx, TX_CHUNK)
        return self._tx.raw[:n]

    def tick(self, now_us: int, counts, current_ma=None) -> tuple[np.ndarray, np.ndarray]:
        """One control tick: (duty float32 (n,), decay uint8 (n,): 0 coast, 1 brake)."""
        n = self.n
        self._counts[:n] = counts
        cur = 0
        if current_ma is not None:
            self._current[:n] = current_ma
            cur = self._current.ctypes.data
        self.lib.vrs_tick(self.address, now_us & 0xFFFFFFFF, self._counts.ctypes.data, cur,
                          self._duty.ctypes.data, self._decay.ctypes.data)
        return self._duty[:n].copy(), self._decay[:n].copy()

    def run_tick(self, now_us: int, counts, current_ma, battery_mv: int) -> tuple[np.ndarray, np.ndarray]:
        """One tick as a board runs it: the battery read, vrs_tick, the bridges' PWM (battery compensated)
        and decay per hinge (controllers.sketch.Sketch has the same method for the whole sketch)."""
        self.battery(battery_mv)
        _, decay = self.tick(now_us, counts, current_ma)
        return self.pwm(), decay

    def battery(self, mv: int) -> None:
        """The battery voltage now, mV, as the device's ADC reads it."""
        self.lib.vrs_set_battery_mv(self.address, max(0, min(int(mv), 0xFFFF)))

    def pwm(self) -> np.ndarray:
        """The H-bridges' PWM (float32 (n,), [-1, 1]) for the last tick's duties: the core's battery compensation."""
        out = np.zeros(MAX_HINGES, np.float32)
        self.lib.vrs_pwm(self.address, out.ctypes.data)
        return out[:self.n]

    def set_targets(self, counts, now_us: int) -> int:
        """0, or the NACK reason (twin.link.protocol.Nack); nothing changes on a refusal."""
        self._counts[:self.n] = counts
        return self.lib.vrs_set_targets(self.address, self._counts.ctypes.data, now_us & 0xFFFFFFFF)

    def set_gains(self, hinge: int, gains: PidGains) -> int:
        """0, or the NACK reason; hinge 0xFF sets every hinge."""
        table = gains_struct([gains])
        return self.lib.vrs_set_gains(self.address, hinge, ctypes.addressof(table))

    def set_telemetry_rate(self, rate_hz: int) -> int:
        return self.lib.vrs_set_telemetry_rate(self.address, rate_hz)

    def estop(self) -> None:
        self.lib.vrs_estop(self.address)

    def clear_fault(self) -> int:
        """0, or Nack.FAULT_PERSISTS while a HARDWARE fault stands."""
        return self.lib.vrs_clear_fault(self.address)

    def confirm_zero(self) -> int:
        """CONFIRM_ZERO: the present counts become zero; 0, or Nack.BAD_STATE outside IDLE."""
        return self.lib.vrs_confirm_zero(self.address)

    def program(self, spec: ProgramSpec) -> int:
        """Start an open-loop program (see program_spec), as PROGRAM would: 0, or the NACK reason."""
        return self.lib.vrs_program(self.address, ctypes.addressof(spec))

    def program_status(self) -> ProgramStatus:
        """The last program: hinge, end (ProgramEnd), ticks run, samples dropped, battery_mv at its end."""
        out = ProgramStatus()
        self.lib.vrs_get_program(self.address, ctypes.addressof(out))
        return out

    def mark_zero_confirmed(self) -> None:
        """Accept the present zero as it is (the twin's counts are true from the start)."""
        self.lib.vrs_mark_zero_confirmed(self.address)

    @property
    def heat(self) -> np.ndarray:
        """Each hinge's I2t estimate as a share of the budget (1: derating)."""
        out = np.zeros(MAX_HINGES, np.float32)
        self.lib.vrs_get_heat(self.address, out.ctypes.data)
        return out[:self.n].astype(float)

    @property
    def derated(self) -> int:
        """Bit k: hinge k's duty held to the continuous rating by the I2t protection."""
        return self.lib.vrs_get_derated(self.address)

    def set_reset_reason(self, reason: int) -> None:
        """Why the device last started (protocol.ResetReason), as HELLO_REPLY reports it."""
        self.lib.vrs_set_reset_reason(self.address, reason)

    @property
    def state(self) -> int:
        """twin.link.protocol.State value."""
        return self.lib.vrs_get_state(self.address)

    @property
    def faults(self) -> int:
        """twin.link.protocol.Fault bits."""
        return self.lib.vrs_get_faults(self.address)

    @property
    def fault_hinge(self) -> int:
        return self.lib.vrs_get_fault_hinge(self.address)

    @property
    def targets(self) -> np.ndarray:
        out = np.zeros(self.n, np.int32)
        self.lib.vrs_get_targets(self.address, out.ctypes.data)
        return out

    def gains(self, hinge: int) -> PidGains:
        g = Gains()
        if self.lib.vrs_get_gains(self.address, hinge, ctypes.addressof(g)):
            raise ValueError(f"no hinge {hinge}")
        return pid_gains(g)

    @property
    def rx_bad_frames(self) -> int:
        return self.lib.vrs_get_rx_bad_frames(self.address)

    @property
    def telemetry_dropped(self) -> int:
        return self.lib.vrs_get_telemetry_dropped(self.address)


# ---- the core's lifecycle on the host: the twin's, the batch twin's and the emulator's ----------------

def tick_us(spec: DeviceSpec) -> int:
    """One firmware tick in device time, us."""
    return round(spec.firmware_dt * 1e6)


def per_hinge(gains, n: int) -> list[PidGains]:
    """n PidGains from one (for every hinge) or a sequence of n."""
    gains = [gains] * n if isinstance(gains, PidGains) else list(gains)
    if len(gains) != n:
        raise ValueError(f"expected gains for {n} hinges, got {len(gains)}")
    return gains


def start_core(spec: DeviceSpec, gains: list[PidGains], counts, stall_detection: bool = False,
               active: bool = True) -> Core:
    """The twin's firmware core, ACTIVE and holding `counts` (IDLE with active=False, as a device whose zero
    was confirmed is, ready for an open-loop program): the device's config with the watchdog off
    (no host talks to the twin) and, unless asked for, stall detection off (the twin is also driven into
    contact on purpose: the CBS baseline, the gate's runs).

    ValueError naming the hinge for gains outside the firmware's bounds.
    """
    cfg = config_from_spec(spec)
    cfg.watchdog_ms = 0
    if not stall_detection:
        cfg.stall_duty = math.inf  # no |duty| reaches it
    fw = Core(cfg, [PidGains.from_spec(spec)] * spec.n_hinges, counts)
    fw.mark_zero_confirmed()  # the twin's counts are true: no one need lay it flat
    set_core_gains(fw, gains)
    if active:
        fw.set_targets(counts, 0)
    return fw


def set_core_gains(fw: Core, gains: list[PidGains]) -> None:
    """Each hinge's gains into the core, as SET_GAINS would; ValueError naming the first hinge it refuses."""
    for k, g in enumerate(gains):
        if fw.set_gains(k, g):
            raise ValueError(f"hinge {k}: the firmware refuses gains outside its bounds (docs/protocol.md): {g}")


def pid_memory(fw: Core) -> np.recarray:
    """A live view of the core's PID memory per hinge: fields prev (counts), rate (counts/s), integral (duty)."""
    return pid_memory_at(fw.address, fw.n, fw)


def pid_memory_at(address: int, n: int, owner) -> np.recarray:
    """pid_memory of the n-hinge core at `address` (a vrs_core in memory `owner` holds: a Core, or the batch
    twin's array of cores); the view keeps `owner` alive."""
    mem = (PidState * n).from_address(library().vrs_pid_memory(address))
    mem.owner = owner
    return np.ctypeslib.as_array(mem).view(np.recarray)


def core_state_bytes(fw: Core) -> np.ndarray:
    """A copy of a core's state (a vrs_core holds no pointers: its copy is a core)."""
    return np.ctypeslib.as_array((ctypes.c_uint8 * library().vrs_core_size()).from_address(fw.address)).copy()

