"""The ESP32-S3 sketch in the loop (controllers.sketch): compiled on this host against stand-ins for its
peripherals, run on the emulator's plant. It agrees with the bare core and the twin; each defect the sketch
once had, put back, makes one of these fail."""

import configparser
import dataclasses
import glob
import json
import os
import re

import numpy as np
import pytest

from controllers import core, sketch
from controllers.encoder import target_counts
from cli import vrscroll
from twin.link import protocol as P
from twin.link.emulator import Emulator, EmulatorOptions
from twin.link.faults import FaultOptions
from twin.sim.plant import as_twin
from twin.sim.twin import Twin

TARGETS = np.radians([30, -25, 20, -20, 25, -30])  # every hinge, both directions


def frames(board, *msgs, battery_mv: int = 8000) -> list:
    """One tick (the encoders read), then msgs (seq 1, 2, ...) to a Sketch and one more: what it answered."""
    board.run_tick(0, board._positions, None, battery_mv)
    for i, m in enumerate(msgs):
        board.rx(P.encode(m, i + 1))
    board.run_tick(0, board._positions, None, battery_mv)
    return [m for _, m in P.Decoder().feed(board.tx())]


def emulated(spec, use_sketch: bool, ticks: int = 1000, heartbeat_every: int = 50, read: bool = True):
    """An emulator of the twin's own plant moved to TARGETS: (counts per tick (ticks, n), the emulator)."""
    emu = Emulator(spec, EmulatorOptions(plant=as_twin(spec), sketch=use_sketch, zeroed=True))
    emu.receive(P.encode(P.SetTargets(tuple(int(c) for c in target_counts(spec, TARGETS))), 1))
    rec = []
    for i in range(ticks):
        if i % heartbeat_every == 0:
            emu.receive(P.encode(P.Heartbeat(), 2 + i))
        emu.step()
        if read:
            emu.take_output()
        rec.append(emu.counts.copy())
    return np.array(rec), emu


def test_the_sketch_the_core_and_the_twin_agree_over_a_move(spec):
    """A 1 s move of every hinge, both directions, the same gains: within a few counts of each other."""
    bare, _ = emulated(spec, False)
    whole, emu = emulated(spec, True)
    twin = Twin(spec).move_to(TARGETS, max_time=1.0, stop_when_settled=False).counts
    assert emu.firmware.state == P.State.ACTIVE and emu.firmware.faults == 0
    assert np.abs(whole[-1] - target_counts(spec, TARGETS)).max() <= 2  # it arrived
    assert np.abs(whole - bare).max() <= 4  # the sketch starts its first tick one tick later
    assert np.abs(bare[1:] - twin[:-1]).max() <= 2


def test_both_encoder_decoders_count_the_same_way():
    """Hinges 0-3 count in PCNT units, 4-5 in a pin-change interrupt: one wiring, one sign (A leading B up)."""
    board = sketch.Sketch(np.zeros(6))
    for k, step in ((3, 40), (4, 40), (0, -25), (5, -25)):
        board.lib.host_set_encoder(k, step)
        board._positions[k] = step
    state = frames(board, P.GetState())[0]
    assert state.counts == (-25, 0, 0, 40, 40, -25)


def test_the_pcnt_stand_in_keeps_counting_past_its_16_bit_limit():
    """accum_count with watch points on the limits: the count goes on past 32767, as the driver extends it."""
    board = sketch.Sketch(np.zeros(6))
    board.lib.host_set_encoder(0, 40000)
    board._positions[0] = 40000
    assert frames(board, P.GetState())[0].counts[0] == 40000


def test_the_board_brakes_from_its_first_instruction_and_says_why_it_started(spec):
    """A reset mid-morph: from the reset through the ROM's boot and set-up (each call taking its time), the
    bridges brake, never coast (which lets the flaps fold) nor drive, and HELLO_REPLY names the reset. The
    stand-ins refuse digitalWrite before pinMode as Arduino-ESP32 3.x does: the old order (digitalWrite HIGH,
    then pinMode) coasts between pinMode and MCPWM's generators."""
    _, emu = emulated(spec, True, ticks=150)
    board = emu.firmware
    board.reset(P.ResetReason.BROWNOUT)
    board.lib.host_advance(100)  # 0.1 ms more: setup() has run, the first tick has not
    for k in range(6):
        shares = board.bridge_shares(k)
        assert shares[2] == 1.0, f"hinge {k}: forward, reverse, brake, coast shares {shares}"
    hello = frames(board, P.Hello())[0]
    assert hello.reset_reason == P.ResetReason.BROWNOUT and hello.setup_error == P.SetupStep.NONE
    assert hello.zero_confirmed == 0
    for _ in range(50):
        emu.step()
    assert emu.firmware.state == P.State.IDLE and np.all(emu.firmware.run_tick(0, emu.counts, None, 8000)[0] == 0)
    nack = frames(board, P.SetTargets((0,) * 6))[0]  # its counts restarted from where the flaps stood
    assert isinstance(nack, P.NackMsg) and nack.reason == P.Nack.ZERO_UNCONFIRMED
    ack, again = frames(board, P.ConfirmZero(), P.SetTargets((0,) * 6))
    assert ack.MSG == again.MSG == P.MsgId.ACK


