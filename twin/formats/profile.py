"""Device profile folder (docs/formats.md "Device profile"): one researcher's device, as the twin
knows it after calibration and tuning.

    profile.json   {"format": "vrscroll-profile/1", "name": NAME, "mount": MOUNT, "calibration": {...},
                   "holding": {...}} (mount, calibration and holding optional)
    spec.toml      the device's spec, a spec TOML: every value with its source ("calibrated from ...")
    gains.json     the device's gains, a gains file (optional: the spec's gains when absent)

"calibration" (written by `vrscroll calibrate --device`): {"runs": [folder, ...], "parameters":
{name: {"value", "prior", "low", "high", "identifiable", "note", "runs_low", "runs_high"}}, "hinges":
[{name: {...}}, ...]}, values in SI (the spec's field units); low..high is the interval the calibration
leaves open for the device (its 95 % interval for a fitted parameter, widened by what the bounded parameters
could move it, and the prior range where it is not identifiable); runs_low..runs_high (optional: a
calibration of before they were kept has none) is the twin's values that reproduce the runs with the
bounded parameters at the profile's values, which `vrscroll tune` tunes over (low..high without them).
"hinges" (optional, `vrscroll calibrate --per-hinge`): per hinge, its own values of the
parameters a hinge's motor and gearbox change, each about the shared value (its "prior"): the twin of
the profile (twin.sim.twin.profile_twin) gives each hinge its own.
"mount" (written by `--mount` with `--device`, or `vrscroll device create NAME --mount M`): how the device is
held, one of twin.device.mount.MOUNTS ("hanging", "flat", "stand"); a profile without it (older ones) hangs.
"holding" (written by `vrscroll holding --device`): {"port", "releases": count, "parameters":
{"backdrive_efficiency": {...}}}, the value also in spec.toml (twin.hil.holding).
Where the folders live is twin.device.profile's; which one a command uses is `chosen_profile` here (the one
named, else the selected one, else the spec's defaults), and the line every report starts with `profile_line`.

Read and written whole as the record twin.records.profile.Profile (its Calibration and Holding records):
`read_profile` gives it, a command makes the changed record with `updated` and `write_profile` writes it, so no
command builds a part of profile.json by hand and what is written is what the next command reads.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

from controllers.pid import PidGains
from twin.checks import json_object, known_keys, number, required_keys
from twin.device.mount import DEFAULT_MOUNT, check_mount
from twin.device.profile import default_name, profile_dir, profiles_dir, set_default
from twin.device.spec import SPEC_PATH, DeviceSpec, load_spec, spec_sources
from twin.device.spec_toml import shown, shown_range, spec_units, write_spec_toml
from twin.device.variation import PLANT_FIELDS, scaled
from twin.formats.gains import read_gains, write_gains
from twin.paths import replacing
from twin.records.calibration import Calibration, Estimate
from twin.records.gains import Gains
from twin.records.profile import Holding, Profile

PROFILE_FORMAT = "vrscroll-profile/1"
META, SPEC, GAINS, WIRING = "profile.json", "spec.toml", "gains.json", "wiring.json"
PARAMETER_KEYS = ("value", "prior", "low", "high", "identifiable", "note")
RUNS_KEYS = ("runs_low", "runs_high")  # optional (a calibration before they were kept has neither): what tuning covers
META_PARTS = ("mount", "calibration", "holding")  # what profile.json holds beside its format and name


def hinge_plants(spec: DeviceSpec, calibration: Calibration | None) -> list[DeviceSpec] | None:
    """Each hinge's own spec where calibration fitted per-hinge values (None where it did not): the spec with
    that hinge's values, the fields that move with one moved alike (twin.device.variation.scaled)."""
    rows = calibration.hinges if calibration else None
    if not rows:
        return None
    return [scaled(spec, {p: e.value / getattr(spec, p) for p, e in row.items()}) for row in rows]


def spec_defaults() -> Profile:
    """The spec's defaults as a profile (name None): models/vrscroll/spec.toml and its gains on every hinge."""
    spec = load_spec()
    return Profile(None, None, spec, spec_sources(), [PidGains.from_spec(spec)] * spec.n_hinges, "spec",
                   DEFAULT_MOUNT)


