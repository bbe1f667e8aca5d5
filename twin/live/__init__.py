"""The live service for VR applications: the MorphPatch loop behind a network service.

A control channel (WebSocket, JSON: session, target, lock, events) and datagram streams
(UDP: device pose and pen binary, newest sample wins); a worker process that approximates;
a lock that goes approximate -> gate -> mirror (onto the device over the serial link, or the
twin alone); a Python client and a session player. The protocol is in docs/live.md.

The top of the stack beside `twin.commands`: may import `twin.device`, `controllers`,
`twin.perception`, `twin.morphpatch`, `twin.sim`, `twin.link`, `twin.hil` and
`twin.evaluation`; nothing imports it but `twin.commands`, the tests and the benchmarks.
"""
