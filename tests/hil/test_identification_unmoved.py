"""A hinge the identification experiments cannot turn (jammed, a dead encoder, a motor that does not turn):
`calibrate --serial` keeps the prior for it, says why in a line a user can act on, and fits the others, rather
than failing whole (twin.hil.calibration_report.identify)."""

import dataclasses
import json
import random

import numpy as np
import pytest

from twin.cli import main as vrscroll
from twin.device.variation import SPREAD
from twin.hil.calibration import HINGE_RANGE
from twin.hil.calibration_report import MIN_TRAVEL, moved, not_moved_note, prior_estimates
from twin.hil.identification import PROFILED, experiments
from twin.link.drawn_plant import ENCODER_MISS, EmulatedDevice, emulator_args
from twin.link.emulator import Emulator, EmulatorOptions
from twin.link.faults import FaultOptions
from twin.sim.plant import PlantRanges, draw_plant


def jammed_device(spec, seed: int, hinge: int) -> EmulatedDevice:
    """seed's drawn plant lying flat, zeroed, its `hinge` jammed from the first drive on."""
    opt, _ = draw_plant(PlantRanges(), random.Random(seed), encoder_miss=ENCODER_MISS, n_hinges=spec.n_hinges)
    dev = EmulatedDevice.__new__(EmulatedDevice)
    dev.emulator = Emulator(spec, EmulatorOptions(plant=dataclasses.replace(opt, mount="flat"), zeroed=True, seed=seed,
                                                  faults=FaultOptions(latency_ms=0.0, jam_hinge=hinge)))
    dev.seq = 0
    return dev


def test_a_jammed_hinge_is_not_fitted_and_the_note_says_how_its_programs_ended(spec):
    dev = jammed_device(spec, 5, 2)
    ends = []

    def run_program(hinge, *args):
        run = dev.run_program(hinge, *args)
        ends.append(run.end)
        return run

    moves, _ = experiments(run_program, spec, hinges=(2,))
    assert moves[2] and not moved(moves[2])
    n = len(moves[2][0].counts)
    assert moved([dataclasses.replace(moves[2][0], counts=moves[2][0].counts + np.linspace(0, 2 * MIN_TRAVEL, n))])
    note = not_moved_note(ends)
    assert f"none of its {len(ends)} programs turned it {MIN_TRAVEL} counts" in note and "bringup" in note
    assert all(end in note for end in ends)
    for p, e in prior_estimates(spec, note).items():
        v = getattr(spec, p)
        assert e.value == e.prior == v and not e.identifiable and e.note == note
        assert e.low == pytest.approx(v * SPREAD[p][0] * HINGE_RANGE[0])
        assert e.high == pytest.approx(v * SPREAD[p][1] * HINGE_RANGE[1])
    assert set(prior_estimates(spec, note)) == set(PROFILED)


@pytest.mark.slow
def test_calibrate_serial_fits_the_hinges_that_turn_and_names_the_jammed_one(emulator, capsys):
    """`vrscroll calibrate --serial PORT --device NAME --json -` on a drawn plant lying flat whose hinge 2's encoder
    is dead (its count never changes): exit 0, the profile written, hinge 2 not fitted (its prior kept, not
    identifiable, the note pointing at bring-up), every other hinge fitted."""
    emu = emulator("--lying-flat", *emulator_args(6), "--wiring-fault", "encoder-dead:2")
    assert vrscroll(["calibrate", "--serial", emu.port, "--device", "jam6", "--json", "-"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["written"]
    for h in out["hinges"]:
        assert h["fitted"] is (h["hinge"] != 2)
    for e in out["hinges"][2]["parameters"].values():
        assert e["value"] == e["prior"] and not e["identifiable"] and "bringup" in e["note"]
