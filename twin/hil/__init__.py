"""Hardware in the loop: mirroring a target onto the device behind the gate, scenario runs on the
device and the twin side by side, and calibration of the twin to recorded runs.

May import `twin.device`, `twin.formats`, `controllers`, `twin.sim` and `twin.link`; never the
approximation.
"""
