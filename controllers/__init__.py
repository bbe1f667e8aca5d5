"""What runs on the device: the firmware's motor control (PID) and encoder maths.

Imports `twin.device` (the spec) and the base modules only; the simulation, the emulator, the file
formats and the tuner import it.
"""
