"""Step metrics against signals with known answers."""

import math

import numpy as np
import pytest

from twin.sim.response import step_metrics


def test_first_order_step():
    tau = 0.05
    t = np.arange(0, 1.0, 1e-4)
    y = 10 * (1 - np.exp(-t / tau))
    m = step_metrics(t, y, 10.0, band=0.2)  # 2 % band
    assert m.settle_time == pytest.approx(tau * math.log(50), abs=2e-4)
    assert m.rise_time == pytest.approx(tau * math.log(9), abs=2e-4)
    assert m.overshoot == 0.0
    assert m.steady_state_error == pytest.approx(0.0, abs=1e-6)


def test_underdamped_second_order_overshoot():
    zeta, wn = 0.3, 40.0
    t = np.arange(0, 2.0, 1e-4)
    wd = wn * math.sqrt(1 - zeta**2)
    y = 1 - np.exp(-zeta * wn * t) * (np.cos(wd * t) + zeta / math.sqrt(1 - zeta**2) * np.sin(wd * t))
    m = step_metrics(t, y, 1.0, band=0.02)
    assert m.overshoot_pct == pytest.approx(100 * math.exp(-zeta * math.pi / math.sqrt(1 - zeta**2)), rel=1e-3)


def test_never_settles_and_offset():
    t = np.linspace(0, 1, 101)
    m = step_metrics(t, np.full(101, 0.5), 1.0, band=0.1)
    assert math.isnan(m.settle_time) and m.steady_state_error == pytest.approx(0.5)
    with pytest.raises(ValueError):
        step_metrics(t, np.zeros(5), 1.0, band=0.1)
