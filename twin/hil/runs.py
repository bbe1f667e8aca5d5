"""Hardware-in-the-loop comparison runs: one scenario on the device and on the twin, traces side by side.

A scenario (docs/tuning-hil-calibration.md) is a list of timed hinge targets. `run_hil` moves the
device to the scenario's start (gated, through twin.mirror), then plays the
targets on the device over the link while a twin with the device's gains,
started at the device's measured start angles with the device's recent history
(`twin_at_start`: so its firmware's integral matches), follows in device time: each
target takes effect in the twin at the device time the device's ACK reports.
Both traces are written as they come (CSV, one flushed line per row), so an
interrupted run keeps both up to that moment. `compare` computes per-hinge
RMSE, largest error, lag and settle times; `write_report` draws an overlay per
hinge and a Markdown report.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import math
import shutil
import time
import tomllib
from pathlib import Path

import numpy as np

from controllers.encoder import angle_from_counts, target_counts
from twin.device.spec import DeviceSpec

TRACE_COLUMNS = ("target_deg", "angle_deg", "counts", "duty", "current_A")


# ---- scenarios ------------------------------------------------------------------------------

@dataclasses.dataclass
class Scenario:
    """Timed hinge targets (rad) from a start (rad); after the last step the run lasts until duration (s)."""

    name: str
    start: np.ndarray  # rad
    times: list[float]  # s, from the first target's taking effect; times[0] == 0
    targets: list[np.ndarray]  # rad
    duration: float  # s

    def target_at(self, t: float) -> np.ndarray:
        i = max(k for k, tk in enumerate(self.times) if tk <= t + 1e-12)
        return self.targets[i]


def _angles_from_file(path: Path, n: int) -> list:
    doc = json.loads(path.read_text())
    for key in ("angles_deg", "hinge_angles_deg", "hinges_deg"):
        if key in doc:
            return doc[key]
    raise ValueError(f"{path}: no 'angles_deg' (or 'hinge_angles_deg') list in it")


def load_scenario(path, spec: DeviceSpec) -> Scenario:
    """Read a scenario (TOML or JSON, see docs/tuning-hil-calibration.md); ValueError naming the step for anything wrong."""
    path = Path(path)
    raw = path.read_bytes()
    doc = json.loads(raw) if path.suffix == ".json" else tomllib.loads(raw.decode())
    n = spec.n_hinges
    steps = doc.get("step") or doc.get("steps")
    if not steps:
        raise ValueError(f"{path}: no [[step]] entries")

    def angles(entry, where):
        if "angles_deg" in entry:
            deg = entry["angles_deg"]
        elif "file" in entry:
            deg = _angles_from_file(path.parent / entry["file"], n)
        else:
            raise ValueError(f"{path}: {where}: give angles_deg or file")
        if not isinstance(deg, list) or len(deg) != n:
            raise ValueError(f"{path}: {where}: expected {n} hinge angles in degrees, got {deg!r}")
        rad = np.radians(np.asarray(deg, float))
        if np.any(np.abs(rad) > spec.hinge_limit):
            k = int(np.argmax(np.abs(rad)))
            raise ValueError(f"{path}: {where}: hinge {k} at {deg[k]} deg is outside +-"
                             f"{math.degrees(spec.hinge_limit):.1f} deg")
        return rad

    times, targets = [], []
    for i, entry in enumerate(steps):
        t = float(entry.get("t_s", 0.0))
        if times and t <= times[-1]:
            raise ValueError(f"{path}: step {i}: t_s {t} is not after the previous step's {times[-1]}")
        times.append(t)
        targets.append(angles(entry, f"step {i}"))
    if times[0] != 0.0:
        raise ValueError(f"{path}: the first step must be at t_s = 0")
    start = angles({"angles_deg": doc["start_deg"]}, "start_deg") if "start_deg" in doc else np.zeros(n)
    duration = float(doc.get("duration_s", times[-1] + 1.0))
    if duration <= times[-1]:
        raise ValueError(f"{path}: duration_s {duration} ends before the last step at {times[-1]} s")
    return Scenario(str(doc.get("name", path.stem)), start, times, targets, duration)


# ---- traces, written as they come -------------------------------------------------------------

class TraceWriter:
    """A CSV trace, one line per row, flushed per line: time_s, then h{k}_{column} per hinge."""

    def __init__(self, path, n: int, extra=()):
        self.n = n
        self.cols = TRACE_COLUMNS + tuple(extra)
        self.f = open(path, "w", newline="", buffering=1)
        self.w = csv.writer(self.f, lineterminator="\n")
        self.w.writerow(["time_s"] + [f"h{k}_{c}" for k in range(n) for c in self.cols])
        self.rows = 0

    def write(self, t: float, **cols) -> None:
        row = [f"{t:.4f}"]
        for k in range(self.n):
            for c in self.cols:
                v = cols[c][k]
                row.append(str(int(v)) if c == "counts" else f"{v:.4f}")
        self.f.write(",".join(row) + "\n")  # one write per row: a killed run loses at most the line being written
        self.rows += 1

    def close(self) -> None:
        self.f.close()


def read_trace(path) -> dict:
    """A trace CSV as arrays: 'time_s' (rows,), each column name (rows, hinges). Skips a cut-off last line."""
    lines = Path(path).read_text().splitlines()
    header = lines[0].split(",")
    ncol = len(header)
    rows = [ln.split(",") for ln in lines[1:]]
    rows = [r for r in rows if len(r) == ncol and all(x != "" for x in r)]
    data = np.array([[float(x) for x in r] for r in rows]).reshape(-1, ncol)
    out = {"time_s": data[:, 0]}
    n = 1 + max(int(h.split("_")[0][1:]) for h in header[1:])
    for c in {h.split("_", 1)[1] for h in header[1:]}:
        out[c] = np.stack([data[:, header.index(f"h{k}_{c}")] for k in range(n)], axis=1)
    return out


# ---- running -------------------------------------------------------------------------------------

class HilInterrupted(RuntimeError):
    pass


def gate_scenario(spec: DeviceSpec, scenario: Scenario, gains, settle_limit: float = 2.0):
    """Check every step of the scenario on the twin (range, collision, settle, current) before anything moves."""
    from twin.sim.gate import check_move, enforce
    from twin.sim.simulation import Twin

    twin = Twin(spec, gains)
    prev = scenario.start
    for tgt in scenario.targets:
        enforce(check_move(spec, prev, tgt, gains, settle_limit=settle_limit, twin=twin))
        prev = tgt


REST = 1.0  # s the twin spends on each leg of the device's history before a run


def twin_at_start(plant: DeviceSpec, gains, meta: dict, spec: DeviceSpec | None = None):
    """A twin at the device's start with the device's recent history, so its firmware state matches.

    The device's PID integral carries the flaps' weight, and where in its
    friction band it sits depends on how the hinge came to rest (a twin started
    with an empty integral sags, then overshoots the first step). So the twin
    lives the run's prelude as the device did (meta "before"): resting at the
    device's pose before the run (holding its targets if it was ACTIVE; limp and
    with a fresh PID, as after IDLE, if not), then brought to the start targets
    (REST s each); finally its hinges are put exactly where the device's
    encoders say (mid-count: the encoder floors), its firmware state kept.
    """
    from twin.sim.simulation import Twin

    spec = spec or plant
    twin = Twin(plant, gains)

    def put(counts):
        return np.clip(angle_from_counts(spec, np.asarray(counts) + 0.5), -spec.hinge_limit, spec.hinge_limit)

    before = meta["before"]
    twin.reset(put(before["counts"]))
    if before["state"] == "ACTIVE":
        twin.move_to(angle_from_counts(spec, before["target_counts"]), max_time=REST, stop_when_settled=False)
    twin.move_to(angle_from_counts(spec, meta["start_target_counts"]), max_time=REST, stop_when_settled=False)
    integral = twin.pid.integral.copy()
    twin.reset(put(meta["start_counts"]))
    twin.pid.integral[:] = integral
    return twin


def run_hil(link, spec: DeviceSpec, scenario: Scenario, out_dir, telemetry_hz: int = 500,
            scenario_path=None, on_progress=None, settle_limit: float = 2.0, gains=None,
            tolerance_deg: float = 5.0) -> dict:
    """Play a scenario on the device and the twin; write out_dir/{device,twin}.csv, gains.json, run.json.

    gains: optional per-hinge PidGains pushed to the device first. tolerance_deg: the device is e-stopped
    if it parts from the twin by more on its way to the scenario's start (twin.hil.mirror). Returns run.json's
    content. On KeyboardInterrupt the device is e-stopped and both traces stay readable up to that moment.
    """
    from twin.tuning.tuner import write_gains
    from twin.hil.mirror import device_gains, mirror, wait_for_rest
    from twin.link import protocol as P

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    n, dt = spec.n_hinges, spec.firmware_dt
    if gains is not None:  # push these first (one PidGains per hinge); the run uses what the device then holds
        for k, g in enumerate(gains):
            link.set_gains(g, hinge=k)
    gains = device_gains(link, n)
    gate_scenario(spec, scenario, gains, settle_limit)
    if scenario_path:
        shutil.copy(scenario_path, out / ("scenario" + Path(scenario_path).suffix))
    write_gains(out / "gains.json", gains, {"source": f"read from the device at {link.url}"})
    # the same start on both sides: move the device there (gated), then start the twin where the device is,
    # with the device's history (twin_at_start)
    prior = wait_for_rest(link, spec)
    res = mirror(link, spec, scenario.start, settle_limit=settle_limit, tolerance_deg=tolerance_deg)
    if not res.ok:
        raise RuntimeError(f"could not bring the device to the scenario's start: {res.message}")
    state = wait_for_rest(link, spec)
    meta = {"scenario": scenario.name, "start_counts": list(state.counts), "start_target_counts": list(state.targets),
            "before": {"state": P.State(prior.state).name, "counts": list(prior.counts),
                       "target_counts": list(prior.targets)},
            "telemetry_hz": telemetry_hz, "firmware_dt_s": dt, "changes": [], "status": "running", "port": link.url}
    twin = twin_at_start(spec, gains, meta)
    run_json = out / "run.json"

    def save_meta():
        tmp = run_json.with_suffix(".json.part")
        tmp.write_text(json.dumps(meta, indent=2) + "\n")
        tmp.replace(run_json)

    dev_w = TraceWriter(out / "device.csv", n)
    twin_w = TraceWriter(out / "twin.csv", n, extra=("true_deg",))
    stride = max(1, int(round(spec.loop_rate / telemetry_hz)))
    changes: list[tuple[float, np.ndarray]] = []
    twin_ticks = 0
    mask = 0xFFFFFFFF

    def advance(to_time: float):
        nonlocal twin_ticks
        while (twin_ticks + 1) * dt <= to_time + 1e-9:
            now = twin_ticks * dt
            cur = max(i for i, (tc, _) in enumerate(changes) if tc <= now + 1e-9)
            nxt = changes[cur + 1][0] if cur + 1 < len(changes) else math.inf
            end = min(to_time, nxt)
            ticks = int(round((end - now) / dt))
            if ticks <= 0:
                ticks = 1
            tr = twin.move_to(changes[cur][1], max_time=ticks * dt, stop_when_settled=False)
            enc = angle_from_counts(spec, tr.counts)
            for i in range(len(tr.time)):
                tick = twin_ticks + i
                if tick % stride == 0:
                    twin_w.write(tick * dt, target_deg=np.degrees(tr.target[i]), angle_deg=np.degrees(enc[i]),
                                 counts=tr.counts[i], duty=tr.duty[i], current_A=tr.current[i],
                                 true_deg=np.degrees(tr.angle[i]))
            twin_ticks += len(tr.time)

    try:
        link.set_telemetry_rate(telemetry_hz)
        link.drain_telemetry()
        ack = link.set_targets(target_counts(spec, scenario.targets[0]))
        t0 = ack.time_us
        host0 = time.monotonic()
        changes.append((0.0, scenario.targets[0]))
        meta["changes"].append({"t_s": 0.0, "angles_deg": np.degrees(scenario.targets[0]).round(4).tolist()})
        meta["device_t0_us"] = t0
        save_meta()
        nxt = 1
        latest = 0.0
        while latest < scenario.duration:
            if nxt < len(scenario.times) and time.monotonic() - host0 >= scenario.times[nxt]:
                ack = link.set_targets(target_counts(spec, scenario.targets[nxt]))
                tc = ((ack.time_us - t0) & mask) / 1e6
                changes.append((tc, scenario.targets[nxt]))
                meta["changes"].append({"t_s": round(tc, 6),
                                        "angles_deg": np.degrees(scenario.targets[nxt]).round(4).tolist()})
                save_meta()
                nxt += 1
            item = link.telemetry(timeout=0.5)
            if item is None:
                link.estop()
                raise RuntimeError("no telemetry from the device for 0.5 s; e-stopped")
            for _, fr in [item] + link.drain_telemetry():
                since = ((fr.time_us - t0) & mask) / 1e6
                if since > 3600:
                    continue  # from before the first target took effect
                if fr.state in (P.State.FAULT, P.State.ESTOP):
                    raise RuntimeError(f"device stopped itself at t={since:.3f} s (faults {fr.faults})")
                dev_w.write(since, target_deg=np.degrees(angle_from_counts(spec, fr.targets)),
                            angle_deg=np.degrees(angle_from_counts(spec, fr.counts)), counts=fr.counts,
                            duty=np.asarray(fr.duty) / P.DUTY_SCALE, current_A=np.asarray(fr.current_ma) / 1000.0)
                latest = max(latest, since)
            advance(min(latest, scenario.duration))
            if on_progress:
                on_progress(latest)
        meta["status"] = "complete"
    except KeyboardInterrupt:
        meta["status"] = "interrupted"
        try:
            link.estop()
        except Exception:
            pass
        raise
    except Exception as exc:
        meta["status"] = f"failed: {exc}"
        raise
    finally:
        dev_w.close()
        twin_w.close()
        meta["device_rows"], meta["twin_rows"] = dev_w.rows, twin_w.rows
        save_meta()
    return meta


# ---- comparison ----------------------------------------------------------------------------------

def _lag(t, a, b, max_lag: float = 0.2) -> float:
    """Seconds by which b lags a (positive: b later), by cross-correlating their rates on a uniform grid."""
    if len(t) < 8:
        return float("nan")
    dt = float(np.median(np.diff(t)))
    grid = np.arange(t[0], t[-1], dt)
    da, db = np.diff(np.interp(grid, t, a)), np.diff(np.interp(grid, t, b))
    if not np.any(da) or not np.any(db):
        return 0.0
    m = int(max_lag / dt)
    best, arg = -np.inf, 0
    for s in range(-m, m + 1):
        x, y = (da[: len(da) - s], db[s:]) if s >= 0 else (da[-s:], db[: len(db) + s])
        c = float(np.dot(x, y))
        if c > best:
            best, arg = c, s
    return arg * dt


def segment_settle(spec: DeviceSpec, t, angle_deg, target_deg, changes_t, end_t):
    """Per step segment and hinge: settle time (s) after each target change, NaN if not settled or no step."""
    from twin.sim.response import step_metrics

    band = math.degrees(spec.settle_band * spec.rad_per_count)
    out = []
    bounds = list(changes_t) + [end_t]
    for i in range(len(changes_t)):
        sel = (t >= bounds[i] - 1e-9) & (t < bounds[i + 1] - 1e-9)
        row = []
        for k in range(angle_deg.shape[1]):
            if sel.sum() < 2:
                row.append(float("nan"))
                continue
            y = angle_deg[sel, k]
            tgt = float(target_deg[sel, k][-1])
            if abs(tgt - y[0]) <= band:
                row.append(float("nan"))  # no step for this hinge here
                continue
            row.append(step_metrics(t[sel], y, tgt, band, tail=spec.settle_hold).settle_time)
        out.append(row)
    return np.array(out).reshape(len(changes_t), angle_deg.shape[1])


def compare(spec: DeviceSpec, device: dict, twin: dict, changes_t=(0.0,)) -> list[dict]:
    """Per hinge: RMSE and largest |device - twin| (deg, encoder angles, at the device's sample times),
    lag (s, positive: the device later than the twin), mean settle time per side over the steps."""
    t = device["time_s"]
    end = float(min(t[-1], twin["time_s"][-1])) if len(t) and len(twin["time_s"]) else 0.0
    sel = t <= end + 1e-9
    t = t[sel]
    n = device["angle_deg"].shape[1]
    rows = []
    tw = np.stack([np.interp(t, twin["time_s"], twin["angle_deg"][:, k]) for k in range(n)], axis=1)
    dv = device["angle_deg"][sel]
    err = dv - tw
    s_dev = segment_settle(spec, t, dv, device["target_deg"][sel], changes_t, end)
    tsel = twin["time_s"] <= end + 1e-9
    s_twin = segment_settle(spec, twin["time_s"][tsel], twin["angle_deg"][tsel], twin["target_deg"][tsel],
                            changes_t, end)
    for k in range(n):
        rows.append({
            "hinge": k,
            "rmse_deg": round(float(np.sqrt(np.mean(err[:, k] ** 2))) if len(t) else float("nan"), 4),
            "max_error_deg": round(float(np.max(np.abs(err[:, k]))) if len(t) else float("nan"), 4),
            "lag_s": round(_lag(t, tw[:, k], dv[:, k]), 4),
            "settle_device_s": _nanmean(s_dev[:, k]),
            "settle_twin_s": _nanmean(s_twin[:, k]),
            "steps": int(np.sum(~np.isnan(s_dev[:, k]) | ~np.isnan(s_twin[:, k]))),
        })
    return rows


def _nanmean(a):
    a = np.asarray(a, float)
    return round(float(np.mean(a[~np.isnan(a)])), 4) if np.any(~np.isnan(a)) else float("nan")


def load_run(run_dir) -> dict:
    """A recorded HIL run: device and twin traces, run.json, gains."""
    from twin.tuning.tuner import read_gains

    d = Path(run_dir)
    meta = json.loads((d / "run.json").read_text())
    return {"dir": d, "meta": meta, "device": read_trace(d / "device.csv"),
            "twin": read_trace(d / "twin.csv") if (d / "twin.csv").exists() else None,
            "gains": read_gains(d / "gains.json")}


def write_report(spec: DeviceSpec, run_dir, rows: list[dict] | None = None) -> Path:
    """Overlay PNG per hinge (target, device, twin) and report.md with the metrics table; returns report.md."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    run = load_run(run_dir)
    d, dev, tw, meta = run["dir"], run["device"], run["twin"], run["meta"]
    changes_t = [c["t_s"] for c in meta["changes"]] or [0.0]
    rows = rows or compare(spec, dev, tw, changes_t)
    lines = [f"# HIL run: {meta['scenario']}", "",
             f"Status: {meta['status']}; device rows {len(dev['time_s'])}, twin rows {len(tw['time_s'])}; "
             f"port {meta.get('port')}. Angles are encoder angles (counts x {math.degrees(spec.rad_per_count):.4f} "
             "deg); error = device - twin; lag > 0: the device is later.", "",
             "| hinge | RMSE deg | largest error deg | lag s | settle device s | settle twin s |",
             "|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['hinge']} | {r['rmse_deg']:.3f} | {r['max_error_deg']:.3f} | {r['lag_s']:.4f} | "
                     f"{r['settle_device_s']:.3f} | {r['settle_twin_s']:.3f} |")
    lines.append("")
    for k in range(dev["angle_deg"].shape[1]):
        fig, ax = plt.subplots(figsize=(7, 3))
        ax.plot(tw["time_s"], tw["target_deg"][:, k], "k--", lw=0.8, label="target")
        ax.plot(dev["time_s"], dev["angle_deg"][:, k], lw=1.2, label="device")
        ax.plot(tw["time_s"], tw["angle_deg"][:, k], lw=1.0, label="twin")
        ax.set_xlabel("time (s)")
        ax.set_ylabel(f"hinge {k} angle (deg)")
        ax.legend(loc="best", fontsize=8)
        fig.tight_layout()
        name = f"hinge{k}.png"
        fig.savefig(d / name, dpi=90)
        plt.close(fig)
        lines.append(f"![hinge {k}]({name})")
        lines.append("")
    (d / "metrics.json").write_text(json.dumps(rows, indent=2) + "\n")
    path = d / "report.md"
    path.write_text("\n".join(lines))
    return path


# ---- one step on the device, for tuning -------------------------------------------------------

def device_step(link, spec: DeviceSpec, targets, settle_limit: float = 2.0):
    """Bring the device to flat, then step to targets (rad), both gated through mirror.

    Returns (t s, angle deg (frames, n), start angle rad): the device's encoder angles
    from the moment the step took effect until it settled (or mirror gave up).
    """
    from twin.hil.mirror import mirror, wait_for_rest

    n = spec.n_hinges
    res = mirror(link, spec, np.zeros(n), settle_limit=settle_limit)
    if not res.ok:
        raise RuntimeError(f"device did not reach flat: {res.message}")
    state = wait_for_rest(link, spec)
    start = angle_from_counts(spec, state.counts)
    ts, ys = [], []
    res = mirror(link, spec, targets, settle_limit=settle_limit, tolerance_deg=30.0,
                 on_frame=lambda t, dev, pred: (ts.append(t), ys.append(np.array(dev))))
    # keep watching a little after mirror's settle so the trace has a tail for the metrics
    return np.array(ts), np.array(ys).reshape(-1, n), start, res
