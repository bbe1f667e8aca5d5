"""A device plant nobody chose: the emulator draws its parameters at random within its stated ranges (twin.sim.plant's
PlantRanges), and an emulated device on one run in-process.

`emulator_args` are the `vrscroll emulate` options that draw every parameter from a seed; the drawn values are
in the emulator's log only (its "start" event: `drawn_plant`, `drawn_hinges`), so the twin never sees them and
only a judge reads them (twin.hil.calibration_verdict). `EmulatedDevice` is one drawn plant lying flat, its
programs run by the emulator in-process (the firmware core, the plant, the protocol's frames both ways) as fast
as the CPU steps it: the calibration tests and benchmarks/bench_calibration.py run the identification
experiments on it without a pty's real time. The pty path (`vrscroll calibrate --serial`) is the same core
answering the same frames.
"""

from __future__ import annotations

import dataclasses
import random

from controllers.program import ProgramEnd, ProgramRun
from twin.link import protocol as P
from twin.link.emulator import Emulator, EmulatorOptions
from twin.link.faults import FaultOptions
from twin.link.serial_link import program_message, program_run
from twin.sim.plant import PlantRanges, draw_plant

# the stated ranges (the emulator's documented defaults), as its options: x the spec's value, or deg and ms
RANGES = {f.name.replace("_", "-"): "{:g},{:g}".format(*getattr(PlantRanges(), f.name))
          for f in dataclasses.fields(PlantRanges)}
ENCODER_MISS = 0.0005  # probability per edge the encoder's counter misses it


def emulator_args(seed: int) -> list[str]:
    """`vrscroll emulate` options: every parameter drawn within RANGES from the seed."""
    args = ["--seed", str(seed), "--encoder-miss", str(ENCODER_MISS)]
    for k, v in RANGES.items():
        args += ["--" + k, v]
    return args


def drawn_plant(emulator) -> dict:
    """The plant the emulator drew (spec field -> SI value), from its log."""
    return next(e for e in emulator.events("start"))["plant"]


def drawn_hinges(emulator) -> list[dict]:
    """Each hinge's drawn values (spec field -> SI value), from the emulator's log."""
    return next(e for e in emulator.events("start"))["hinges"]


class EmulatedDevice:
    """One drawn plant lying flat, zeroed, in the emulator; `run_program` as Link.run_program."""

    def __init__(self, spec, seed: int):
        opt, _ = draw_plant(PlantRanges(), random.Random(seed), encoder_miss=ENCODER_MISS, n_hinges=spec.n_hinges)
        self.emulator = Emulator(spec, EmulatorOptions(plant=dataclasses.replace(opt, mount="flat"),
                                                       faults=FaultOptions(latency_ms=0.0), zeroed=True, seed=seed))
        self.seq = 0

    @property
    def truth(self) -> list:
        """Each hinge's drawn spec (what the emulator's log says)."""
        return self.emulator.plant.hinge_specs

    def _send(self, msg) -> None:
        self.seq += 1
        self.emulator.receive(P.encode(msg, self.seq & 0xFFFF))

    def run_program(self, hinge, segments, window_counts, timeout_s=None) -> ProgramRun:
        """The program run by the core to its end, a heartbeat every 50 ticks: its samples (ProgramRun)."""
        emu, decoder = self.emulator, P.Decoder()
        self._send(program_message(hinge, segments, window_counts, timeout_s))
        samples, status, tick = {}, None, 0
        while status is None:
            if tick % 50 == 0:
                self._send(P.Heartbeat())
            if tick % 10 == 9:
                self._send(P.GetProgram())
            emu.step()
            tick += 1
            for seq, m in decoder.feed(emu.take_output()):
                if isinstance(m, P.ProgramSample):
                    samples[seq] = m
                elif isinstance(m, P.NackMsg):
                    raise ValueError(f"the emulator refused the program: {m}")
                elif isinstance(m, P.ProgramStatus) and m.end != ProgramEnd.RUNNING and tick > 2:
                    status = m
        return program_run(hinge, samples, status, emu.dt)
