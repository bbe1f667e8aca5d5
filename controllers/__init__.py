"""Firmware-equivalent motor control: the PID that runs on the device, encoder maths, tuning."""
