"""The ESP32-S3 sketch (controllers/firmware/esp32s3) built for this host and run against its peripherals.

`build()` compiles the sketch's own source, unchanged, as C++ against stand-ins for exactly the
Arduino-ESP32 3.x and ESP-IDF 5.x calls it makes (controllers/firmware/esp32s3/host: MCPWM, PCNT,
GPIO and pin interrupts, the timer alarm, USB CDC, the ADC, the reset reason, the task watchdog,
each with the limits Espressif documents), linked with the C core, cached like the core
(controllers.core.cached_build). `Sketch` is one board: each instance loads its own copy of the
library, so a reset (`Sketch.reset`) starts the sketch's globals afresh as a real reset does, with
the motors where they stand. The board's wiring is pins.h's (`wiring()`); a wiring fault is a
changed `Wiring`. Units: counts, us of the board's clock, mV.
"""

from __future__ import annotations

import ctypes
import dataclasses
import os
import re
import shutil
import tempfile
from pathlib import Path

import numpy as np

from controllers import core
from controllers.core import FIRMWARE_DIR

SKETCH_DIR = FIRMWARE_DIR / "esp32s3"
HOST_DIR = SKETCH_DIR / "host"
C_FLAGS = ("-std=c99", "-Wall", "-Wextra", "-Werror", "-O2", "-fPIC")
CXX_FLAGS = ("-std=c++17", "-Wall", "-Wextra", "-Werror", "-O2", "-fPIC")
TICK_US = 1000  # the sketch's timer alarm, us (1 MHz timer, alarm at 1000: VRS_DEVICE_LOOP_RATE_HZ)
DECAY_BRAKE = 1  # VRS_DECAY_BRAKE


def cxx_compiler() -> str:
    return core.compiler("CXX", "c++", "C++", "g++")


def build(defines: tuple[str, ...] = ()) -> Path:
    """The sketch, its stand-ins and the core as one shared library (cached); `defines` (NAME=VALUE)
    override pins.h's settings, for tests that put a defect back."""
    cc, cxx = core.compiler(), cxx_compiler()
    dflags = [f"-D{d}" for d in defines]
    inputs = [*sorted(FIRMWARE_DIR.glob("*.[ch]")), *sorted(SKETCH_DIR.glob("*.[hi]*")),
              *sorted(HOST_DIR.rglob("*.[ch]*"))]

    def make(out: str) -> None:
        with tempfile.TemporaryDirectory() as tmp:
            objs = []
            for src in core.core_sources():
                obj = f"{tmp}/{src.stem}.o"
                core.run_compiler([cc, *C_FLAGS, f"-I{FIRMWARE_DIR}", "-c", str(src), "-o", obj], "the firmware core")
                objs.append(obj)
            includes = [f"-I{HOST_DIR}", f"-I{FIRMWARE_DIR}", f"-I{SKETCH_DIR}"]
            for src, lang in ((SKETCH_DIR / "esp32s3.ino", ["-x", "c++"]), (HOST_DIR / "esp32s3_host.cpp", [])):
                obj = f"{tmp}/{src.stem}.o"
                core.run_compiler([cxx, *CXX_FLAGS, *dflags, *includes, *lang, "-c", str(src), "-o", obj],
                                  f"the sketch ({src.name})")
                objs.append(obj)
            core.run_compiler([cxx, "-shared", "-o", out, *objs], "the sketch")

    return core.cached_build("esp32s3_sketch", ".so", [cc, cxx, *C_FLAGS, *CXX_FLAGS, *dflags], inputs, make)


@dataclasses.dataclass(frozen=True)
class Wiring:
    """Which GPIO each motor's bridge inputs and encoder outputs reach (-1: not connected), the battery's pin,
    and whether the board pulls every bridge input up (docs/firmware.md "Wiring": braked through reset and boot;
    without, the DRV8833's pull-downs hold them low: coast)."""

    in1: tuple[int, ...]
    in2: tuple[int, ...]
    enc_a: tuple[int, ...]
    enc_b: tuple[int, ...]
    battery_pin: int
    battery_divider: float
    in_pull_ups: bool = True


