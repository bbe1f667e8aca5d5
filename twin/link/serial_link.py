"""The host end of the serial link: requests with acknowledgements, heartbeat, telemetry, a session log.

`Link(url)` talks the protocol of twin/link/protocol.py over any pyserial URL: a real
port (/dev/ttyACM0), a pty path (the emulator's), or socket://host:port. A reader
thread decodes every byte (resyncing after garbage); replies go to the request
waiting for them, telemetry into a queue of at most TELEMETRY_KEPT frames, the oldest dropped (or to a
callback). A heartbeat thread keeps the device's watchdog fed. Everything sent
and received is written, as it happens, to a JSON-lines session log, one flushed
line per event, so a crash loses nothing before it.

    with Link("/dev/pts/5", log_path="session.jsonl") as link:
        link.set_telemetry_rate(500)
        link.set_targets([0, 100, 0, 0, -100, 0])
        frame = link.telemetry(timeout=1.0)
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import queue
import threading
import time

import numpy as np
import serial

from controllers.core import MAX_HINGES
from controllers.program import COAST, ProgramEnd, ProgramRun, end_name
from twin.device.spec import LOOP_RATE_RANGE
from twin.formats.gains import check_gains
from twin.link import protocol as P


class LinkError(RuntimeError):
    """The link failed: the port went away, or the device stopped answering."""


class LinkTimeout(LinkError):
    """No reply after every retry."""


class NackError(LinkError):
    """The device refused a command; `reason` is a protocol.Nack, `detail` its argument (e.g. a hinge)."""

    def __init__(self, msg_name: str, reason: int, detail: int):
        self.reason = P.Nack(reason) if reason in P.Nack._value2member_map_ else reason
        self.detail = detail
        name = self.reason.name if isinstance(self.reason, P.Nack) else f"reason {reason}"
        hint = (f": its zero is unconfirmed since it started: {zero_hint('PORT')}"
                if self.reason == P.Nack.ZERO_UNCONFIRMED else
                f": hinge {detail} is disabled on the device (braked, never driven: a dead wire bring-up named, or "
                f"disabled by hand); mend it and run `vrscroll bringup`, or `vrscroll status --serial PORT "
                f"--enable-hinges {detail}`" if self.reason == P.Nack.HINGE_DISABLED
                else f" (detail {detail})")
        super().__init__(f"device refused {msg_name}: {name}{hint}")


def hinge_list(bits: int) -> list[int]:
    """The hinges whose bits are set in a per-hinge bit mask (STATE's derated and disabled)."""
    return [k for k in range(bits.bit_length()) if bits >> k & 1]


def zero_hint(port: str) -> str:
    """What to do about a device whose zero is unconfirmed."""
    return f"lay it flat and run `vrscroll zero --serial {port}` (docs/firmware.md, 'Bring-up')"


class ZeroUnconfirmed(LinkError):
    """The device started (a power-on, a brown-out, a reset) and nobody has confirmed its flat pose since:
    its counts may not be the flaps' angles, so nothing moves it."""


class DeviceUntrusted(LinkError):
    """The device said something it cannot mean: its clock going back (a restart), stuck or racing ahead; its
    zero lost mid-session (a restart); a state, fault bit, blamed hinge, hinge count, loop rate or watchdog
    out of range; gains it ACKed and does not hold. The host stops feeding its watchdog at once, e-stops it if
    this session moved it, and every later request or telemetry read raises this (docs/protocol.md, "What the
    host does not take from the device")."""


_CLOSED = object()  # put in the telemetry queue when the link ends
# sent before every frame: it ends whatever is on the line before it (noise, a write cut short by an
# interrupt), so the frame is read whole (docs/protocol.md, "Frames"); without it a frame that followed garbage
# with no 0x00 was dropped with it, and under a stream of noise no request was answered
FRAME_START = b"\x00"
# telemetry frames the link keeps for its reader, the oldest dropped beyond (`telemetry_unread` counts them):
# 20 s at 500 Hz; a queue nobody read grew by 0.45 MB/s without end (issue 40)
TELEMETRY_KEPT = 10_000

# What a HELLO_REPLY's figures may be (inclusive): a loop the twin can simulate and telemetry can follow (any
# design's, LOOP_RATE_RANGE), a watchdog the host's 50 ms heartbeat can feed (at least two of them) that fires
# before long (0, off, would leave a device driving after its host died)
HELLO_RANGES = {"loop_rate_hz": LOOP_RATE_RANGE, "watchdog_ms": (100, 60_000), "max_telemetry_hz": (1, 10_000)}
CLOCK_AHEAD_S = 0.25  # s the device's clock may run ahead of the host's over a session ...
CLOCK_DRIFT = 1e-3  # ... plus this share of the session's length (a crystal is within 1e-4)
ESTOP_RETRY_S = 0.05  # s between an ESTOP's tries
CLOCK_BACK_US = 1000  # µs a stamp may precede the one before it (one tick: a reply and a frame stamped apart)
CLOCK_STUCK_S = 0.2  # s of host time after which a reply stamped as the last stamp means a stopped clock
PTY_RETRIES = 19  # a Link's resends where the device is on a pseudo-terminal: an emulator on this host's own CPU
# (`vrscroll emulate`, twin.link.pty_device.served), which the machine's load can leave unscheduled while the host
# runs. In the slow bring-up sweeps on 2 cores shared by five sessions (load 8-9) a served emulator's loop stopped
# for 0.29 and 0.33 s at once in both test workers while the Link sent its 2nd and 3rd try of 100 ms (a real
# device, which does not share the host's CPU, answers within the 4 tries' 0.4 s), and the gen-2 collections of a
# long test session held the process 0.33-0.66 s; `calibrate --serial` on `vrscroll emulate` at load 21 lost a
# GET_PROGRAM's 4 tries. 20 tries of the Link's 100 ms wait out 2 s.
PROGRAM_STILL_S = 2.0  # s of host time a running program's ticks may stand still (wait_program): a device's loop
# that stopped; a loaded host's emulator left without a core goes on within it (at load 9 on 2 cores its thread
# was left waiting up to 0.56 s: PTY_RETRIES)
MAX_LOOP_RATE_KHZ = 2  # program samples kept per ms of PROGRAM_MAX_MS: bounded, whatever the device sends


def program_message(hinge: int, segments, window_counts, timeout_s: float | None = None) -> P.Program:
    """The PROGRAM message for segments ((duty, duration_s) pairs; duty controllers.program.COAST: the hinge
    coasts), a window (low, high counts) and a timeout (s; default the segments' sum); ValueError naming the
    bound for a program the device would refuse on its face (the hinge's range and its present counts the
    device checks)."""
    segments = [(d if d == COAST else float(d), float(s)) for d, s in segments]
    low, high = (int(w) for w in window_counts)
    ms = [round(s * 1000) for _, s in segments]
    total = sum(ms)
    timeout_ms = total if timeout_s is None else round(timeout_s * 1000)
    if not 1 <= len(segments) <= P.PROGRAM_MAX_SEGMENTS:
        raise ValueError(f"a program has 1 to {P.PROGRAM_MAX_SEGMENTS} segments, not {len(segments)}")
    if any(d != COAST and not abs(round(d * P.DUTY_SCALE)) <= round(P.PROGRAM_MAX_DUTY * P.DUTY_SCALE)
           for d, _ in segments):
        raise ValueError(f"a program's |duty| is at most {P.PROGRAM_MAX_DUTY}: {[d for d, _ in segments]}")
    if any(m < 1 for m in ms) or total > P.PROGRAM_MAX_MS or not 1 <= timeout_ms <= P.PROGRAM_MAX_MS:
        raise ValueError(f"a program's segments last 1 ms or more, {P.PROGRAM_MAX_MS} ms in all, and its timeout "
                         f"1 to {P.PROGRAM_MAX_MS} ms: segments {ms} ms, timeout {timeout_ms} ms")
    if not low < high:
        raise ValueError(f"a program's window is low < high counts, not [{low}, {high}]")
    pad = P.PROGRAM_MAX_SEGMENTS - len(segments)
    return P.Program(hinge, low, high, timeout_ms, len(segments),
                     tuple(P.PROGRAM_COAST if d == COAST else round(d * P.DUTY_SCALE) for d, _ in segments)
                     + (0,) * pad, tuple(ms) + (0,) * pad)


def program_run(hinge: int, samples: dict, status: P.ProgramStatus, tick_s: float) -> ProgramRun:
    """A program's run from its PROGRAM_SAMPLEs ({seq: ProgramSample}, those lost absent) and the status that
    ended it: a sample per tick received, a coasting tick's duty 0 with its `coasting` set."""
    index = np.array(sorted(i for i in samples if i < status.ticks), np.int64)
    wire = np.array([samples[i].duty for i in index], np.int64)
    coasting = wire == P.PROGRAM_COAST
    return ProgramRun(hinge=hinge, time_s=index * tick_s, duty=np.where(coasting, 0, wire) / P.DUTY_SCALE,
                      counts=np.array([samples[i].counts for i in index], np.int64),
                      battery_mV=float(status.battery_mv) if status.battery_mv else None,
                      end=end_name(status.end), samples_lost=int(status.ticks - len(index)), coasting=coasting)


def on_pty(url: str) -> bool:
    """Whether url is a pseudo-terminal's path (a device emulated on this host), by its device number's major
    (Linux's UNIX98 pty slaves: 136-143)."""
    try:
        return 136 <= os.major(os.stat(url).st_rdev) <= 143
    except (OSError, ValueError):
        return False


class Link:
    """One session with a device over a serial port.

    timeout: s to wait for each reply; retries: resends (with the same sequence
    number; every command is idempotent) before LinkTimeout (default: 3, or PTY_RETRIES where url is a
    pseudo-terminal: an emulator on this host's CPU, `vrscroll emulate`); heartbeat: s between
    heartbeats (None: none, e.g. to test the watchdog); telemetry_callback: called
    from the reader thread with each (seq, Telemetry) instead of queueing it; hinges: the hinge count of
    the spec the host uses (a device whose HELLO says otherwise is refused).
    """

    def __init__(self, url: str, log_path=None, baudrate: int = 921600, timeout: float = 0.1, retries: int | None = None,
                 heartbeat: float | None = 0.05, telemetry_callback=None, log_telemetry: bool = True,
                 hinges: int | None = None):
        self.url = url
        self.hinges = hinges  # the hinge count the host's spec has: a device that says otherwise is refused
        self.timeout = timeout
        self.retries = retries if retries is not None else PTY_RETRIES if on_pty(url) else 3
        self.heartbeat_interval = heartbeat
        self.telemetry_callback = telemetry_callback
        self.log_telemetry = log_telemetry
        self._baudrate = baudrate
        self._serial = None
        self._log = open(log_path, "a", buffering=1) if log_path else None
        self._log_lock = threading.Lock()
        self._write_lock = threading.Lock()
        self._pending: dict[int, list] = {}  # seq -> [event, reply]
        self._pending_lock = threading.Lock()
        self._seq = 0
        self._stop = threading.Event()
        self._heartbeat_off = threading.Event()
        self._threads: list[threading.Thread] = []
        self._last_sent = 0.0
        self._telemetry: queue.Queue = queue.Queue()  # at most TELEMETRY_KEPT frames: the oldest dropped first
        self.telemetry_unread = 0  # frames dropped from the queue because nobody read them
        self._last_telemetry_seq = None
        self.decoder = P.Decoder()
        self.error: LinkError | None = None
        self.telemetry_received = 0
        self.telemetry_lost = 0  # gaps in the device's telemetry sequence numbers
        self.info: P.HelloReply | None = None
        self.zero_confirmed = False  # from HELLO_REPLY, and set by confirm_zero
        self.moved = False  # whether this session sent targets
        self.echoes = 0  # frames that came back as the host sent them (a looped-back line)
        self._samples: dict[int, P.ProgramSample] = {}  # the running program's samples by tick index
        self.untrusted: DeviceUntrusted | None = None
        self._clock = None  # (first device stamp us, host time s at it, last stamp us unwrapped, host time s at it)
        self._last_telemetry_us = None

    # ---- session ----------------------------------------------------------------------
    def open(self, hello: bool = True) -> "Link":
        """Open the port, start the reader and heartbeat threads, and (by default) shake hands."""
        try:
            # exclusive: a second host on the same port is refused here, not mixed into this session's bytes
            self._serial = serial.serial_for_url(self.url, baudrate=self._baudrate, timeout=0.01, exclusive=True)
            self._serial.reset_input_buffer()
        except (serial.SerialException, OSError, ValueError) as exc:
            if "exclusively lock" in str(exc):
                raise LinkError(f"cannot open {self.url}: the port is in use by another program (another vrscroll "
                                "session, a serial monitor); close it first") from None
            raise LinkError(f"cannot open {self.url}: {exc}") from exc
        self.log("open", url=self.url)
        self._start(self._reader, "link-reader")
        if self.heartbeat_interval:
            self._start(self._heartbeat, "link-heartbeat")
        if hello:
            try:
                self.hello()
            except BaseException:
                self.close()  # the threads and the port, as __exit__ would (it is not called when __enter__ fails)
                raise
        return self

    def _start(self, target, name) -> None:
        t = threading.Thread(target=target, name=name, daemon=True)
        t.start()
        self._threads.append(t)

    def close(self) -> None:
        """Stop the threads and close the port and the log (safe to call twice)."""
        self._stop.set()
        for t in self._threads:
            if t is not threading.current_thread():
                t.join(timeout=1.0)
        self._threads.clear()
        if self._serial is not None:
            try:
                self._serial.close()
            except Exception:  # the port may already be gone
                pass
            self._serial = None
            self.log("close", rx_bad_frames=self.decoder.bad_frames, telemetry_received=self.telemetry_received,
                     telemetry_lost=self.telemetry_lost, telemetry_unread=self.telemetry_unread)
        if self._log:
            with self._log_lock:
                self._log.close()
                self._log = None

    def __enter__(self) -> "Link":
        return self.open()

    def __exit__(self, exc_type, exc, tb) -> None:
        """Close; a session that sent targets and ends on an exception e-stops the device first, so it never
        keeps driving toward them unwatched: an interrupt (Ctrl-C; SIGTERM, SIGHUP, SIGQUIT, which the CLI
        raises as KeyboardInterrupt: twin.commands.interrupts), a closed terminal (EIO writing to it), a
        device the host stopped trusting, any error of the host's own."""
        if exc_type is not None:
            self.estop_if_moved("estop_on_interrupt" if issubclass(exc_type, KeyboardInterrupt) else "estop_on_error")
        self.close()

    def estop_if_moved(self, event: str) -> None:
        """ESTOP, logged as `event`, if this session sent targets or a pulse; a failure is logged, not raised
        (the reason the session ends is what its caller hears about)."""
        if not self.moved:
            return
        try:
            self.estop()
            self.log(event)
        except Exception as failed:
            self.log(event + "_failed", error=str(failed))

    def log(self, event: str, **fields) -> None:
        """One line in the session log, flushed: host time (s since the epoch), event, fields."""
        if self._log is None:
            return
        line = json.dumps({"t": round(time.time(), 6), "event": event, **fields}, default=_jsonable)
        with self._log_lock:
            if self._log is not None:
                self._log.write(line + "\n")

    # ---- sending ----------------------------------------------------------------------
    def _fail(self, why: str, exc: BaseException | None = None) -> LinkError:
        if self.error is None:
            self.error = LinkError(f"{self.url}: {why}" + (f" ({exc})" if exc else ""))
            self.log("link_error", error=str(self.error))
            self._stop.set()
            with self._pending_lock:
                for slot in self._pending.values():
                    slot[0].set()
            self._telemetry.put(_CLOSED)
        return self.error

    def distrust(self, why: str) -> DeviceUntrusted:
        """Stop trusting the device (the first reason is kept): no more heartbeats, so its watchdog is not fed
        by a host that cannot read it; an ESTOP sent at once if this session moved it; waiting requests and
        telemetry reads raise the error. Returns it, to be raised."""
        with self._pending_lock:
            first = self.untrusted is None
            if first:
                self.untrusted = DeviceUntrusted(f"{self.url}: the device cannot be trusted: {why}")
        if not first:
            return self.untrusted
        self._heartbeat_off.set()
        self.log("device_untrusted", error=str(self.untrusted), moved=self.moved)
        if self.moved:
            try:
                self._write(FRAME_START + P.encode(P.EStop(), self._next_seq()), estop=True)
                self.log("estop_untrusted")
            except LinkError as exc:
                self.log("estop_untrusted_failed", error=str(exc))
        with self._pending_lock:
            for slot in self._pending.values():
                slot[0].set()
        self._telemetry.put(_CLOSED)
        return self.untrusted

    def _check(self, estop: bool = False) -> None:
        """LinkError when the link failed or is closed; DeviceUntrusted once the device is, except for an ESTOP."""
        if self.error is not None:
            raise self.error
        if self._serial is None:
            raise LinkError(f"{self.url}: link is not open")
        if self.untrusted is not None and not estop:
            raise self.untrusted

    def _write(self, frame: bytes, estop: bool = False) -> None:
        self._check(estop)
        try:
            with self._write_lock:
                self._serial.write(frame)
                self._last_sent = time.monotonic()
        except (serial.SerialException, OSError, TypeError, AttributeError) as exc:
            raise self._fail("port went away while writing", exc) from exc

    def write_raw(self, data: bytes) -> None:
        """Bytes straight onto the wire (for tests: garbage)."""
        self.log("tx_raw", hex=data.hex())
        self._write(data)

    def send(self, msg) -> int:
        """Send a message that expects no reply (HEARTBEAT); returns its sequence number."""
        seq = self._next_seq()
        self._write(FRAME_START + P.encode(msg, seq))
        return seq

    def _next_seq(self) -> int:
        with self._pending_lock:
            self._seq = (self._seq + 1) & 0xFFFF
            return self._seq

    def request(self, msg, timeout: float | None = None, retries: int | None = None):
        """Send a command and wait for its reply (ACK, or the data asked for); NackError on NACK.

        Resends with the same sequence number up to `retries` times, each after
        `timeout` s of silence; LinkTimeout after the last.
        """
        timeout = self.timeout if timeout is None else timeout
        retries = self.retries if retries is None else retries
        estop = msg.MSG == P.MsgId.ESTOP  # still sent to a device the host does not trust
        self._check(estop)
        seq = self._next_seq()
        slot = [threading.Event(), None, msg.MSG, time.monotonic()]  # answered, the answer, what it answers, sent
        with self._pending_lock:
            self._pending[seq] = slot
        frame = FRAME_START + P.encode(msg, seq)
        fields = _fields(msg)
        try:
            for attempt in range(retries + 1):
                self.log("tx", msg=msg.MSG.name, seq=seq, attempt=attempt, **fields)
                self._write(frame, estop)
                if slot[0].wait(timeout):
                    break
            else:
                self.log("timeout", msg=msg.MSG.name, seq=seq)
                other = self.decoder.other_version
                echo = (f" (the device answers in protocol version {other}, this host speaks {P.PROTOCOL_VERSION}: "
                        "flash the firmware this host ships, docs/firmware.md 'Flashing')" if other is not None else
                        " (only the host's own frames came back: a looped-back line, not a device?)"
                        if self.echoes else "")
                raise LinkTimeout(f"{self.url}: no reply to {msg.MSG.name} after {retries + 1} tries "
                                  f"of {timeout * 1000:.0f} ms{echo}")
        finally:
            with self._pending_lock:
                self._pending.pop(seq, None)
        self._check(estop)
        reply = slot[1]
        if isinstance(reply, P.NackMsg):
            raise NackError(msg.MSG.name, reply.reason, reply.detail)
        return reply

    # ---- commands -----------------------------------------------------------------------
    def hello(self) -> P.HelloReply:
        reply = self.request(P.Hello())
        if reply.protocol != P.PROTOCOL_VERSION:
            raise LinkError(f"{self.url}: device speaks protocol {reply.protocol}, this host {P.PROTOCOL_VERSION}")
        if not 1 <= reply.n_hinges <= MAX_HINGES:
            raise LinkError(f"{self.url}: the device says it has {reply.n_hinges} hinges; a device has 1 to {MAX_HINGES}")
        if self.hinges is not None and reply.n_hinges != self.hinges:
            raise LinkError(f"{self.url}: the device has {reply.n_hinges} hinges, the spec this host uses "
                            f"{self.hinges}: select the device's profile (--device) or calibrate one for it")
        for key, (low, high) in HELLO_RANGES.items():
            if not low <= getattr(reply, key) <= high:
                raise self.distrust(f"HELLO says {key} {getattr(reply, key)}, outside {low}..{high}")
        if reply.max_telemetry_hz > reply.loop_rate_hz:
            raise self.distrust(f"HELLO says max_telemetry_hz {reply.max_telemetry_hz}, above its loop rate "
                                f"{reply.loop_rate_hz} Hz")
        for key, kind in (("reset_reason", P.ResetReason), ("setup_error", P.SetupStep)):
            if getattr(reply, key) not in kind._value2member_map_:
                raise self.distrust(f"HELLO says {key} {getattr(reply, key)}, not one of {kind.__name__}'s")
        if reply.zero_confirmed not in (0, 1) or reply.wiring_set not in (0, 1):
            raise self.distrust(f"HELLO says zero_confirmed {reply.zero_confirmed}, wiring_set {reply.wiring_set}: "
                                "each is 0 or 1")
        if reply.disabled >> reply.n_hinges:
            raise self.distrust(f"HELLO says hinges {hinge_list(reply.disabled)} are disabled, of {reply.n_hinges}")
        self.info = reply
        self.zero_confirmed = bool(reply.zero_confirmed)
        return reply

    def confirm_zero(self) -> P.Ack:
        """CONFIRM_ZERO: the flaps lie flat now and their counts become zero (the device must be IDLE)."""
        ack = self.request(P.ConfirmZero())
        self.zero_confirmed = True
        return ack

    def get_state(self) -> P.StateMsg:
        """STATE; DeviceUntrusted (the device e-stopped if this session moved it) when the zero this session
        saw confirmed is gone: the device restarted mid-session, and its counts are no longer the flaps'."""
        state = self.request(P.GetState())
        if self.zero_confirmed and not state.zero_confirmed:
            reason = "" if self.info is None else f" (it last started: {P.enum_name(P.ResetReason, self.info.reset_reason)} before this session)"
            raise self.distrust(f"its zero, confirmed in this session, is unconfirmed now: it restarted mid-session"
                                f"{reason}; its counts are not the flaps' angles")
        return state

    def get_gains(self, hinge: int) -> P.Gains:
        return self.request(P.GetGains(hinge)).gains

    def set_gains(self, gains, hinge: int = P.BROADCAST) -> P.Ack:
        """gains: a controllers.pid.PidGains (SI) or protocol.Gains (wire units); ValueError, and nothing
        sent, for a value outside the bounds the firmware takes (docs/protocol.md, Gain bounds)."""
        check_gains({hinge: gains.to_pid() if isinstance(gains, P.Gains) else gains}, "set_gains")
        wire = gains if isinstance(gains, P.Gains) else P.Gains.from_pid(gains)
        ack = self.request(P.SetGains(hinge, wire))
        n = self.info.n_hinges if self.info else MAX_HINGES
        for k in range(n) if hinge == P.BROADCAST else (hinge,):  # read back: a device may ACK and not keep them
            held = self.get_gains(k)
            if not _same_gains(held, wire):
                raise self.distrust(f"it ACKed hinge {k}'s gains {dataclasses.asdict(wire)} and holds "
                                    f"{dataclasses.asdict(held)}")
        return ack

    def set_targets(self, counts) -> P.Ack:
        """ZeroUnconfirmed, and nothing sent, when the device has not had its zero confirmed since it started."""
        if not self.zero_confirmed:
            reason = P.enum_name(P.ResetReason, self.info.reset_reason) if self.info else "unknown"
            raise ZeroUnconfirmed(f"{self.url}: not moved: the device started ({reason}) and its zero is unconfirmed "
                                  f"since: {zero_hint(self.url)}")
        self.moved = True  # from now on an interrupt e-stops (see __exit__)
        return self.request(P.SetTargets(tuple(int(c) for c in counts)))

    def pulse(self, hinge: int, duty: float, duration_s: float) -> P.Ack:
        """Bring-up: hinge's motor open loop at duty ([-PULSE_MAX_DUTY, PULSE_MAX_DUTY]) for duration_s, the
        device IDLE; ValueError, and nothing sent, outside those bounds."""
        if not (abs(duty) <= P.PULSE_MAX_DUTY and 0 < duration_s <= P.PULSE_MAX_MS / 1000):
            raise ValueError(f"a pulse is at most duty {P.PULSE_MAX_DUTY} for {P.PULSE_MAX_MS} ms; "
                             f"asked duty {duty} for {duration_s} s")
        self.moved = True
        self.wait_program()  # the device refuses a pulse while the last still runs (its clock may lag the host's)
        # toward zero on the wire: rounded to nearest, PULSE_MAX_DUTY itself comes back over the firmware's bound
        return self.request(P.Pulse(hinge, int(duty * P.DUTY_SCALE), round(duration_s * 1000)))

    def wait_program(self, timeout_s: float = P.PULSE_MAX_MS / 1000 + 1.0, poll_s: float = 0.01) -> P.ProgramStatus:
        """Wait until the device's last program (or PULSE) has ended; its PROGRAM_STATUS. LinkError once the device's
        own clock (the ticks it reports) shows it running past timeout_s, or once its ticks stop advancing for
        PROGRAM_STILL_S of the host's time: timed by the device, so a host or an emulator that a loaded machine
        leaves waiting for a core is not taken for a device that drives on."""
        dt = self.tick_s
        last, since = -1, time.monotonic()
        while (status := self.request(P.GetProgram())).end == ProgramEnd.RUNNING:
            now = time.monotonic()
            if status.ticks != last:
                last, since = status.ticks, now
            if status.ticks * dt > timeout_s or now - since > PROGRAM_STILL_S:
                raise LinkError(f"{self.url}: the device's program on hinge {status.hinge} still runs after "
                                f"{status.ticks * dt:g} s of its own time (its end at {timeout_s:g} s)")
            time.sleep(poll_s)
        return status

    @property
    def tick_s(self) -> float:
        """s per firmware tick (HELLO's loop rate; 1 kHz before HELLO)."""
        return 1.0 / (self.info.loop_rate_hz if self.info and self.info.loop_rate_hz else 1000)

    def run_program(self, hinge: int, segments, window_counts, timeout_s: float | None = None,
                    poll_s: float = 0.02) -> ProgramRun:
        """Run an open-loop duty program on one hinge (the device IDLE, its zero confirmed) and return its samples.

        segments: (duty, duration_s) pairs, at most PROGRAM_MAX_SEGMENTS, |duty| <= PROGRAM_MAX_DUTY, in all at
        most PROGRAM_MAX_MS; a duty of 0 brakes, COAST coasts. window_counts: (low, high), counts within the hinge's range, the
        hinge inside it now. timeout_s: when the core ends it at the latest (default: the segments' sum). The
        device ends it itself (docs/protocol.md, "PROGRAM"); this waits for that, polling GET_PROGRAM every
        poll_s, and gives one sample per firmware tick (PROGRAM_SAMPLE), those lost on the way counted.
        ValueError, and nothing sent, outside the bounds; NackError where the device refuses."""
        msg = program_message(hinge, segments, window_counts, timeout_s)
        dt = self.tick_s
        self.wait_program()  # a pulse or program still running would refuse it
        with self._pending_lock:
            self._samples = {}
        self.moved = True  # an interrupt from here on e-stops (see __exit__)
        self.request(msg)
        try:
            status = self.wait_program(msg.timeout_ms / 1000 + 1.0, poll_s)
        except LinkError as exc:
            if self.error is None:  # the link stands: the device kept driving past the program's timeout
                self.estop()
                raise LinkError(f"{exc}: e-stopped") from None
            raise
        with self._pending_lock:  # every sample was queued before the status that says the program ended
            samples, self._samples = self._samples, {}
        run = program_run(hinge, samples, status, dt)
        self.log("program_end", hinge=hinge, end=run.end, ticks=status.ticks, received=len(run.time_s),
                 dropped=status.dropped)
        return run

    def get_program(self) -> P.ProgramStatus:
        """How the last program (or PULSE) stands: its hinge, end reason (ProgramEnd), ticks run."""
        return self.request(P.GetProgram())

    def get_wiring(self) -> P.WiringReply:
        return self.request(P.GetWiring())

    def set_wiring(self, encoder, flags, bridge) -> P.Ack:
        """The wiring correction (see protocol.SetWiring), disabled hinges included: kept on the device; a change
        of encoder, bridge or direction leaves its zero to be confirmed again (a hinge disabled or enabled alone
        keeps it: read back)."""
        ack = self.request(P.SetWiring(tuple(int(e) for e in encoder), tuple(int(f) for f in flags),
                                       tuple(int(b) for b in bridge)))
        self.zero_confirmed = False
        self.zero_confirmed = bool(self.get_state().zero_confirmed)
        return ack

    def set_disabled(self, hinges) -> P.WiringReply:
        """Disable exactly `hinges` (braked, never driven; the device IDLE), the rest of its wiring as it holds it;
        the wiring it then holds."""
        w = self.get_wiring()
        off = set(int(h) for h in hinges)
        flags = [(f & ~P.WIRING_DISABLED) | (P.WIRING_DISABLED if k in off else 0) for k, f in enumerate(w.flags)]
        self.set_wiring(w.encoder, flags, w.bridge)
        return self.get_wiring()

    def estop(self) -> P.Ack:
        """ESTOP, resent every ESTOP_RETRY_S (sooner than other requests: a lost one is sent again at once) for as long
        as any request waits (timeout x (retries + 1)), and at least 6 times."""
        tries = max(6, round(self.timeout * (self.retries + 1) / ESTOP_RETRY_S))
        return self.request(P.EStop(), timeout=ESTOP_RETRY_S, retries=tries - 1)

    def clear_fault(self) -> P.Ack:
        return self.request(P.ClearFault())

    def set_telemetry_rate(self, rate_hz: int) -> P.Ack:
        return self.request(P.SetTelemetryRate(int(rate_hz)))

    # ---- telemetry --------------------------------------------------------------------
    def telemetry(self, timeout: float | None = None):
        """The next (seq, Telemetry) in order; None after `timeout` s; LinkError if the link died."""
        try:
            item = self._telemetry.get(timeout=timeout)
        except queue.Empty:
            self._check()
            return None
        if item is _CLOSED:
            self._telemetry.put(_CLOSED)
            raise self.error or self.untrusted or LinkError(f"{self.url}: link closed")
        return item

    def drain_telemetry(self) -> list:
        """Every (seq, Telemetry) queued now, oldest first."""
        out = []
        while True:
            try:
                item = self._telemetry.get_nowait()
            except queue.Empty:
                return out
            if item is _CLOSED:
                self._telemetry.put(_CLOSED)
                return out
            out.append(item)

    # ---- threads ------------------------------------------------------------------------
    def _reader(self) -> None:
        ser = self._serial
        while not self._stop.is_set():
            try:
                data = ser.read(max(1, ser.in_waiting))
            except (serial.SerialException, OSError, TypeError, AttributeError) as exc:
                if not self._stop.is_set():
                    self._fail("port went away while reading", exc)
                return
            if not data:
                continue
            bad = self.decoder.bad_frames
            for seq, msg in self.decoder.feed(data):
                self._dispatch(seq, msg)
            if self.decoder.bad_frames != bad:
                self.log("rx_bad_frames", count=self.decoder.bad_frames, last_error=self.decoder.last_error)

    def _dispatch(self, seq: int, msg) -> None:
        if isinstance(msg, P.ProgramSample):  # a tick of the running program, by its index (the seq)
            with self._pending_lock:
                if len(self._samples) < P.PROGRAM_MAX_MS * MAX_LOOP_RATE_KHZ:
                    self._samples[seq] = msg
            return
        if self.untrusted is None:
            why = self._implausible(seq, msg)
            if why:
                self.log("rx_untrusted", msg=msg.MSG.name, seq=seq, **_fields(msg))
                self.distrust(why)  # requests waiting now raise it; an ESTOP's still takes its answer
                if isinstance(msg, P.Telemetry):
                    return
        if isinstance(msg, P.Telemetry):
            if self._last_telemetry_seq is not None:
                self.telemetry_lost += (seq - self._last_telemetry_seq - 1) & 0xFFFF
            self._last_telemetry_seq = seq
            self.telemetry_received += 1
            if self.log_telemetry:
                self.log("telemetry", seq=seq, **_fields(msg))
            if self.telemetry_callback:
                self.telemetry_callback(seq, msg)
                return
            while self._telemetry.qsize() >= TELEMETRY_KEPT:  # nobody reads them (status --watch after mirror)
                try:
                    if self._telemetry.get_nowait() is _CLOSED:
                        self._telemetry.put(_CLOSED)
                        break
                    self.telemetry_unread += 1
                except queue.Empty:
                    break
            self._telemetry.put((seq, msg))
            return
        self.log("rx", msg=msg.MSG.name, seq=seq, **_fields(msg))
        with self._pending_lock:
            slot = self._pending.get(seq)
        if slot is None or slot[0].is_set():
            return
        if not P.answers(slot[2], msg):  # right number, wrong message: not taken as the answer
            self.echoes += msg.MSG == slot[2]
            self.log("rx_unmatched", msg=msg.MSG.name, seq=seq, awaiting=slot[2].name)
            return
        slot[1] = msg
        slot[0].set()

    def _implausible(self, seq: int, msg) -> str | None:
        """Why `msg` cannot be what the device means (None: it can): a state, fault bit, blamed hinge or hinge
        count out of range; a clock that went back, stopped or ran ahead of the host's."""
        n = self.info.n_hinges if self.info else self.hinges
        name = msg.MSG.name
        if isinstance(msg, (P.StateMsg, P.Telemetry)):
            if msg.state not in P.State._value2member_map_:
                return f"{name} says state {msg.state}, not one of {[s.name for s in P.State]}"
            if msg.faults & ~sum(P.Fault):
                return f"{name} says fault bits 0x{msg.faults:04X}, of which 0x{msg.faults & ~sum(P.Fault):04X} no fault"
            if n is not None and len(msg.counts) != n:
                return f"{name} has {len(msg.counts)} hinges, the device {n}"
            hinges = len(msg.counts) if n is None else n  # before HELLO says how many, the frame's own count: a
            # session's first frames may be an e-stopped device's telemetry still blaming the hinge it stopped on
            if msg.fault_hinge != 0xFF and msg.fault_hinge >= hinges:
                return f"{name} blames hinge {msg.fault_hinge}, of {hinges}"
        if isinstance(msg, P.StateMsg) and n is not None and msg.disabled >> n:
            return f"STATE says hinges {hinge_list(msg.disabled)} are disabled, of {n}"
        if isinstance(msg, P.GainsReply) and n is not None and msg.hinge >= n:
            return f"GAINS for hinge {msg.hinge}, of {n}"
        stamp = getattr(msg, "time_us", None)
        return None if stamp is None else self._clock_wrong(name, stamp, isinstance(msg, P.Telemetry), seq)

    def _clock_wrong(self, name: str, stamp: int, telemetry: bool, seq: int) -> str | None:
        """Why a device time stamp (us, u32 wrapping) cannot follow the ones before it (None: it can).

        Host time minus device time at any stamp's generation is one constant C (the clocks' offset); received
        later, a stamp's host time minus its device time is C or more. A reply to a request was generated after
        the request was sent, so C >= sent - its stamp: the largest such bound so far (`floor`) is one no stamp
        may fall below by more than CLOCK_AHEAD_S (plus CLOCK_DRIFT of the session). Only replies set it: a
        stale backlog of telemetry at a session's start says nothing of C."""
        now = time.monotonic()
        reply_sent = None
        if not telemetry:
            with self._pending_lock:
                slot = self._pending.get(seq)
            reply_sent = None if slot is None else slot[3]
        if self._clock is None:
            self._clock = (stamp, now, -math.inf, now)
        last_us, last_host, floor, first_host = self._clock
        step = ((stamp - last_us + 2**31) & 0xFFFFFFFF) - 2**31  # us since the last stamp, signed
        if step < -CLOCK_BACK_US or (telemetry and stamp == self._last_telemetry_us):
            what = "went back" if step < 0 else "stopped"
            return (f"its clock {what}: {name} stamped {stamp} us after {last_us & 0xFFFFFFFF} us (a restart, or a "
                    "clock the host cannot compare the device with the twin by)")
        if telemetry:
            self._last_telemetry_us = stamp
        if step <= 0 and reply_sent is not None and reply_sent - last_host > CLOCK_STUCK_S:
            return (f"its clock stopped: {name} stamped {stamp} us, as the stamp the host had "
                    f"{reply_sent - last_host:.2f} s before asking")
        unwrapped = last_us + max(step, 0)
        ahead = floor - (now - unwrapped / 1e6)
        if ahead > CLOCK_AHEAD_S + CLOCK_DRIFT * (now - first_host):
            return (f"its clock ran ahead: {name} stamped {ahead:.3f} s later than the host's clock allows "
                    f"(the device's clock has run {ahead:.3f} s more than the host's since an earlier reply)")
        if reply_sent is not None:
            floor = max(floor, reply_sent - unwrapped / 1e6)
        self._clock = (unwrapped, now if step > 0 else last_host, floor, first_host)
        return None

    def _heartbeat(self) -> None:
        interval = self.heartbeat_interval
        while not self._stop.wait(interval / 2) and not self._heartbeat_off.is_set():
            if time.monotonic() - self._last_sent >= interval:
                try:
                    self.send(P.Heartbeat())
                except LinkError:
                    return

    def stop_heartbeat(self) -> None:
        """Stop feeding the device's watchdog (to test it); commands still feed it."""
        self._heartbeat_off.set()
        self.log("heartbeat_stopped")


def _same_gains(a: P.Gains, b: P.Gains) -> bool:
    """Equal within the device's float32 (its wire units back and forth: within a unit, or 1e-6 of a large
    value)."""
    return all(abs(x - y) <= 1 + abs(y) * 1e-6 for x, y in zip(dataclasses.astuple(a), dataclasses.astuple(b)))


def _fields(msg) -> dict:
    return {f.name: _jsonable(getattr(msg, f.name)) for f in dataclasses.fields(msg)}


def _jsonable(v):
    if dataclasses.is_dataclass(v):
        return dataclasses.asdict(v)
    if isinstance(v, tuple):
        return list(v)
    if hasattr(v, "item"):
        return v.item()
    return v
