"""What runs on the device: the firmware's motor control (PID) and encoder maths.

Imports `twin.device` (the spec) only; the simulation, the emulator and the tuner import it.
"""
