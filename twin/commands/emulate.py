"""`vrscroll emulate`: a device emulator on a pseudo-terminal (see twin/link/emulator.py)."""

from twin.link.emulator import add_arguments, run  # noqa: F401