def test_a_pwm_the_timer_cannot_make_is_a_named_hardware_fault():
    """A period the MCPWM timer refuses (over 65535 ticks): every bridge brakes from the reset on, the device says
    which set-up step failed, faults, and CLEAR_FAULT cannot clear it."""
    board = sketch.Sketch(np.zeros(6), defines=("PWM_PERIOD_TICKS=70000",))
    board.lib.host_advance(5000)
    for k in range(6):  # the group's pins stay the GPIO outputs set up first, high: braked, not coasting
        assert board.bridge_shares(k)[2] == 1.0
    hello, state = frames(board, P.Hello(), P.GetState())
    assert hello.setup_error == P.SetupStep.PWM_TIMER
    assert state.state == P.State.FAULT and state.faults & P.Fault.HARDWARE
    nack = frames(board, P.ClearFault())[0]
    assert isinstance(nack, P.NackMsg) and nack.reason == P.Nack.FAULT_PERSISTS
    nack = frames(board, P.SetTargets((10,) * 6))[0]
    assert isinstance(nack, P.NackMsg) and nack.reason == P.Nack.BAD_STATE


def test_a_host_that_stops_reading_costs_telemetry_not_ticks(spec):
    """Heartbeats keep coming but nothing is read for 1 s at 500 Hz telemetry: the tick period stays within
    +-0.5 ms, no serial write waits, telemetry is dropped, and the watchdog (fed by the heartbeats) stays quiet."""
    emu = Emulator(spec, EmulatorOptions(plant=as_twin(spec), sketch=True))
    emu.receive(P.encode(P.SetTelemetryRate(500), 1))
    for i in range(1000):
        if i % 50 == 0:
            emu.receive(P.encode(P.Heartbeat(), 2 + i))
        emu.step()  # nothing taken: the emulator stops draining the board once its backlog is full
    board = emu.firmware
    period = np.diff(board.sample_times()[-900:])
    assert np.abs(period - sketch.TICK_US).max() <= 500, np.unique(period)
    assert board.blocked_us == 0
    assert board.telemetry_dropped > 0 and board.faults == 0


def test_the_host_build_names_a_missing_cxx_compiler(monkeypatch, tmp_path):
    monkeypatch.setenv("VRSCROLL_CACHE", str(tmp_path))
    monkeypatch.setenv("CXX", "no-such-cxx")
    with pytest.raises(sketch.core.FirmwareBuildError, match="needs a C\\+\\+ compiler and `no-such-cxx`"):
        sketch.build()


def test_commands_against_the_sketch_on_a_pty_wait_for_the_zero(tmp_path):
    """`emulate --sketch` without --zeroed, as a device fresh from power-on: status says the zero is unconfirmed,
    mirror refuses to move it naming `vrscroll zero`, zero confirms, mirror then moves it."""
    from twin.link.emulator_process import EmulatorProcess

    with EmulatorProcess(tmp_path / "emulator.jsonl", "--sketch", "--ideal") as dev:
        r = vrscroll("status", "--serial", dev.port)
        assert r.returncode == 0, r.stderr
        assert "started  POWERON" in r.stdout and "faults   none" in r.stdout and "zero     UNCONFIRMED" in r.stdout
        r = vrscroll("mirror", "--serial", dev.port, "--angles=5,0,0,0,0,0", "--tolerance-deg", "30", cwd=tmp_path)
        assert r.returncode == 2 and f"vrscroll zero --serial {dev.port}" in r.stderr, r.stderr
        assert not [e for e in dev.events("rx") if e["msg"] == "SET_TARGETS"]
        r = vrscroll("zero", "--serial", dev.port)
        assert r.returncode == 0 and "zero confirmed" in r.stdout, r.stderr
        r = vrscroll("mirror", "--serial", dev.port, "--angles=5,0,0,0,0,0", "--tolerance-deg", "30", cwd=tmp_path)
        assert r.returncode == 0, r.stdout + r.stderr