def wiring() -> Wiring:
    """The board as pins.h wires it."""
    text = (SKETCH_DIR / "pins.h").read_text()

    def array(name: str) -> tuple[int, ...]:
        m = re.search(rf"{name}\[\d+\]\s*=\s*\{{([^}}]*)\}}", text)
        return tuple(int(x) for x in m.group(1).split(","))

    def value(name: str) -> float:
        return float(re.search(rf"#define {name} (\d+)", text).group(1))

    return Wiring(array("PIN_IN1"), array("PIN_IN2"), array("PIN_ENC_A"), array("PIN_ENC_B"),
                  int(value("PIN_BATTERY")), value("BATTERY_DIVIDER"))


_U8, _I32, _U32, _I64, _U64, _VP = (ctypes.c_uint8, ctypes.c_int, ctypes.c_uint32, ctypes.c_int64, ctypes.c_uint64,
                                    ctypes.c_void_p)
_SIGNATURES = {
    "host_connect_motor": ([_I32, _I32, _I32, _I32, _I32, _I64], None),
    "host_set_encoder": ([_I32, _I64], None),
    "host_set_encoder_racing": ([_I32, _I64], None),
    "host_encoder_glitch": ([_I32], None),
    "host_set_pin_mv": ([_I32, _U32], None),
    "host_boot": ([_I32, _U64], None),
    "host_hang_loop": ([_U32], None),
    "host_pull_up": ([_I32, _I32], None),
    "host_advance": ([_U32], _I32),
    "host_bridge": ([_I32, _VP, _VP, _VP], None),
    "host_rx": ([_VP, _U32], _U32),
    "host_tx": ([_VP, _U32], _U32),
    "host_now_us": ([], _U64),
    "host_blocked_us": ([], _U64),
    "host_sample_times": ([_VP, _U32], _U32),
    "host_nvs_dump": ([_VP, _U32], _U32),
    "host_nvs_load": ([_VP, _U32], None),
    "vrs_get_state": ([_VP], _U8),
    "vrs_confirm_zero": ([_VP], _I32),
    "vrs_get_faults": ([_VP], ctypes.c_uint16),
    "vrs_get_fault_hinge": ([_VP], _U8),
    "vrs_get_rx_bad_frames": ([_VP], _U32),
    "vrs_get_telemetry_dropped": ([_VP], _U32),
    "vrs_get_battery_mv": ([_VP], ctypes.c_uint16),
    "vrs_get_derated": ([_VP], _U8),
}


def _load(path: Path) -> ctypes.CDLL:
    """A private copy of the library: its own globals, as a freshly reset board has."""
    fd, copy = tempfile.mkstemp(suffix=".so")
    os.close(fd)
    try:
        shutil.copyfile(path, copy)
        lib = ctypes.CDLL(copy)
    finally:
        os.unlink(copy)  # the loaded image stays mapped
    for fn, (args, res) in _SIGNATURES.items():
        f = getattr(lib, fn)
        f.argtypes, f.restype = args, res
    return lib


