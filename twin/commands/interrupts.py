"""The signals that end a command as Ctrl-C does, so that a session with the device e-stops it on the way out.

SIGINT (Ctrl-C), SIGTERM (kill, a service manager), SIGHUP (the terminal closed: a window shut, an ssh session
dropped) and SIGQUIT (Ctrl-\\) all raise KeyboardInterrupt in the main thread: twin.link.serial_link.Link's
`__exit__` then e-stops a device its session moved before the port closes. Without this, SIGHUP and SIGQUIT
killed the host at once and left the device driving toward its targets, then holding them for the watchdog's
10 s (issue 40). Only the first signal interrupts: a second one (Ctrl-C pressed twice, a SIGTERM after the
terminal's SIGHUP) is ignored, so it cannot cut the e-stop short; the e-stop is bounded (a few 50 ms tries),
and SIGKILL still ends everything.
"""

from __future__ import annotations

import signal

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP, signal.SIGQUIT)

_stopping = []  # the signal that started the stop, once one has


def _interrupt(signum, frame):
    if _stopping:
        return  # already on the way out: let the e-stop finish
    _stopping.append(signum)
    raise KeyboardInterrupt


def interrupt_on_stop_signals() -> None:
    """Make every signal of STOP_SIGNALS raise KeyboardInterrupt (once); one this process was started with
    ignored (SIGINT in a background job, SIGHUP under nohup) stays ignored."""
    for sig in STOP_SIGNALS:
        if signal.getsignal(sig) is not signal.SIG_IGN:
            signal.signal(sig, _interrupt)


def stop_signals_call(loop, stop) -> None:
    """In an asyncio service (serve): every signal of STOP_SIGNALS calls stop() on `loop`, which ends the
    service the way its own shutdown does (its device e-stopped where it moved it)."""
    for sig in STOP_SIGNALS:
        if signal.getsignal(sig) is not signal.SIG_IGN:
            loop.add_signal_handler(sig, stop)

