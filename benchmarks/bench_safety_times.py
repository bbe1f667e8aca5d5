"""The sketch's two safety times on the host's stand-ins (issue 38), each beside the board without its remedy:

- hang: how long a motor stays driven after loop() hangs mid-move (every hinge moving, the hang at 60 ms),
  with the timer interrupt's brake (LOOP_LATE_TICKS) and with it taken out (only the 5 s task watchdog left);
- reset: per hinge, the time its bridge is not braking (coasting or driven) from a reset to the end of set-up,
  with the board's pull-ups on the DRV8833 inputs and without them;
- blind: a hinge with a dead wire (the emulator's encoder-dead, channel-dead, input-open) given a +10 deg target
  anyway (the core in the loop, drawn seed 61, SET_TARGETS with no gate): when the core faults and how far the flap
  went meanwhile (docs/firmware.md, "What software cannot mend"); then with the hinge disabled, as bring-up now
  leaves it (SET_WIRING's WIRING_DISABLED): what the device answers and how far the flap went in 3 s.

    python benchmarks/bench_safety_times.py

Board time, not this host's: the stand-ins' assumed costs (ROM boot 300 ms, GPIO calls 2 us, driver calls
20 us: esp32s3_host.cpp), not silicon's. One run: the figures are deterministic.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from controllers import sketch  # noqa: E402
from controllers.encoder import target_counts  # noqa: E402
from twin.commands import emulate  # noqa: E402
from twin.device.spec import load_spec  # noqa: E402
from twin.link.drawn_plant import emulator_args  # noqa: E402
from twin.link import protocol as P  # noqa: E402
from twin.link.emulator import Emulator, EmulatorOptions  # noqa: E402
from twin.sim.plant import as_twin  # noqa: E402

TARGETS = np.radians([30, -25, 20, -20, 25, -30])  # every hinge, both directions
NO_BRAKE = ("LOOP_LATE_TICKS=100000000",)  # the interrupt's brake never fires


def driven_after_hang(spec, defines: tuple[str, ...] = ()) -> int:
    """ms a motor stays driven after loop() hangs 60 ms into a move of every hinge (until the watchdog's reset)."""
    emu = Emulator(spec, EmulatorOptions(plant=as_twin(spec), sketch=True, zeroed=True))
    if defines:
        emu.firmware = sketch.Sketch(emu.plant.counts, P.ResetReason.POWERON, defines=defines)
        emu.firmware.confirm_zero()
    emu.receive(P.encode(P.SetTargets(tuple(int(c) for c in target_counts(spec, TARGETS))), 1))
    for i in range(60):
        if i % 50 == 0:
            emu.receive(P.encode(P.Heartbeat(), 2 + i))
        emu.step()
        emu.take_output()
    return emu.firmware.driven_after_hang(emu.counts, 10.0, 10000)


def unbraked_after_reset(pull_ups: bool) -> np.ndarray:
    """us each bridge is not braking from a reset to the end of set-up (the ROM's boot and setup())."""
    board = sketch.Sketch(np.zeros(6), wires=dataclasses.replace(sketch.wiring(), in_pull_ups=pull_ups))
    elapsed = float(board.lib.host_now_us())
    return np.array([(1 - board.bridge_shares(k)[2]) * elapsed for k in range(6)])


def driven_blind(spec, fault: str, flat: bool, seed: int = 61,
                 disabled: bool = False) -> tuple[int | None, str, float]:
    """A +10 deg target on the faulty hinge alone (disabled first: SET_WIRING's WIRING_DISABLED on it): (ms to the
    core's fault or None in 3 s, the fault or the NACK's reason, the flap's largest travel, deg)."""
    p = argparse.ArgumentParser()
    emulate.add_arguments(p)
    args = p.parse_args([*emulator_args(seed), "--latency-ms", "0", "--zeroed", *(["--lying-flat"] * flat),
                         "--wiring-fault", fault])
    emu = Emulator(spec, emulate.options_from_args(args, spec))
    k = int(fault.split(":")[1].split(",")[0])
    start = emu.plant.angles.copy()
    targets = [0] * spec.n_hinges
    targets[k] = round(np.radians(10) / spec.rad_per_count)
    n, said = spec.n_hinges, P.Decoder()
    if disabled:
        flags = tuple(P.WIRING_DISABLED if h == k else 0 for h in range(n))
        emu.receive(P.encode(P.SetWiring(tuple(range(n)), flags, tuple(range(n))), 100_000))
    emu.receive(P.encode(P.SetTargets(tuple(targets)), 1))
    refused = "none"
    travel = 0.0
    for t in range(3000):
        if t % 50 == 0:
            emu.receive(P.encode(P.Heartbeat(), 2 + t))
        emu.step()
        refused = next((P.enum_name(P.Nack, m.reason) for _, m in said.feed(emu.take_output())
                        if isinstance(m, P.NackMsg)), refused)
        travel = max(travel, abs(float(np.degrees(emu.plant.angles - start)[k])))
        if emu.firmware.state == P.State.FAULT:
            return t + 1, P.enum_name(P.Fault, emu.firmware.faults), travel
    return None, refused, travel


def main() -> None:
    spec = load_spec()
    print(f"hang:  a motor driven {driven_after_hang(spec)} ms after loop() hung (the interrupt's brake); "
          f"{driven_after_hang(spec, NO_BRAKE)} ms without it (the task watchdog's reset)")
    for pull_ups in (True, False):
        us = unbraked_after_reset(pull_ups)
        print(f"reset: {'with' if pull_ups else 'without'} the board's pull-ups, not braking from the reset to "
              f"the first tick: " + ", ".join(f"{x:.0f}" for x in us) + " us (hinges 0-5)")
    for fault, flat in (("encoder-dead:5", True), ("encoder-dead:5", False), ("channel-dead:3", True),
                        ("input-open:4,2", True)):
        for disabled in (False, True):
            ms, what, travel = driven_blind(spec, fault, flat, disabled=disabled)
            print(f"blind: {fault} {'lying flat' if flat else 'hanging'}{', disabled' if disabled else ''}, "
                  "+10 deg anyway: " + (f"{what} after {ms} ms" if ms else f"no fault in 3 s (NACK {what})")
                  + f", the flap moved up to {travel:.0f} deg")


if __name__ == "__main__":
    main()