def updated(profile: Profile, values: dict | None = None, source: str = "", **parts) -> Profile:
    """The profile with plant `values` (spec field -> SI) in its spec, each from `source`, and `parts` (name,
    calibration, holding, mount) replaced; its per-hinge plants made again from its spec and calibration."""
    values = values or {}
    spec = profile.spec.replace(**values)
    out = dataclasses.replace(profile, spec=spec, sources=profile.sources | {f: source for f in values}, **parts)
    return dataclasses.replace(out, hinges=hinge_plants(spec, out.calibration))


def plant_is_physical(spec: DeviceSpec, where, hinge_rows=None) -> None:
    """ValueError naming the entry when a profile's drive train is not one a gearmotor can have (issue 40: a
    gear_stiction of 1e6 N*m, a back-driven efficiency of 5, no winding resistance, a negative friction
    simulated with exit 0 and "settled", and zeros divided by): the winding, the motor's speed, torque and
    inertia positive; friction, damping and backlash not negative; the static friction at least the Coulomb
    friction and below the motor's stall torque at the output (else the hinge could never start); the
    back-driven efficiency in (0, 1]; the cogging a share below 1. hinge_rows: the calibration's per-hinge
    values (`_calibration`), each scaling the spec's own value, which must then be positive."""
    checks = [("resistance", spec.resistance > 0, "> 0 ohm"), ("no_load_speed", spec.no_load_speed > 0, "> 0"),
              ("stall_torque", spec.stall_torque > 0, "> 0 N*m"), ("rotor_inertia", spec.rotor_inertia > 0, "> 0"),
              ("gear_ratio", spec.gear_ratio >= 1, ">= 1"), ("gear_friction", spec.gear_friction >= 0, ">= 0"),
              ("gear_stiction", spec.gear_friction <= spec.gear_stiction < spec.stall_torque,
               f"from gear_friction ({spec.gear_friction:g} N*m) to below the stall torque ({spec.stall_torque:g} N*m)"),
              ("gear_damping", spec.gear_damping >= 0, ">= 0"), ("backlash", spec.backlash >= 0, ">= 0"),
              ("backdrive_efficiency", 0 < spec.backdrive_efficiency <= 1, "in (0, 1]"),
              ("cogging", 0 <= spec.cogging < 1, "in [0, 1)")]
    for field, ok, wanted in checks:
        if not ok:
            raise ValueError(f"{where}: {field} = {getattr(spec, field):g} (SI) is not a gearmotor's: it must be {wanted}")
    for k, row in enumerate(hinge_rows or []):
        for p in row:
            if not getattr(spec, p) > 0:
                raise ValueError(f"{where}: {p} = {getattr(spec, p):g}, but hinge {k} has its own value of it, a "
                                 "scale of the spec's: it must be > 0")


def _calibration(doc, where: str, n_hinges: int) -> Calibration:
    """profile.json's "calibration", checked, as the record; ValueError naming the key."""
    if not isinstance(doc, dict):
        raise ValueError(f"{where}: expected an object with runs, parameters")
    known_keys(doc, ("runs", "parameters", "hinges"), where)
    required_keys(doc, ("runs", "parameters"), where)
    if not isinstance(doc["runs"], list) or not all(isinstance(r, str) for r in doc["runs"]):
        raise ValueError(f"{where}: runs: expected a list of run folders")
    _parameters(doc["parameters"], f"{where}: parameters")
    if "hinges" in doc:
        if not isinstance(doc["hinges"], list) or len(doc["hinges"]) != n_hinges:
            raise ValueError(f"{where}: hinges: expected a list of {n_hinges} objects, one per hinge")
        for k, row in enumerate(doc["hinges"]):
            _parameters(row, f"{where}: hinges[{k}]")
    estimates = (lambda row: {p: Estimate(**e) for p, e in row.items()})
    return Calibration(list(doc["runs"]), estimates(doc["parameters"]),
                       [estimates(row) for row in doc["hinges"]] if "hinges" in doc else None)


def _holding(doc, where: str) -> Holding:
    """profile.json's "holding", checked, as the record; ValueError naming the key."""
    if not isinstance(doc, dict):
        raise ValueError(f"{where}: expected an object with port, releases, parameters")
    known_keys(doc, ("port", "releases", "parameters"), where)
    required_keys(doc, ("port", "releases", "parameters"), where)
    _parameters(doc["parameters"], f"{where}: parameters")
    return Holding(doc["port"], doc["releases"], {p: Estimate(**e) for p, e in doc["parameters"].items()})


