"""When the device is at rest: the one rule for waiting until it rests and for trusting the start a gate
simulated from (twin.hil.mirror).

Both are judged between two of the device's STATEs, over the device time that passed between them: at rest
while no hinge moves faster than REST_COUNTS per REST_TIME; and a gate's start still the device's while,
besides, no hinge drifted farther than the settle band while the twin simulated. A device hanging from its
root flap has its flaps beside the root sag under gravity while nothing drives them, and creep at 10-40
counts/s for one to several seconds after the sag (docs/protocol.md, "Session, as the host runs it"): at rest
by the rate, while a host that takes a second to simulate sees it drift tens of counts.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from twin.device.spec import DeviceSpec
from twin.link import protocol as P

REST_COUNTS = 2  # the device is at rest while no hinge moves faster than this many counts ...
REST_TIME = 0.05  # ... per this many s of device time (40 counts/s); over a shorter time, REST_COUNTS at most


@dataclasses.dataclass(frozen=True)
class Motion:
    """How the device moved from one STATE to a later one."""

    seconds: float  # device time between them
    rate: float  # counts/s, the fastest hinge's, over max(seconds, REST_TIME)
    drift: int  # counts, the farthest any hinge moved
    hinge: int  # the hinge that moved farthest

    @property
    def at_rest(self) -> bool:
        """No hinge moved faster than REST_COUNTS per REST_TIME."""
        return self.rate * REST_TIME <= REST_COUNTS

    def kept_start(self, spec: DeviceSpec) -> bool:
        """At rest, and no hinge drifted farther than the settle band (spec.settle_band counts): the firmware and
        the twin call a hinge within the band of a position there, so a gate that simulated from the earlier
        STATE simulated from the device's start."""
        return self.at_rest and self.drift <= spec.settle_band

    def text(self, spec: DeviceSpec) -> str:
        """The rate and the drift in counts and degrees, naming the hinge and the time."""
        deg = math.degrees(spec.rad_per_count)
        return (f"hinge {self.hinge} drifted {self.drift} counts ({self.drift * deg:.1f} deg) in {self.seconds:.2f} s, "
                f"fastest {self.rate:.0f} counts/s ({self.rate * deg:.1f} deg/s)")


def motion(before: P.StateMsg, after: P.StateMsg) -> Motion:
    """How the device moved from `before` to `after` (its STATEs), on the device's clock."""
    seconds = P.elapsed_s(before.time_us, after.time_us)
    moved = np.abs(np.asarray(after.counts) - np.asarray(before.counts))
    hinge = int(np.argmax(moved))
    return Motion(seconds, float(moved.max()) / max(seconds, REST_TIME), int(moved[hinge]), hinge)
