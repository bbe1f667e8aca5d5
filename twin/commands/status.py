"""`vrscroll status --serial PORT`: the device's firmware version, state, faults and hinge angles."""

from __future__ import annotations

import time

import numpy as np

from controllers.encoder import angle_from_counts
from twin.commands.options import (
    add_device_option,
    add_serial,
    comma_list,
    device_session,
    link_errors,
    opened,
    profile_line,
    within,
)
from twin.errors import UserError
from twin.hil.mirror import faults_text
from twin.link import protocol as P
from twin.link.serial_link import hinge_list, zero_hint


def add_arguments(p) -> None:
    add_serial(p, required=True)
    p.add_argument("--clear-fault", action="store_true", help="clear an ESTOP or FAULT first")
    p.add_argument("--estop", action="store_true", help="e-stop the device first")
    p.add_argument("--disable-hinges", type=comma_list(), metavar="K1,K2,...",
                   help="disable these hinges on the device (kept with its wiring, across power cycles and "
                        "CLEAR_FAULT): braked, never driven, their targets and pulses refused; the device IDLE "
                        "(with --clear-fault from a fault)")
    p.add_argument("--enable-hinges", type=comma_list(), metavar="K1,K2,...",
                   help="enable these hinges again (once the dead wire is mended; bring-up does it for a hinge it "
                        "finds healthy)")
    p.add_argument("--log", help="session log, JSON lines")
    p.add_argument("--watch", type=within(0, 86400, "s"), nargs="?", const=0.0, metavar="SECONDS",
                   help="then a live readout of the hinge angles, 5 lines a second, for SECONDS (none or 0: until "
                        "Ctrl-C): for the bring-up steps where you bend a flap by hand")
    add_device_option(p)


def run(args) -> int:
    profile, spec = opened(args, say=False)  # said with what the device says
    with link_errors(), device_session(args, spec) as (link, spec):
        if args.estop:
            link.estop()
        if args.clear_fault:
            link.clear_fault()
        if args.disable_hinges or args.enable_hinges:
            off = set(hinge_list(link.get_state().disabled))
            off = (off | _hinges(args.disable_hinges, spec)) - _hinges(args.enable_hinges, spec)
            link.set_disabled(sorted(off))
        s = link.get_state()
        info = link.info
        held = [link.get_gains(k) for k in range(spec.n_hinges)]  # as the wire carries them
        _report(spec, profile, s, info, held, args.serial)
        if args.watch is not None:
            watch(link, spec, args.watch)
    return 0


def _hinges(items, spec) -> set[int]:
    """Hinge numbers from --disable-hinges / --enable-hinges; UserError naming one the device does not have."""
    out = set()
    for text in items or ():
        if not text.isdigit() or int(text) >= spec.n_hinges:
            raise UserError(f"hinge {text!r}: the device's hinges are 0 to {spec.n_hinges - 1}")
        out.add(int(text))
    return out


WATCH_PERIOD_S = 0.2


def watch(link, spec, seconds: float) -> None:
    """One line of hinge angles (deg) and the state every WATCH_PERIOD_S, for seconds (0: until Ctrl-C)."""
    start = time.monotonic()
    try:
        while not seconds or time.monotonic() - start < seconds:
            s = link.get_state()
            deg = np.degrees(angle_from_counts(spec, s.counts))
            print(f"t={time.monotonic() - start:6.1f} s " + " ".join(f"{a:7.1f}" for a in deg)
                  + f"  deg  {P.enum_name(P.State, s.state)}", flush=True)
            time.sleep(WATCH_PERIOD_S)
    except KeyboardInterrupt:  # the way a watch ends: nothing was moved
        print()


def _report(spec, profile, s, info, held, port) -> None:
    deg = np.degrees(angle_from_counts(spec, s.counts))
    tgt = np.degrees(angle_from_counts(spec, s.targets))
    print(profile_line(profile))
    print(f"firmware {'.'.join(map(str, s.firmware))}, protocol {info.protocol}, {info.n_hinges} hinges, "
          f"loop {info.loop_rate_hz} Hz, watchdog {info.watchdog_ms} ms")
    print(f"started  {P.enum_name(P.ResetReason, info.reset_reason)}"
          + ("" if info.setup_error == P.SetupStep.NONE else
             f"; set-up failed at {P.enum_name(P.SetupStep, info.setup_error)} (docs/firmware.md, 'Set-up faults')"))
    print(f"zero     {'confirmed' if s.zero_confirmed else 'UNCONFIRMED: ' + zero_hint(port)}")
    if s.disabled:
        print(f"disabled hinges {hinge_list(s.disabled)}: braked, never driven, their targets and pulses refused "
              "(bring-up found a dead wire, or you disabled them); `--enable-hinges` once mended, or run bring-up "
              "again")
    if s.derated:
        print(f"derated  hinges {hinge_list(s.derated)}: held to the motor's "
              "continuous current by the I2t protection")
    print(f"state    {P.enum_name(P.State, s.state)}")
    print(f"faults   {faults_text(s.faults)}" + (f" (hinge {s.fault_hinge})" if s.fault_hinge != 0xFF else ""))
    print("angles   " + " ".join(f"{a:7.1f}" for a in deg) + "  deg")
    print("targets  " + " ".join(f"{a:7.1f}" for a in tgt) + "  deg")
    print("counts   " + " ".join(f"{c:7d}" for c in s.counts))
    print("integral " + " ".join(f"{x * 100:7.1f}" for x in s.integral_duty)
          + "  % duty (what each PID holds its load with)")
    other = [k for k, (a, b) in enumerate(zip(held, profile.gains)) if a != P.Gains.from_pid(b)]
    print(f"gains    {'as' if not other else 'NOT as'} {profile.label}'s ({profile.gains_from})"
          + (f" on hinges {other}" if other else ""))
    print(f"device time {s.time_us / 1e6:.3f} s, bad frames received {s.rx_bad_frames}", flush=True)