def _parameters(doc, where: str) -> None:
    """ValueError unless doc is {plant parameter: estimate} with low <= value <= high, all positive."""
    if not isinstance(doc, dict):
        raise ValueError(f"{where}: expected an object {{name: {{...}}}}")
    for p, e in doc.items():
        w = f"{where}: {p}"
        if p not in PLANT_FIELDS:
            raise ValueError(f"{w}: not a plant parameter ({', '.join(PLANT_FIELDS)})")
        if not isinstance(e, dict):
            raise ValueError(f"{w}: expected an object with {', '.join(PARAMETER_KEYS)}")
        known_keys(e, PARAMETER_KEYS + RUNS_KEYS, w)
        required_keys(e, PARAMETER_KEYS, w)
        lo, v, hi, prior = (number(e[k], f"{w}: {k}") for k in ("low", "value", "high", "prior"))
        if not 0 < lo <= v <= hi or prior <= 0:
            raise ValueError(f"{w}: value {v:g} is not within low {lo:g} .. high {hi:g}, or not positive")
        if any(k in e for k in RUNS_KEYS):
            required_keys(e, RUNS_KEYS, w)
            runs_lo, runs_hi = (number(e[k], f"{w}: {k}") for k in RUNS_KEYS)
            if not (0 < runs_lo <= v * (1 + 1e-9) and v <= runs_hi * (1 + 1e-9)):
                raise ValueError(f"{w}: value {v:g} is not within runs_low {runs_lo:g} .. runs_high {runs_hi:g}, "
                                 f"or not positive")
        if not isinstance(e["identifiable"], bool):
            raise ValueError(f"{w}: identifiable: expected true or false")


def design_unchanged(spec: DeviceSpec, base: DeviceSpec, where) -> None:
    """ValueError naming the first field a profile's spec changes that is not a plant parameter
    (twin.device.variation.PLANT_FIELDS): the host's checks (the gate's hinge range, the settle band, the flap
    count) are the spec's, whatever a profile says."""
    for f in dataclasses.fields(base):
        mine, theirs = getattr(spec, f.name), getattr(base, f.name)
        if f.name in PLANT_FIELDS or mine == theirs:
            continue
        if isinstance(mine, float) and isinstance(theirs, float) and math.isclose(mine, theirs, rel_tol=1e-9):
            continue
        raise ValueError(f"{where}: {f.name} = {mine!r} is not the spec's {theirs!r}: a profile holds only the "
                         f"plant parameters calibration and holding fit ({', '.join(PLANT_FIELDS)}); the rest is the "
                         "device's design (models/vrscroll/spec.toml)")


def read_profile(folder) -> Profile:
    """The profile in folder; ValueError naming the file and key for anything missing or wrong."""
    folder = Path(folder)
    if not folder.is_dir():
        raise ValueError(f"{folder}: no such device profile")
    meta_path = folder / META
    if not meta_path.is_file():
        raise ValueError(f"{folder}: not a device profile (no {META})")
    meta = json_object(meta_path)
    if meta.get("format") != PROFILE_FORMAT:
        raise ValueError(f"{meta_path}: not a {PROFILE_FORMAT} profile (no \"format\": \"{PROFILE_FORMAT}\")")
    known_keys(meta, ("format", "name") + META_PARTS, str(meta_path))
    if meta.get("name") != folder.name:
        raise ValueError(f"{meta_path}: name {meta.get('name')!r} is not the folder's, {folder.name!r}")
    calibration = _calibration(meta["calibration"], f"{meta_path}: calibration", load_spec().n_hinges) if "calibration" in meta else None
    holding = _holding(meta["holding"], f"{meta_path}: holding") if "holding" in meta else None
    mount = check_mount(meta.get("mount", DEFAULT_MOUNT), f"{meta_path}: mount")
    if not (folder / SPEC).is_file():
        raise ValueError(f"{folder}: device profile without its {SPEC}")
    spec = load_spec(folder / SPEC, defaults=load_spec())  # (one written before an entry was added: the spec's)
    design_unchanged(spec, load_spec(), folder / SPEC)
    plant_is_physical(spec, folder / SPEC, calibration.hinges if calibration else None)
    if (folder / GAINS).is_file():
        gains, source = read_gains(folder / GAINS, spec.n_hinges).hinges, str(folder / GAINS)
    else:
        gains, source = [PidGains.from_spec(spec)] * spec.n_hinges, "spec"
    return Profile(folder.name, folder, spec, spec_sources(folder / SPEC, defaults=load_spec()), gains, source, mount,
                   calibration, hinge_plants(spec, calibration), holding)