# PlatformIO's source matching (platformio-core: platformio/fs.py match_src_files; the extensions of
# builder/tools/piobuild.py SRC_BUILD_EXT, and .ino/.pde, which the Arduino builder converts)
PIO_BUILD_EXT = ("c", "cc", "cpp", "cxx", "c++", "S", "spp", "SPP", "sx", "s", "asm", "ASM", "ino", "pde")
PIO_DEFAULT_FILTER = "+<*> -<.git/> -<.svn/>"


def pio_sources(src_dir, src_filter: str) -> set:
    """The files PlatformIO compiles from src_dir under src_filter: each +<glob> adds, each -<glob> removes, a
    folder standing for every file below it."""
    matched = set()
    for action, pattern in re.findall(r"(\+|-)<([^>]+)>", src_filter):
        found = set()
        for item in glob.glob(os.path.join(glob.escape(str(src_dir)), pattern), recursive=True):
            files = [os.path.join(r, f) for r, _, fs in os.walk(item) for f in fs] if os.path.isdir(item) else [item]
            found |= {os.path.relpath(f, src_dir) for f in files if f.rsplit(".", 1)[-1] in PIO_BUILD_EXT}
        matched = matched | found if action == "+" else matched - found
    return matched


def test_platformio_builds_only_the_sketch_and_the_core():
    """platformio.ini's build_src_filter, applied to the tree as PlatformIO applies it, picks the sketch and
    nothing else (not host/'s stand-ins, whose HWCDC:: and Preferences:: would clash with Arduino's); the core's
    library.json picks exactly the core's sources."""
    ini = configparser.ConfigParser()
    ini.read(sketch.SKETCH_DIR / "platformio.ini")
    src_dir = sketch.SKETCH_DIR / ini.get("platformio", "src_dir", fallback="src")
    src_filter = ini.get("env:esp32s3", "build_src_filter", fallback=PIO_DEFAULT_FILTER)
    assert pio_sources(src_dir, src_filter) == {"esp32s3.ino"}
    lib = json.loads((core.FIRMWARE_DIR / "library.json").read_text())["build"]
    lib_dir = core.FIRMWARE_DIR / lib.get("srcDir", "src")
    picked = pio_sources(lib_dir, " ".join(lib.get("srcFilter", [PIO_DEFAULT_FILTER])))
    assert picked == {p.name for p in core.core_sources()}


def test_without_the_boards_pull_ups_the_bridges_coast_until_setup():
    """What holds the inputs before setup() is the board's: without its pull-ups the DRV8833's own pull-downs
    hold both inputs low (coast) from the reset until setup() brakes them, the ROM's boot."""
    bare = sketch.Sketch(np.zeros(6), wires=dataclasses.replace(sketch.wiring(), in_pull_ups=False))
    shares = bare.bridge_shares(0)
    assert shares[3] > 0.99, shares


def test_a_hung_loop_stops_the_motors_within_a_few_ticks(spec):
    """Mid-move, loop() hangs (a wait that never ends): the timer's interrupt, which does not need loop(), brakes
    every bridge within a few ticks; before, MCPWM ran on at the last compare values until the 5 s task watchdog.
    Then the watchdog resets the board, which starts braked and says why."""
    _, emu = emulated(spec, True, ticks=60)
    board = emu.firmware
    assert np.any(board.run_tick(0, emu.counts, None, 8000)[0] != 0)  # driving when it hangs
    driven_ms = board.driven_after_hang(emu.counts, 10.0, 6000)
    assert driven_ms <= 5, f"a motor stayed driven {driven_ms} ms after loop() hung"
    assert board.resets == 1 and frames(board, P.Hello())[0].reset_reason == P.ResetReason.TASK_WDT


