"""The serial link to a device: the wire protocol (framing, checksum, messages), the host end of
the link (requests, acknowledgements, heartbeat, telemetry, session log), and the emulator that
stands in for a device on a pseudo-terminal.

May import `twin.sim` (the emulator drives its own plant) and the layers below it (README
"Layout"); never the approximation or the HIL runs.
"""