def _calibration_json(c: Calibration) -> dict:
    return {"runs": list(c.runs), "parameters": {p: e.to_json() for p, e in c.parameters.items()},
            **({"hinges": [{p: e.to_json() for p, e in row.items()} for row in c.hinges]} if c.hinges else {})}


def _write_meta(folder: Path, doc: dict) -> None:
    """profile.json: its format and name, and `doc`'s parts (mount, calibration, holding), each checked as
    read_profile checks it."""
    doc = {"format": PROFILE_FORMAT, "name": folder.name, **doc}
    if "calibration" in doc:
        _calibration(doc["calibration"], str(folder / META), load_spec().n_hinges)
    if "holding" in doc:
        _holding(doc["holding"], str(folder / META))
    if "mount" in doc:
        check_mount(doc["mount"], f"{folder / META}: mount")
    with replacing(folder / META) as tmp:
        tmp.write_text(json.dumps(doc, indent=2) + "\n")


def write_profile(profile: Profile, by: str = "vrscroll calibrate") -> Path:
    """Write the profile record whole into the folder of profile.name (made where it is not there): its
    spec.toml gets each plant value whose value or source (profile.sources) is not the file's (the spec's for a
    new profile), every other entry kept as written; profile.json its mount, calibration and holding. The gains
    are tune's, with what they were tuned for (write_profile_gains). by: the command writing it, said in the
    spec.toml's header. Returns the folder."""
    folder = profile_dir(profile.name)
    folder.mkdir(parents=True, exist_ok=True)
    template = folder / SPEC if (folder / SPEC).is_file() else SPEC_PATH
    was, was_from = load_spec(template, defaults=load_spec()), spec_sources(template, defaults=load_spec())
    values = {f: getattr(profile.spec, f) for f in PLANT_FIELDS
              if getattr(profile.spec, f) != getattr(was, f) or profile.sources.get(f) != was_from.get(f)}
    if values or template == SPEC_PATH:
        with replacing(folder / SPEC) as spec_tmp:
            write_spec_toml(spec_tmp, template, values, {f: profile.sources[f] for f in values},
                            header=f"Device profile {profile.name}: the spec of this device, written by `{by}` "
                                   "(docs/tuning-hil-calibration.md).")
            load_spec(spec_tmp, defaults=load_spec())  # what was written reads back, or nothing is replaced
    holding = profile.holding
    _write_meta(folder, {"mount": profile.mount,
                         **({"calibration": _calibration_json(profile.calibration)} if profile.calibration else {}),
                         **({"holding": {"port": holding.port, "releases": holding.releases, "parameters": {
                             p: e.to_json() for p, e in holding.parameters.items()}}} if holding else {})})
    return folder


def write_profile_gains(name: str, gains: Gains) -> Path:
    """Store the gains record as the profile's gains.json (the profile must exist). Returns the file."""
    folder = profile_dir(name)
    if not (folder / META).is_file():
        raise ValueError(f"device profile {name!r} is not in {profiles_dir()}: calibrate first "
                         f"(`vrscroll calibrate RUN --device {name}`) or `vrscroll device create {name}`")
    write_gains(folder / GAINS, gains)
    return folder / GAINS


def write_profile_wiring(name: str, wiring, checks: list[str]) -> Path:
    """Keep a copy of the wiring correction the device holds (`vrscroll bringup`; wiring: its encoder, flags and
    bridge per hinge) as the profile's wiring.json: per hinge the encoder input it reads, its WIRING_* flags and the
    H-bridge its motor is on, with what bring-up found. Returns the file."""
    folder = profile_dir(name)
    if not (folder / META).is_file():
        raise ValueError(f"device profile {name!r} is not in {profiles_dir()}: `vrscroll device create {name}`")
    doc = {"encoder": [int(e) for e in wiring.encoder], "flags": [int(f) for f in wiring.flags],
           "bridge": [int(b) for b in wiring.bridge], "found": list(checks)}
    with replacing(folder / WIRING) as tmp:
        tmp.write_text(json.dumps(doc, indent=2) + "\n")
    return folder / WIRING


def create_profile(name: str, mount: str | None = None) -> Path:
    """A new profile holding the spec's defaults (its spec.toml a copy of the spec's), held as `mount` (None:
    not said, hanging). ValueError if it exists."""
    folder = profile_dir(name)
    if folder.exists():
        raise ValueError(f"{folder}: a device profile {name!r} exists already")
    if mount is not None:
        check_mount(mount)
    folder.mkdir(parents=True)
    (folder / SPEC).write_text(Path(SPEC_PATH).read_text())
    _write_meta(folder, {"mount": mount} if mount else {})
    return folder


