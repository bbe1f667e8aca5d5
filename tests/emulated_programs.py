"""A drawn plant lying flat, its programs run by the emulator in-process (the firmware core, the plant, the
protocol's frames both ways) as fast as the CPU steps it: the calibration tests and benchmarks/bench_calibration.py
run the identification experiments on it without a pty's real time. The pty path (`vrscroll calibrate
--serial`) is the same core answering the same frames."""

from __future__ import annotations

import dataclasses
import random

import numpy as np

from controllers.program import ProgramEnd, ProgramRun, end_name
from twin.link import protocol as P
from twin.link.emulator import Emulator, EmulatorOptions
from twin.link.faults import FaultOptions
from twin.link.serial_link import program_message
from twin.sim.plant import PlantRanges, draw_plant

ENCODER_MISS = 0.0005  # as tests/random_plant.py's


class EmulatedDevice:
    """One drawn plant lying flat, zeroed, in the emulator; `run_program` as Link.run_program."""

    def __init__(self, spec, seed: int):
        opt, _ = draw_plant(PlantRanges(), random.Random(seed), encoder_miss=ENCODER_MISS, n_hinges=spec.n_hinges)
        self.emulator = Emulator(spec, EmulatorOptions(plant=dataclasses.replace(opt, lying_flat=True),
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
        index = np.array(sorted(i for i in samples if i < status.ticks), np.int64)
        return ProgramRun(hinge, index * emu.dt, np.array([samples[i].duty for i in index], float) / P.DUTY_SCALE,
                          np.array([samples[i].counts for i in index], np.int64),
                          float(status.battery_mv) or None, end_name(status.end), int(status.ticks - len(index)))
