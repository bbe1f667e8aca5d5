"""An emulated device served on a real pseudo-terminal, paced to real time.

`open_pty()` gives a raw pty pair; `serve(emulator, fd, should_stop)` ticks the
device at the firmware rate against the wall clock, moving bytes between the pty
master and the device, until should_stop() is true. Connect to the slave end's
path as to /dev/ttyACM0.
"""

from __future__ import annotations

import contextlib
import errno
import os
import select
import threading
import time
import tty

from twin.link.emulator import Emulator

UART_BUFFER = 8192  # bytes the device can have on their way to the host; it sends no more until they drain
# An emulator served here shares the host's CPU: a Link to its pty waits as serial_link.PTY_RETRIES says.


def open_pty() -> tuple[int, int, str]:
    """(master fd, slave fd, slave path) of a new raw pseudo-terminal."""
    master, slave = os.openpty()
    tty.setraw(slave)
    return master, slave, os.ttyname(slave)


def serve(emu: Emulator, fd: int, should_stop) -> int:
    """Tick emu at its firmware rate in real time on fd until should_stop(); returns the overruns.

    An overrun is falling more than 50 ticks behind the wall clock: the pacing
    then restarts from now rather than trying to catch up.
    """
    os.set_blocking(fd, False)
    out = bytearray()
    overruns = 0
    start = time.monotonic()
    first = emu.tick
    while not should_stop():
        _read(emu, fd)
        emu.step()
        out += emu.take_output(UART_BUFFER - len(out))
        _write(fd, out)
        next_at = start + (emu.tick - first) * emu.dt
        wait = next_at - time.monotonic()
        if wait > 0:
            r, _, _ = select.select([fd], [], [], wait)
            if r:
                _read(emu, fd)
                wait = next_at - time.monotonic()
                if wait > 0:
                    time.sleep(wait)
        elif wait < -0.05:
            overruns += 1
            start, first = time.monotonic(), emu.tick
    return overruns


def _read(emu: Emulator, fd: int) -> None:
    try:
        data = os.read(fd, 65536)
    except BlockingIOError:
        return
    except OSError as exc:
        if exc.errno in (errno.EIO, errno.EAGAIN):
            return
        raise
    if data:
        emu.receive(data)


def _write(fd: int, out: bytearray) -> None:
    while out:
        try:
            sent = os.write(fd, out)
        except (BlockingIOError, InterruptedError):
            break
        except OSError as exc:
            if exc.errno in (errno.EIO, errno.EAGAIN):
                out.clear()
                return
            raise
        del out[:sent]


@contextlib.contextmanager
def served(emu: Emulator):
    """An in-process emulator on a real pty, paced in real time by a thread; yields the port's path."""
    master, slave, path = open_pty()
    stop = threading.Event()
    thread = threading.Thread(target=serve, args=(emu, master, stop.is_set), daemon=True)
    thread.start()
    try:
        yield path
    finally:
        stop.set()
        thread.join(5)
        os.close(master)
        os.close(slave)
