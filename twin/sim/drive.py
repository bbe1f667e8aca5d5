"""The drive train's electrical side and its gearbox: one model for the twin, the batch twin and the emulator.

Each firmware tick the core gives a PWM per hinge (its battery compensation applied, `vrs_pwm`) and a
decay mode; `drive` turns them, with each gearbox output's speed, into what MuJoCo's dcmotor is given
and what the device's sensors would read:

- the pack: open-circuit voltage V_pack behind pack_resistance, shared by every driver. Its
  terminal (the bus) is V_bus = V_pack - R_pack * sum_k pwm_k * I_k, which with the currents
  below is one linear equation, solved exactly;
- each driver in slow decay (brake: the winding shorted in the PWM's off-time) is the average
  voltage pwm * V_bus behind its FETs' on-resistance, in series with the winding:
  I = (pwm * V_bus - K*N*w) / (R + R_on);
- coast at zero PWM opens the winding: no current, no back-EMF braking (the core chooses it only for an
  open-loop program's coasting segment: docs/firmware.md);
- the driver's analog current limit clamps |I| at driver_current_limit;
- the gearbox passes the motor's torque N*K*I with efficiency eta driving (power from the motor to
  the flap) and 1 / eta_back back-driven (the flap drives the motor: the load must supply more
  than the motor takes). MuJoCo's dcmotor applies N*K*I; the difference, (eff - 1) * N*K*I, is
  the gearbox's load-dependent friction and goes to qfrc_applied on the gear joint.

The result is held over the tick's physics steps (MuJoCo's dcmotor recomputes its back-EMF every
step from `ctrl`, the voltage behind R + R_on). Units: V, A, ohm, rad/s, N*m.
"""

from __future__ import annotations

import numba
import numpy as np

from twin.device.spec import DeviceSpec

# indices into the parameter vector `drive_params` returns
V_PACK, R_PACK, K_EMF, R_DRIVE, I_LIMIT, ETA, ETA_BACK = range(7)
BACKDRIVE_SPEED = 1e-3  # rad/s: below this the gearbox counts as driving (a held flap is driven, not back-driving)
DECAY_COAST = 0  # VRS_DECAY_COAST in vrs_core.h


def drive_params(spec: DeviceSpec, hinges: list[DeviceSpec] | None = None) -> np.ndarray:
    """The drive model's constants for a spec, as the compiled loops take them: (n_hinges, 7) float64, a row
    per hinge. hinges: each hinge's own spec where the motors differ (the emulator's plant); the pack's
    values (V_PACK, R_PACK) are the spec's in every row."""
    hinges = hinges or [spec] * spec.n_hinges
    p = np.zeros((len(hinges), 7))
    p[:, V_PACK], p[:, R_PACK] = spec.supply_voltage, spec.pack_resistance
    for h, s in enumerate(hinges):
        p[h, K_EMF], p[h, R_DRIVE] = s.motor_constant * s.gear_ratio, s.drive_resistance
        p[h, I_LIMIT], p[h, ETA], p[h, ETA_BACK] = s.driver_current_limit, s.gearbox_efficiency, s.backdrive_efficiency
    return p


@numba.njit(cache=True)
def drive(params, pwm, decay, qvel, gear_dof, ctrl, qfrc_applied, current) -> float:
    """One tick's drive: writes ctrl (V behind R + R_on, per actuator), qfrc_applied at each gear dof (N*m,
    the gearbox's efficiency) and current (A, the winding's); returns the bus voltage (V).

    pwm (per hinge, [-1, 1]) and decay (0 coast, 1 brake) are the core's; qvel and qfrc_applied are the
    MjData arrays (or one batch row), gear_dof the gear joints' dof addresses.
    """
    n = pwm.shape[0]
    # the bus: V_bus (1 + R_pack sum p^2 / R) = V_pack + R_pack sum p e / R over the windings that conduct
    a, b = 0.0, 0.0
    for h in range(n):
        if pwm[h] != 0.0 or decay[h] != DECAY_COAST:
            a += pwm[h] * pwm[h] / params[h, R_DRIVE]
            b += pwm[h] * params[h, K_EMF] * qvel[gear_dof[h]] / params[h, R_DRIVE]
    v_bus = (params[0, V_PACK] + params[0, R_PACK] * b) / (1.0 + params[0, R_PACK] * a)
    bus_current = 0.0
    for h in range(n):
        k_emf, r, lim = params[h, K_EMF], params[h, R_DRIVE], params[h, I_LIMIT]
        w = qvel[gear_dof[h]]
        emf = k_emf * w
        if pwm[h] == 0.0 and decay[h] == DECAY_COAST:
            i = 0.0
        else:
            i = min(max((pwm[h] * v_bus - emf) / r, -lim), lim)
        current[h] = i
        ctrl[h] = emf + r * i  # the voltage behind R that gives MuJoCo's dcmotor this current
        torque = k_emf * i  # N*K*I at the output, before the gearbox's losses
        eff = params[h, ETA] if torque * w >= 0.0 or abs(w) < BACKDRIVE_SPEED else 1.0 / params[h, ETA_BACK]
        qfrc_applied[gear_dof[h]] = (eff - 1.0) * torque
        bus_current += pwm[h] * i
    return params[0, V_PACK] - params[0, R_PACK] * bus_current

