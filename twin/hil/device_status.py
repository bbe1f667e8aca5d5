"""The device's state as `vrscroll status` reports it: its HELLO and STATE in words, the changes the command
asks first (e-stop, clear a fault, disable or enable hinges), and a live readout of the hinge angles."""

from __future__ import annotations

import time

import numpy as np

from controllers.encoder import angle_from_counts
from twin.errors import UserError
from twin.hil.mirror import faults_text
from twin.link import protocol as P
from twin.link.serial_link import hinge_list, zero_hint
from twin.records.profile import Profile


def device_status(link, spec, profile: Profile, estop: bool = False, clear_fault: bool = False, disable=(),
                  enable=()) -> list[str]:
    """E-stop, clear a fault, disable and enable hinges (numbers as given on the command line) as asked, then
    the device's state in words (status_lines). UserError for a hinge the device does not have."""
    if estop:
        link.estop()
    if clear_fault:
        link.clear_fault()
    if disable or enable:
        off = set(hinge_list(link.get_state().disabled))
        off = (off | _hinges(disable, spec)) - _hinges(enable, spec)
        link.set_disabled(sorted(off))
    s = link.get_state()
    held = [link.get_gains(k) for k in range(spec.n_hinges)]  # as the wire carries them
    return status_lines(spec, profile, s, link.info, held, link.url)


def _hinges(items, spec) -> set[int]:
    """Hinge numbers from --disable-hinges / --enable-hinges; UserError naming one the device does not have."""
    out = set()
    for text in items or ():
        if not text.isdigit() or int(text) >= spec.n_hinges:
            raise UserError(f"hinge {text!r}: the device's hinges are 0 to {spec.n_hinges - 1}")
        out.add(int(text))
    return out


WATCH_PERIOD_S = 0.2


def watch(link, spec, seconds: float, say=print) -> None:
    """say(line) with the hinge angles (deg) and the state every WATCH_PERIOD_S, for seconds (0: until Ctrl-C)."""
    start = time.monotonic()
    try:
        while not seconds or time.monotonic() - start < seconds:
            s = link.get_state()
            deg = np.degrees(angle_from_counts(spec, s.counts))
            say(f"t={time.monotonic() - start:6.1f} s " + " ".join(f"{a:7.1f}" for a in deg)
                + f"  deg  {P.enum_name(P.State, s.state)}")
            time.sleep(WATCH_PERIOD_S)
    except KeyboardInterrupt:  # the way a watch ends: nothing was moved
        say("")


def status_lines(spec, profile: Profile, s, info, held, port: str) -> list[str]:
    """The device's state (s, info: its STATE and HELLO; held: the gains it holds, as the wire carries them) in
    words: firmware, how it started, zero, disabled and derated hinges, state, faults, angles (deg), counts,
    integrals, and whether its gains are the profile's."""
    deg = np.degrees(angle_from_counts(spec, s.counts))
    tgt = np.degrees(angle_from_counts(spec, s.targets))
    lines = []
    say = lines.append
    say(f"firmware {'.'.join(map(str, s.firmware))}, protocol {info.protocol}, {info.n_hinges} hinges, "
        f"loop {info.loop_rate_hz} Hz, watchdog {info.watchdog_ms} ms")
    say(f"started  {P.enum_name(P.ResetReason, info.reset_reason)}"
        + ("" if info.setup_error == P.SetupStep.NONE else
           f"; set-up failed at {P.enum_name(P.SetupStep, info.setup_error)} (docs/firmware.md, 'Set-up faults')"))
    say(f"zero     {'confirmed' if s.zero_confirmed else 'UNCONFIRMED: ' + zero_hint(port)}")
    if s.disabled:
        say(f"disabled hinges {hinge_list(s.disabled)}: braked, never driven, their targets and pulses refused "
            "(bring-up found a dead wire, or you disabled them); `--enable-hinges` once mended, or run bring-up "
            "again")
    if s.derated:
        say(f"derated  hinges {hinge_list(s.derated)}: held to the motor's "
            "continuous current by the I2t protection")
    say(f"state    {P.enum_name(P.State, s.state)}")
    say(f"faults   {faults_text(s.faults)}" + (f" (hinge {s.fault_hinge})" if s.fault_hinge != 0xFF else ""))
    say("angles   " + " ".join(f"{a:7.1f}" for a in deg) + "  deg")
    say("targets  " + " ".join(f"{a:7.1f}" for a in tgt) + "  deg")
    say("counts   " + " ".join(f"{c:7d}" for c in s.counts))
    say("integral " + " ".join(f"{x * 100:7.1f}" for x in s.integral_duty)
        + "  % duty (what each PID holds its load with)")
    other = [k for k, (a, b) in enumerate(zip(held, profile.gains)) if a != P.Gains.from_pid(b)]
    say(f"gains    {'as' if not other else 'NOT as'} {profile.label}'s ({profile.gains_from})"
        + (f" on hinges {other}" if other else ""))
    say(f"device time {s.time_us / 1e6:.3f} s, bad frames received {s.rx_bad_frames}")
    return lines
