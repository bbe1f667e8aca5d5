"""A pen sample's redirection in the service, on state allocated once: the datagram's buffer, the sample's values,
the redirection's inputs and outputs, the reply's bytes.

Per sample, three compiled calls and no JSON: the check (`SampleBuffer.check`), the redirection's kernel
(`twin.morphpatch.redirection`'s, the one `redirect` runs, called here on the preallocated arrays) and the reply's
encoding with the thresholds' verdict (`encode_pen_reply`). `redirect` itself, for one sample, allocated its
outputs and a Redirected, and the JSON on either side of it was most of a pen's time in the service
(docs/live.md, "Measured"). A pen that carries the tracked device's pose has its correction (the approximation's
root pose times the inverse of the device's) computed in numpy, as `redirect` does: that variant allocates.
"""

from __future__ import annotations

import numpy as np

from twin.device.kinematics import pose_matrix, quat_matrix
from twin.live.messages import PEN_REPLY, SampleBuffer, encode_pen_reply
from twin.morphpatch.redirection import RedirectionField, redirect_kernel
from twin.perception.thresholds import Thresholds


class PenRedirection:
    """The service's pens: `buffer` receives a datagram; once checked, `redirect()` writes the reply to `reply`."""

    def __init__(self, thresholds: Thresholds):
        self.thresholds = thresholds
        self.buffer = SampleBuffer()
        values = self.buffer.values
        self._position, self._quat = values[2:5].reshape(1, 3), values[5:9].reshape(1, 4)  # views: SI, unit
        self._out_p, self._out_q, self._info = np.zeros((1, 3)), np.zeros((1, 4)), np.zeros((1, 6))
        self._carry, self._no_carry = np.zeros((1, 4, 4)), np.zeros((0, 4, 4))
        self._words = np.zeros(PEN_REPLY.size // 8)
        self._raw, self._longs = self._words.view(np.uint8), self._words.view(np.uint64)
        self.reply = memoryview(self._raw)  # the reply datagram, PEN_REPLY.size bytes
        self._field = None  # the kernel's arguments from the field
        self._root = None

    def set_field(self, field: RedirectionField | None) -> None:
        """The field pens are redirected with from now on (None: none); the compiled code loaded now, not on a pen."""
        if field is None:
            self._field = self._root = None
            return
        self._root = field.root_pose
        self._field = (np.ascontiguousarray(field.frames[:, :3, :3]), np.ascontiguousarray(field.frames[:, :3, 3]),
                       field.s_edges, field.s0, field.ds, field.y0, field.dy, field.offset, field.rotation)
        self.buffer.values[:] = 0.0
        self.buffer.values[5] = 1.0
        self.redirect()

    def redirect(self) -> bool:
        """The checked pen sample in `buffer` redirected, its reply in `reply`; whether within both thresholds."""
        values = self.buffer.values
        carry = self._no_carry
        if values[17]:  # the pen relative to the tracked device, put where the approximation has the device
            carry = self._carry
            carry[:] = self._root @ np.linalg.inv(pose_matrix(values[9:12], quat_matrix(values[12:16]))[None])
        redirect_kernel(*self._field, self._position, self._quat, carry, self._out_p, self._out_q, self._info)
        return encode_pen_reply(values, self._out_p, self._out_q, self._info, self.thresholds.position,
                                self.thresholds.rotation, self._raw, self._words, self._longs)