@pytest.mark.parametrize("broken_mv", [450, 0, 9300], ids=["150mV-at-the-pin", "zero", "adc-top"])
def test_an_implausible_battery_reading_is_a_named_fault_and_no_more_than_nominal_compensation(broken_mv):
    """The pack reads 7.6 V; one sample of 0 (noise) is filtered out. Then the divider breaks: within the
    filter's time the device faults BATTERY and compensates as for the spec's nominal pack, not for the reading
    (150 mV at the pin multiplied the loop's gain by 40; 0 removed compensation); CLEAR_FAULT is refused while
    the reading stays out, and accepted once the pack reads right again."""
    board = sketch.Sketch(np.zeros(6))
    for mv in [7600] * 20 + [0] + [7600] * 5:
        board.run_tick(0, board._positions, None, mv)
    assert board.faults == 0 and abs(board.battery_mv - 7600) < 500
    for tick in range(40):
        board.run_tick(0, board._positions, None, broken_mv)
        assert board.battery_mv >= 4500, board.battery_mv  # never compensating for the broken reading
        if board.faults:
            break
    assert board.faults == P.Fault.BATTERY and board.state == P.State.FAULT and tick < 30
    assert board.battery_mv == 7400  # the spec's nominal (supply_voltage)
    nack = frames(board, P.ClearFault(), battery_mv=broken_mv)[0]
    assert isinstance(nack, P.NackMsg) and nack.reason == P.Nack.FAULT_PERSISTS
    for _ in range(60):
        board.run_tick(0, board._positions, None, 7600)
    ack = frames(board, P.GetState(), P.ClearFault())[1]  # seq 2: not the repeat of the refused seq 1
    assert ack.MSG == P.MsgId.ACK and board.faults == 0


def test_every_reset_reason_the_s3_gives_is_named_on_the_host():
    """ESP-IDF v5.4.1's esp_reset_reason_t, 0-15 (the stand-in's copy of esp_system.h): each value has its name in
    the protocol's table, so `status` prints USB, not 11, after a USB reset; the board reports what it was given."""
    text = (sketch.HOST_DIR / "esp_system.h").read_text()
    names = re.findall(r"ESP_RST_(\w+)", re.search(r"typedef enum \{(.*?)\}", text, re.S).group(1))
    assert len(names) == 16 and names[11] == "USB"
    assert [P.enum_name(P.ResetReason, v) for v in range(len(names))] == names
    board = sketch.Sketch(np.zeros(6), reset_reason=11)
    assert frames(board, P.Hello())[0].reset_reason == P.ResetReason.USB


def test_a_derated_hinge_still_faults_stall():
    """Hinge 0 creeps under full duty (a heavy load: 1 count per 100 ms, never a stall) until the I2t protection
    holds it to 0.25 duty, then jams: STALL, at the same share of the duty it may give (0.5 x 0.25), within its
    0.3 s; before, STALL at 0.5 could never trip once derated."""
    board = sketch.Sketch(np.zeros(6))
    assert frames(board, P.ConfirmZero(), P.SetTargets((300, 0, 0, 0, 0, 0)))[1].MSG == P.MsgId.ACK
    pos = board._positions.copy()
    for tick in range(2500):
        pos[0] = tick // 100
        board.run_tick(0, pos, None, 8000)
    assert board.state == P.State.ACTIVE or board.state == P.State.HOLDING, board.faults
    assert board.lib.vrs_get_derated(board._core) & 1
    for tick in range(1000):  # jammed where it stands
        board.run_tick(0, pos, None, 8000)
        if board.faults:
            break
    assert board.faults == P.Fault.STALL and board.fault_hinge == 0 and tick <= 350, (board.faults, tick)


def test_the_software_decoder_reads_one_snapshot_per_edge_and_counts_illegal_transitions():
    """Hinges 4-5 decode in a pin interrupt. Edges closer than the interrupt's latency (each landing while the one
    before is being read): one read of both channels counts every edge, where two digitalReads saw states that
    never were. Both channels flipping at once (a glitch) moves no count and is counted as illegal."""
    board = sketch.Sketch(np.zeros(6))
    board.lib.host_set_encoder_racing(4, 400)
    board.lib.host_set_encoder_racing(5, -400)
    board.lib.host_set_encoder_racing(3, 400)  # a PCNT hinge, for comparison
    board._positions[3:] = (400, 400, -400)
    assert frames(board, P.GetState())[0].counts[3:] == (400, 400, -400)
    assert board.illegal_transitions() == [0] * 6
    board.lib.host_encoder_glitch(4)
    assert frames(board, P.GetState())[0].counts[4] == 400 and board.illegal_transitions()[4] == 1
    pins = sketch.wiring()
    assert max(pins.enc_a[4:] + pins.enc_b[4:]) < 32  # one GPIO_IN_REG holds them


