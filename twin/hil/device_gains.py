"""What the device itself says it runs: the device opened with its configuration from HELLO over the profile's
spec (`device_session`; a link failure as one line, `link_errors`), and its PID gains (reading them, and pushing a
new set so that it is all or nothing).

Every hinge's gains are checked against the bounds the firmware takes before any is sent; if the
device refuses one anyway, the hinges already changed get their previous gains back.
"""

from __future__ import annotations

import contextlib
import math

from controllers.pid import PidGains
from twin.device.spec import DeviceSpec
from twin.errors import UserError
from twin.formats.gains import check_gains
from twin.link.protocol import HelloReply
from twin.link.serial_link import Link, LinkError

# HELLO_REPLY field -> (spec field, to SI, what it is): the device's word wins over the profile's spec
_HELLO = {"loop_rate_hz": ("loop_rate", 1.0, "loop rate", "Hz"), "watchdog_ms": ("watchdog", 1e-3, "watchdog", "ms"),
          "max_telemetry_hz": ("max_telemetry_rate", 1.0, "telemetry rate limit", "Hz")}


def device_spec(spec: DeviceSpec, info: HelloReply) -> tuple[DeviceSpec, list[str]]:
    """The spec with the device's own configuration (HELLO_REPLY: loop rate, watchdog, telemetry limit) where
    they disagree, and one plain line per difference: the twin then predicts the device as it is."""
    changes, notes = {}, []
    for key, (field, si, what, unit) in _HELLO.items():
        theirs, ours = getattr(info, key), getattr(spec, field)
        if not math.isclose(theirs * si, ours, rel_tol=1e-6):
            changes[field] = theirs * si
            notes.append(f"the device's {what} is {theirs:g} {unit}, the profile's spec says {ours / si:g} {unit}: "
                         "the device's is used")
    return (spec.replace(**changes) if changes else spec), notes


@contextlib.contextmanager
def device_session(port: str, spec: DeviceSpec, log=None, say=print):
    """(link, spec): the device on `port`, opened (closed, e-stopped on an interrupt, when the block ends; `log`
    the session log, JSON lines), and the spec with the device's own configuration from its HELLO (device_spec),
    each difference said through `say` as a "note: ..." line."""
    with Link(port, log_path=log, hinges=spec.n_hinges) as link:
        spec, notes = device_spec(spec, link.info)
        for note in notes:
            say(f"note: {note}")
        yield link, spec


@contextlib.contextmanager
def link_errors(note: str = ""):
    """A LinkError in the block (the device's port, its replies, a refusal) as one line, UserError
    "link: ..." + note (e.g. where the session log is)."""
    try:
        yield
    except LinkError as exc:
        raise UserError(f"link: {exc}{note}") from None


def device_gains(link: Link, n: int) -> list[PidGains]:
    """The device's PID gains, one PidGains per hinge, as the device holds them."""
    return [link.get_gains(k).to_pid() for k in range(n)]


def restore_gains(link: Link, previous: list[PidGains]) -> None:
    """Send each hinge its gains from `previous` (what `push_gains` returned)."""
    for k, g in enumerate(previous):
        link.set_gains(g, hinge=k)


def push_gains(link: Link, gains: list[PidGains], n: int, where: str = "gains") -> list[PidGains]:
    """Send one PidGains per hinge of the device's n, all checked first; returns the gains the device held before.

    ValueError (nothing sent) for the wrong hinge count or a value outside the firmware's bounds;
    NackError if the device refuses a hinge's gains, after restoring the hinges already changed; likewise an
    interrupt (Ctrl-C, SIGTERM) or a link failure half-way restores them before it goes on up.
    """
    if len(gains) != n:
        raise ValueError(f"{where}: gains for {len(gains)} hinges, the device has {n}")
    check_gains(gains, where)
    previous = device_gains(link, n)
    for k, g in enumerate(gains):
        try:
            link.set_gains(g, hinge=k)
        except (LinkError, KeyboardInterrupt):  # a NACK is a LinkError too
            try:
                restore_gains(link, previous[:k + 1])  # hinge k too: its SET_GAINS may have landed unanswered
            except LinkError:
                link.log("restore_gains_failed", hinges=k + 1)
            raise
    return previous
