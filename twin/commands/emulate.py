"""`vrscroll emulate`: a device emulator on a pseudo-terminal (see twin/emulator.py)."""

from twin.emulator import add_arguments, run  # noqa: F401