def test_the_devkits_rgb_led_pin_is_named_and_never_written():
    """The DevKitC-1's RGB LED is on GPIO48 (v1.0) or GPIO38 (v1.1), each a bridge input here: pins.h names both
    and the bridge each shares, the wiring docs say so, and the sketch never writes the LED."""
    text = (sketch.SKETCH_DIR / "pins.h").read_text()
    leds = {rev: int(pin) for rev, pin in re.findall(r"#define PIN_DEVKIT_(V1_\d)_RGB_LED (\d+)", text)}
    assert leds == {"V1_0": 48, "V1_1": 38}
    w = sketch.wiring()
    assert [w.in1.index(pin) for pin in leds.values()] == [5, 2]  # hinge 5's and hinge 2's IN1
    docs = (core.FIRMWARE_DIR.parents[1] / "docs" / "firmware.md").read_text()
    assert "GPIO38 on v1.1 (hinge 2's IN1)" in docs and "GPIO48 on board v1.0 (hinge 5's IN1)" in docs
    ino = (sketch.SKETCH_DIR / "esp32s3.ino").read_text()
    assert not re.search(r"rgbLedWrite|neopixelWrite|RGB_LED|RGB_BUILTIN|LED_BUILTIN", ino)


@pytest.mark.parametrize("fault", ["encoder-reversed:2", "motor-reversed:4"])
def test_a_runaway_faults_within_the_stall_window(spec, fault):
    """A hinge wired the wrong way round, not corrected, given a 10 deg target: the PID drives it away from the
    target at its full duty; the core faults RUNAWAY on that hinge within three runaway windows (a tenth of the
    stall time each) and the few ms its duty takes to rise, before the range (LIMIT, 104-136 ms), and brakes."""
    k = int(fault.split(":")[1])
    emu = Emulator(spec, EmulatorOptions(plant=as_twin(spec), sketch=True, zeroed=True,
                                         faults=FaultOptions(latency_ms=0.0, wiring=(fault,))))
    targets = np.zeros(6)
    targets[k] = np.radians(10)
    emu.receive(P.encode(P.SetTargets(tuple(int(c) for c in target_counts(spec, targets))), 1))
    for tick in range(1000):
        emu.step()
        emu.take_output()
        if emu.firmware.faults:
            break
    board = emu.firmware
    assert board.faults == P.Fault.RUNAWAY and board.fault_hinge == k, (board.faults, board.fault_hinge)
    assert tick <= 3 * spec.stall_time * 100 + 5, tick
    assert np.all(board.run_tick(0, emu.counts, None, 8000)[0] == 0)


def test_a_disabled_hinge_is_kept_in_flash_and_no_cleared_fault_drives_it():
    """Hinge 3 disabled (SET_WIRING's WIRING_DISABLED, as bring-up sets it for a dead wire): the sketch keeps it in
    NVS with the wiring, so after a power cycle HELLO and STATE still name it; with the zero confirmed and a fault
    cleared, a target that moves it is refused naming it, and under targets for every other hinge its bridge brakes
    the whole time while theirs drive."""
    board = sketch.Sketch(np.zeros(6))
    identity, off = tuple(range(6)), (0, 0, 0, P.WIRING_DISABLED, 0, 0)
    assert frames(board, P.SetWiring(identity, off, identity))[0].MSG == P.MsgId.ACK
    board.reset(P.ResetReason.POWERON)
    hello, state = frames(board, P.Hello(), P.GetState())
    assert hello.disabled == state.disabled == 0b1000 and hello.wiring_set == 0
    assert frames(board, P.ConfirmZero(), P.EStop(), P.ClearFault())[2].MSG == P.MsgId.ACK
    for refused in (P.SetTargets((60, 60, 60, 60, 60, 60)), P.Pulse(3, 1000, 30)):
        assert frames(board, refused)[0] == P.NackMsg(refused.MSG, P.Nack.HINGE_DISABLED, 3)
    assert frames(board, P.SetTargets((60, 60, 60, 0, 60, 60)))[0].MSG == P.MsgId.ACK
    ticks = [board.run_tick(0, board._positions, None, 8000) for _ in range(100)]
    assert all(pwm[3] == 0 and decay[3] == 1 and np.all(np.delete(pwm, 3) > 0) for pwm, decay in ticks[2:]), ticks[:3]
    assert board.state == P.State.ACTIVE
