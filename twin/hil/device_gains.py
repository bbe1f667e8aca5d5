"""The device's PID gains: reading them, and pushing a new set so that it is all or nothing.

Every hinge's gains are checked against the bounds the firmware takes before any is sent; if the
device refuses one anyway, the hinges already changed get their previous gains back.
"""

from __future__ import annotations

from controllers.pid import PidGains
from twin.formats.gains import check_gains
from twin.link.serial_link import Link, NackError


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
    NackError if the device refuses a hinge's gains, after restoring the hinges already changed.
    """
    if len(gains) != n:
        raise ValueError(f"{where}: gains for {len(gains)} hinges, the device has {n}")
    check_gains(gains, where)
    previous = device_gains(link, n)
    for k, g in enumerate(gains):
        try:
            link.set_gains(g, hinge=k)
        except NackError:
            restore_gains(link, previous[:k])
            raise
    return previous
