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
the profile (twin.commands.options.profile_twin) gives each hinge its own.
"mount" (written by `--mount` with `--device`, or `vrscroll device create NAME --mount M`): how the device is
held, one of twin.device.mount.MOUNTS ("hanging", "flat", "stand"); a profile without it (older ones) hangs.
"holding" (written by `vrscroll holding --device`): {"port", "releases": count, "parameters":
{"backdrive_efficiency": {...}}}, the value also in spec.toml (twin.hil.holding).
Where the folders live is twin.device.profile's; which one a command uses, twin.commands.options'.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

from controllers.pid import PidGains
from twin.checks import json_object, known_keys, number, required_keys
from twin.device.mount import DEFAULT_MOUNT, MOUNTS, check_mount
from twin.device.profile import NO_PROFILE, profile_dir, profiles_dir
from twin.device.spec import SPEC_PATH, DeviceSpec, load_spec, spec_sources
from twin.device.spec_toml import write_spec_toml
from twin.device.variation import PLANT_FIELDS, scaled
from twin.formats.gains import read_gains, write_gains
from twin.paths import replacing
from twin.records.calibration import Calibration, Estimate

PROFILE_FORMAT = "vrscroll-profile/1"
META, SPEC, GAINS, WIRING = "profile.json", "spec.toml", "gains.json", "wiring.json"
PARAMETER_KEYS = ("value", "prior", "low", "high", "identifiable", "note")
RUNS_KEYS = ("runs_low", "runs_high")  # optional (a calibration before they were kept has neither): what tuning covers
META_PARTS = ("mount", "calibration", "holding")  # what profile.json holds beside its format and name


@dataclasses.dataclass
class Profile:
    """The device the commands simulate, gate and talk to: a profile, or the spec's defaults (name None)."""

    name: str | None
    folder: Path | None
    spec: DeviceSpec
    gains: list[PidGains]  # per hinge
    gains_from: str  # where the gains came from: the profile's gains.json or the spec
    calibration: Calibration | None  # profile.json's "calibration", if the profile was calibrated
    holding: dict | None = None  # profile.json's "holding", if a release was measured (`vrscroll holding`)
    mount: str = DEFAULT_MOUNT  # how the device is held (twin.device.mount.MOUNTS): the twin is held so too

    @property
    def label(self) -> str:
        """How every report names it: the profile's name, or "spec defaults"."""
        return self.name or NO_PROFILE

    def ranges(self) -> dict:
        """parameter -> (low, high) SI, what tuning covers: the twin's values that reproduce the calibration's
        runs (runs_low .. runs_high; low .. high where the calibration kept no such interval) ({} when not
        calibrated)."""
        if not self.calibration:
            return {}
        return {p: e.runs_range for p, e in self.calibration.parameters.items()}

    def hinge_ranges(self) -> list[dict] | None:
        """Per hinge, parameter -> (low, high) SI, as `ranges` for its own values (None where calibration
        fitted none)."""
        rows = self.calibration.hinges if self.calibration else None
        return [{p: e.runs_range for p, e in row.items()} for row in rows] if rows else None

    @property
    def hinges(self) -> list[DeviceSpec] | None:
        """Each hinge's own spec where calibration fitted per-hinge values (None where it did not): the
        profile's spec with that hinge's values, the fields that move with one moved alike."""
        rows = self.calibration.hinges if self.calibration else None
        if not rows:
            return None
        return [scaled(self.spec, {p: e.value / getattr(self.spec, p) for p, e in row.items()}) for row in rows]


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


def _holding(doc, where: str) -> dict:
    if not isinstance(doc, dict):
        raise ValueError(f"{where}: expected an object with port, releases, parameters")
    known_keys(doc, ("port", "releases", "parameters"), where)
    required_keys(doc, ("port", "releases", "parameters"), where)
    _parameters(doc["parameters"], f"{where}: parameters")
    return doc


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
        gains, source = read_gains(folder / GAINS, spec.n_hinges), str(folder / GAINS)
    else:
        gains, source = [PidGains.from_spec(spec)] * spec.n_hinges, "spec"
    return Profile(folder.name, folder, spec, gains, source, calibration, holding, mount)


def _write_meta(folder: Path, **parts) -> None:
    """profile.json with `parts` (calibration, holding: a dict, or None to drop it) in place of those it held,
    the others kept."""
    doc = {"format": PROFILE_FORMAT, "name": folder.name}
    if (folder / META).is_file():
        doc |= {k: v for k, v in json_object(folder / META).items() if k in META_PARTS}
    doc |= parts
    doc = {k: v for k, v in doc.items() if v is not None}
    if doc.get("calibration"):
        _calibration(doc["calibration"], str(folder / META), load_spec().n_hinges)
    if doc.get("holding"):
        _holding(doc["holding"], str(folder / META))
    if "mount" in doc:
        check_mount(doc["mount"], f"{folder / META}: mount")
    with replacing(folder / META) as tmp:
        tmp.write_text(json.dumps(doc, indent=2) + "\n")


def write_profile_spec(name: str, values: dict, source: str, by: str = "vrscroll calibrate", **parts) -> Path:
    """Create or update the profile called name: its spec.toml gets `values` (field -> SI) with `source`
    (every other value as it was: the profile's own spec, or the spec's defaults for a new profile), and
    profile.json `parts` (calibration, holding: each replaced, the others kept). by: the command writing it.
    Returns the folder."""
    folder = profile_dir(name)
    folder.mkdir(parents=True, exist_ok=True)
    template = folder / SPEC if (folder / SPEC).is_file() else SPEC_PATH
    with replacing(folder / SPEC) as spec_tmp:
        write_spec_toml(spec_tmp, template, values, source,
                        header=f"Device profile {name}: the spec of this device, written by `{by}` "
                               "(docs/tuning-hil-calibration.md).")
        load_spec(spec_tmp, defaults=load_spec())  # what was written reads back, or nothing is replaced
    _write_meta(folder, **parts)
    return folder


def write_profile_gains(name: str, gains: list[PidGains], meta: dict | None = None) -> Path:
    """Store gains as the profile's gains.json (the profile must exist). Returns the file."""
    folder = profile_dir(name)
    if not (folder / META).is_file():
        raise ValueError(f"device profile {name!r} is not in {profiles_dir()}: calibrate first "
                         f"(`vrscroll calibrate RUN --device {name}`) or `vrscroll device create {name}`")
    write_gains(folder / GAINS, gains, meta)
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
    _write_meta(folder, mount=mount)
    return folder


def write_profile_mount(name: str, mount: str) -> Path:
    """Record how the device of the profile called name is held (one of MOUNTS; the profile must exist).
    Returns its profile.json."""
    folder = profile_dir(name)
    if not (folder / META).is_file():
        raise ValueError(f"device profile {name!r} is not in {profiles_dir()}: `vrscroll device create {name}`")
    _write_meta(folder, mount=check_mount(mount))
    return folder / META


def spec_source_of(profile: Profile) -> dict:
    """field -> where its value came from, for the profile's spec."""
    return spec_sources(profile.folder / SPEC, defaults=load_spec()) if profile.folder else spec_sources()