def select_profile(name: str | None = None) -> Profile:
    """The profile called name, or the selected one (twin.device.profile.default_name), or the spec's defaults.

    ValueError (one line) for a profile that is not there or is damaged, naming it and where it was looked for.
    """
    chosen = name or default_name()
    if chosen is None:
        return spec_defaults()
    folder = profile_dir(chosen)
    if not folder.is_dir():
        how = "given with --device" if name else f"selected in {profiles_dir() / 'default'}"
        raise ValueError(f"device profile {chosen!r} ({how}) is not in {profiles_dir()}: `vrscroll device list` "
                         f"shows those there are; `vrscroll calibrate RUN --device {chosen}` makes one")
    return read_profile(folder)


def profile_or_new(name: str | None) -> tuple[Profile, bool]:
    """(the profile called name, or the selected one (select_profile), False), or for a name not there yet (a
    profile a command makes) (the spec's defaults, True)."""
    if name and not profile_dir(name).is_dir():
        return spec_defaults(), True
    return select_profile(name), False


def chosen_profile(name: str | None, mount: str | None = None) -> Profile:
    """What a command opens (`--device NAME`, `--mount M`): the profile called name (then remembered as the
    default), or the selected one, or the spec's defaults; held as `mount` where given (recorded in the profile,
    when there is one). ValueError (one line) for a profile that is not there or is damaged."""
    profile = select_profile(name)
    if name:
        set_default(name)
    if mount and mount != profile.mount:
        profile = updated(profile, mount=mount)
        if profile.name:
            write_profile(profile)
    return profile


def profile_line(profile: Profile) -> str:
    """The line every report starts with."""
    where = f" ({profile.folder})" if profile.folder else " (models/vrscroll/spec.toml)"
    return f"device profile: {profile.label}{where}; mount: {profile.mount}"


def profile_lines(profile: Profile) -> list[str]:
    """A profile in words (`vrscroll device show`): its folder, mount, gains, calibration (each value in the spec
    file's unit), holding, the spec values not the spec's defaults, and the hinges."""
    lines = []
    say = lines.append
    say(f"device profile: {profile.label}" + (f" ({profile.folder})" if profile.folder else ""))
    say(f"mount: {profile.mount}")
    say(f"gains: {profile.gains_from}")
    for k, g in enumerate(profile.gains):
        say(f"  hinge {k}: kp {g.kp:g} ki {g.ki:g} kd {g.kd:g}")
    sources = profile.sources
    units = spec_units(SPEC_PATH)  # each value in the unit the spec file gives it in
    if profile.calibration:
        say("calibration from " + ", ".join(profile.calibration.runs) + ":")
        for p, e in profile.calibration.parameters.items():
            u = units.get(p, "")
            say(f"  {p:<14} {shown(e.value, u, '.6g')}  (prior {shown(e.prior, u, '.6g')}; interval "
                f"{shown_range(e.low, e.high, u, '.6g')}; "
                f"{'identifiable' if e.identifiable else 'NOT identifiable'}): {e.note}")
        for k, row in enumerate(profile.calibration.hinges or []):
            say(f"  hinge {k}'s own, x the shared value (95 % interval): " + "; ".join(
                f"{p} x{e.value / e.prior:.3f} (x{e.low / e.prior:.2f} .. x{e.high / e.prior:.2f}"
                f"{', identifiable' if e.identifiable else ''})" for p, e in row.items()))
    else:
        say("not calibrated")
    for p, e in (profile.holding.parameters if profile.holding else {}).items():
        u = units.get(p, "")
        say(f"holding (vrscroll holding, {profile.holding.releases} release(s) on {profile.holding.port}): "
            f"{p} {shown(e.value, u, '.3g')} (prior {shown(e.prior, u, '.3g')}; interval "
            f"{shown_range(e.low, e.high, u, '.3g')}; {'identifiable' if e.identifiable else 'NOT identifiable'})")
    defaults = spec_sources()
    changed = [f for f, s in sources.items() if s != defaults.get(f)]
    say("spec values not the spec's defaults: " + (", ".join(
        f"{f} = {shown(getattr(profile.spec, f), units.get(f, ''), '.6g')} ({sources[f]})" for f in changed)
        if changed else "none"))
    say(f"hinge limit {math.degrees(profile.spec.hinge_limit):g} deg, {profile.spec.n_hinges} hinges")
    return lines