class Sketch:
    """One ESP32-S3 running the sketch, its motors at `positions` (encoder counts) when it starts.

    `run_tick` is one firmware tick of the board's time: encoders turned to the plant's counts, the
    battery at the ADC, the board run for TICK_US, each bridge's PWM and decay over that time, as the
    emulator's plant takes them. `rx` and `tx` are the USB CDC port's two ends.
    """

    def __init__(self, positions, reset_reason: int = 1, defines: tuple[str, ...] = (), wires: Wiring | None = None,
                 at_us: int = 0):
        self.path = build(defines)
        self.wires = wires or wiring()
        self.n = len(positions)
        self._tx = ctypes.create_string_buffer(4096)
        self._pwm, self._decay = ctypes.c_float(), ctypes.c_uint8()
        self.resets = 0
        self._boot(np.asarray(positions, np.int64), reset_reason, at_us)

    def _boot(self, positions, reason: int, at_us: int, flash: bytes = b"") -> None:
        self.lib = lib = _load(self.path)
        lib.host_nvs_load(flash, len(flash))
        self._core = ctypes.addressof(ctypes.c_uint8.in_dll(lib, "core"))
        w = self.wires
        for k in range(self.n):
            lib.host_connect_motor(k, w.in1[k], w.in2[k], w.enc_a[k], w.enc_b[k], int(positions[k]))
            for pin in (w.in1[k], w.in2[k]):
                lib.host_pull_up(pin, int(w.in_pull_ups))
        self._positions = positions.copy()
        lib.host_boot(reason, at_us)

    def reset(self, reason: int) -> None:
        """The board restarts (esp_reset_reason `reason`), its motors where they stand: the sketch from setup()."""
        self.resets += 1
        flash = ctypes.create_string_buffer(4096)
        used = self.lib.host_nvs_dump(flash, len(flash))
        kept = flash.raw[:used]  # the flash survives the reset
        self._boot(self._positions, reason, int(self.lib.host_now_us()), kept)

    def bridge_shares(self, k: int) -> np.ndarray:
        """Motor k's bridge since the last call: the shares of time forward, reverse, braking, coasting."""
        shares = np.zeros(4)
        self.lib.host_bridge(k, ctypes.byref(self._pwm), ctypes.byref(self._decay), shares.ctypes.data)
        return shares

    def hang(self, seconds: float) -> None:
        """loop() stops returning for `seconds` of the board's time from now (the timer's interrupts go on)."""
        self.lib.host_hang_loop(int(seconds * 1e6))

    def driven_after_hang(self, counts, seconds: float, ticks: int) -> int:
        """Ticks (ms at the loop's rate) a motor stays driven after loop() hangs for `seconds`, the encoders held at
        counts, up to `ticks` or the watchdog's reset."""
        self.hang(seconds)
        driven = 0
        for tick in range(ticks):
            pwm, _ = self.run_tick(0, counts, None, 8000)
            if np.any(pwm != 0):
                driven = tick + 1
            if self.resets:
                break
        return driven

    def confirm_zero(self) -> int:
        """What CONFIRM_ZERO does, done on the board (a bench user at power-on); 0 or the NACK reason."""
        return self.lib.vrs_confirm_zero(self._core)

    def run_tick(self, now_us: int, counts, current_ma, battery_mv: int) -> tuple[np.ndarray, np.ndarray]:
        """One tick: (pwm float32 (n,), decay uint8 (n,)) the bridges gave the motors over it. now_us is
        the emulator's clock; the board keeps its own, which started with it."""
        lib = self.lib
        for k in range(self.n):
            c = int(counts[k])
            if c != self._positions[k]:
                lib.host_set_encoder(k, c)
                self._positions[k] = c
        lib.host_set_pin_mv(self.wires.battery_pin, int(battery_mv / self.wires.battery_divider))
        if lib.host_advance(TICK_US):
            self.reset(6)  # ESP_RST_TASK_WDT
        pwm = np.zeros(self.n, np.float32)
        decay = np.zeros(self.n, np.uint8)
        for k in range(self.n):
            lib.host_bridge(k, ctypes.byref(self._pwm), ctypes.byref(self._decay), None)
            pwm[k], decay[k] = self._pwm.value, self._decay.value
        return pwm, decay

    def rx(self, data: bytes, now_us: int = 0) -> int:
        """Bytes from the host into the board's receive buffer; returns how many fit (the rest is lost)."""
        return self.lib.host_rx(data, len(data))

    def tx(self) -> bytes:
        """What the board has written for the host since the last call."""
        n = self.lib.host_tx(self._tx, len(self._tx))
        return self._tx.raw[:n]

    def sample_times(self) -> np.ndarray:
        """The board's last control ticks' sampling instants, us (up to 4096)."""
        out = np.zeros(4096, np.uint64)
        n = self.lib.host_sample_times(out.ctypes.data, len(out))
        return out[:n].astype(np.int64)

    @property
    def blocked_us(self) -> int:
        """Time the sketch's serial writes spent waiting on the host, us."""
        return int(self.lib.host_blocked_us())

    @property
    def state(self) -> int:
        return self.lib.vrs_get_state(self._core)

    @property
    def faults(self) -> int:
        return self.lib.vrs_get_faults(self._core)

    @property
    def fault_hinge(self) -> int:
        return self.lib.vrs_get_fault_hinge(self._core)

    def illegal_transitions(self) -> list[int]:
        """Per hinge, the software decoder's illegal transitions (both channels changed at once; PCNT hinges: 0)."""
        return list((ctypes.c_uint32 * 6).in_dll(self.lib, "soft_illegal"))

    @property
    def battery_mv(self) -> int:
        """The battery the core compensates for, mV."""
        return self.lib.vrs_get_battery_mv(self._core)

    @property
    def rx_bad_frames(self) -> int:
        return self.lib.vrs_get_rx_bad_frames(self._core)

    @property
    def telemetry_dropped(self) -> int:
        return self.lib.vrs_get_telemetry_dropped(self._core)

