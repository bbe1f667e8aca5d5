"""Python's garbage collection in the approximation worker: between requests, not inside one.

CPython runs its cycle collector whenever 700 more container objects were made than freed,
wherever that happens: inside an approximation, too. Measured with gc.callbacks in the service and
its worker during bench_live (load ~4 on 2 cores): the youngest generation 0.1-0.2 ms each (up to
10 ms), the middle one ~1.6 ms, a full one 60-250 ms over the objects the imports left. While
samples stream they are rare (the service made 5 in the last 6 s of a run, 360 pens and 90 poses a
second), so what this saves is the tail: the sample that met one. The worker (and the benchmark's
measuring client) instead

- freeze what start-up made (`gc.freeze`: the imports' objects are never scanned again; those
  still alive at exit are not collected, which they never would have been), then
- turn the automatic collector off, and
- call `collect_if_due` once a reply has gone: the same thresholds (`gc.get_threshold`), the
  same generations, only at a moment of the caller's choosing.

A process that calls `hold_collection` must call `collect_if_due` often (after each request it
answers): nothing else collects its cycles. The service's event loop keeps CPython's own collector:
its garbage comes from the control channel and the morph thread too, so holding it would need a
timer to collect when no datagram comes (a wake-up 50 times a second), and with one no gain was
measurable (docs/live.md, "Measured").
"""

from __future__ import annotations

import gc


def hold_collection() -> None:
    """Freeze every object made so far and stop the automatic collector (see the module's docstring)."""
    gc.collect()
    gc.freeze()
    gc.disable()


def collect_if_due() -> int:
    """Collect the generation CPython's own thresholds say is due now, if any; its number, or -1 if none."""
    counts, thresholds = gc.get_count(), gc.get_threshold()
    if counts[0] < thresholds[0]:
        return -1
    generation = 0
    while generation < 2 and counts[generation + 1] >= thresholds[generation + 1]:
        generation += 1
    gc.collect(generation)
    return generation


def release_collection() -> None:
    """Undo `hold_collection`: the automatic collector on again, the frozen objects collectable."""
    gc.unfreeze()
    gc.enable()
