"""The device's MJCF, generated from the spec, and loading it into MuJoCo.

`mjcf(spec)` writes the XML that is committed as models/vrscroll/vrscroll.xml (the device
alone), `scene_mjcf()` the scene.xml beside it that includes it and adds a floor, a light and a
camera, as MuJoCo Menagerie lays out its models (`vrscroll model --write` regenerates both);
every number comes from the spec, and a test proves the committed files are what it generates.
"""

from __future__ import annotations

import math

import mujoco

from twin.device.kinematics import hinge_axis_sign
from twin.device.mount import DEFAULT_MOUNT, check_mount, table_height
from twin.device.spec import DeviceSpec, load_spec
from twin.paths import MODELS_DIR

ROTOR_MASS = 1e-9  # kg: a body with a joint needs some; negligible beside the device's 0.228 kg
ROTOR_INERTIA = 1e-12  # kg*m^2: negligible beside the reflected rotor inertia (armature, ~1e-4)
# The dead zone's ends are hard stops: the shortest time
# constant MuJoCo integrates stably (two 1 ms steps) and an impedance near 1, so a flap loaded by its
# weight presses ~0.005 deg into its stop (0.1 deg with MuJoCo's defaults 0.02 s, 0.9-0.95)
BACKLASH_SOLREF = (0.002, 1.0)
BACKLASH_SOLIMP = (0.999, 0.999, 0.001)
MJCF_PATH = MODELS_DIR / "vrscroll" / "vrscroll.xml"  # the device alone
SCENE_PATH = MODELS_DIR / "vrscroll" / "scene.xml"  # includes the device, adds floor, light and camera


def _f(*values: float) -> str:
    return " ".join(f"{v:.9g}" for v in values)


def _flap_body(spec: DeviceSpec, i: int, indent: str, children: str, root: str) -> str:
    """One flap's <body>; its frame sits on its inner hinge (the root flap's on the anchor)."""
    p, t, d = spec.flap_pitch, spec.thickness, spec.depth
    r = spec.root_flap
    side = 0 if i == r else (1 if i > r else -1)  # which way the flap extends from its frame
    cx = side * p / 2  # touch-surface centre, in the body frame
    half = (p - spec.flap_gap) / 2
    lines = []
    if i == r:
        lines.append(f'{indent}<body name="flap{i}" childclass="vrscroll" pos="0 0 0">')
        if root == "free":
            lines.append(f'{indent}  <freejoint name="root"/>')
        # battery and electronics ride on the root flap (spec [mass] electronics)
        lines.append(
            f'{indent}  <geom name="electronics" class="electronics" pos="{_f(0, 0, -t - 0.004)}"'
            f' size="{_f(half * 0.9, spec.usable_depth / 2 * 0.6, 0.004)}" mass="{_f(spec.mass_electronics)}"/>'
        )
        if has_backlash(spec):
            lines += _rotor_bodies(spec, indent + "  ")
    else:
        hinge = i - 1 if i > r else i
        parent_x = (spec.flap_pitch / 2) * (1 if i > r else -1) if abs(i - r) == 1 else side * p
        lines.append(f'{indent}<body name="flap{i}" pos="{_f(parent_x, 0, 0)}">')
        lines.append(
            f'{indent}  <joint name="hinge{hinge}" class="hinge" axis="{_f(0, hinge_axis_sign(spec)[hinge], 0)}"/>'
        )
    lines += [
        f'{indent}  <geom name="flap{i}_visual" class="flap_visual" pos="{_f(cx, 0, -t / 2)}" size="{_f(half, d / 2, t / 2)}"/>',
        f'{indent}  <geom name="flap{i}_collision" class="flap_collision" pos="{_f(cx, 0, -t / 2)}"'
        f' size="{_f(half, d / 2, t / 2)}" mass="{_f(spec.flap_mass)}"/>',
        f'{indent}  <site name="surface{i}" class="surface" pos="{_f(cx, 0, 0)}"/>',
    ]
    # the motor of each hinge on this flap's outer side is carried by this (inner) flap
    for hinge, outer in _hinges_from(spec, i):
        hx = cx + (p / 2 if outer > i else -p / 2)
        lines.append(
            f'{indent}  <geom name="motor{hinge}_housing" class="motor"'
            f' pos="{_f(hx, d / 2 - spec.motor_length / 2, -t - spec.motor_diameter / 2)}"/>'
        )
    if children:
        lines.append(children)
    lines.append(f"{indent}</body>")
    return "\n".join(lines)


def _rotor_bodies(spec: DeviceSpec, indent: str) -> list[str]:
    """One body per hinge whose joint gear{k} is the gearbox output's angle (relative to the hinge's inner flap,
    as the backlash tendon compares it with the flap's hinge{k}); it carries the motor, its encoder and its
    friction. Its place in space means nothing: it has no geometry, and its own inertia is negligible (the
    rotor's, reflected by N^2, is the actuator's armature)."""
    sign = hinge_axis_sign(spec)
    return [f'{indent}<body name="rotor{k}"><joint name="gear{k}" class="gear" axis="{_f(0, sign[k], 0)}"/>'
            f'<inertial pos="0 0 0" mass="{_f(ROTOR_MASS)}" diaginertia="{_f(*[ROTOR_INERTIA] * 3)}"/></body>'
            for k in range(spec.n_hinges)]


def _backlash(spec: DeviceSpec) -> str:
    """The dead zone between gear{k} and hinge{k}: a fixed tendon hinge - gear limited to +-backlash/2, a
    constraint only at its ends. Without backlash there is no gear joint (the motor turns the flap's)."""
    if not has_backlash(spec):
        return "  <!-- no backlash (spec [motor] backlash = 0): the motors turn the hinges directly -->"
    half = math.degrees(spec.backlash) / 2
    rows = "\n".join(f'    <fixed name="backlash{k}" class="backlash"><joint joint="hinge{k}" coef="1"/>'
                     f'<joint joint="gear{k}" coef="-1"/></fixed>' for k in range(spec.n_hinges))
    return (f"  <!-- backlash: the flap moves +-{half:.9g} deg about its gearbox output (spec [motor] backlash) -->\n"
            f"  <tendon>\n{rows}\n  </tendon>")


def has_backlash(spec: DeviceSpec) -> bool:
    """Whether the model has a gearbox output joint per hinge (gear{k}) beside the flap's (hinge{k})."""
    return spec.backlash > 0


def motor_joint(spec: DeviceSpec, k: int) -> str:
    """The joint hinge k's motor turns: its gearbox output, or the flap's own where there is no backlash."""
    return f"gear{k}" if has_backlash(spec) else f"hinge{k}"


def _hinges_from(spec: DeviceSpec, i: int):
    """Hinges whose inner flap is flap i, as (hinge, outer flap)."""
    r = spec.root_flap
    out = []
    if i >= r and i + 1 < spec.n_flaps:
        out.append((i, i + 1))
    if i <= r and i - 1 >= 0:
        out.append((i - 1, i - 1))
    return out


def _chain(spec: DeviceSpec, flaps: list[int], depth: int, root: str) -> str:
    if not flaps:
        return ""
    i, rest = flaps[0], flaps[1:]
    return _flap_body(spec, i, "  " * depth, _chain(spec, rest, depth + 1, root), root)


def motor_attributes(s: DeviceSpec) -> str:
    """The dcmotor attributes a spec gives a gearmotor (the device's default class; or one hinge's own, where
    its motor differs): K, R, rotor armature, viscous damping, LuGre friction and cogging, written motor side."""
    N = s.gear_ratio
    lugre = _f(s.friction_stiffness / N**2, s.friction_damping / N**2, s.gear_friction / N, s.gear_stiction / N,
               s.stribeck_speed * N)
    return (f'motorconst="{_f(s.motor_constant)}" resistance="{_f(s.drive_resistance)}"\n'
            f'        armature="{_f(s.rotor_inertia)}" damping="{_f(s.gear_damping / N**2)}"\n'
            f'        lugre="{lugre}" cogging="{_f(s.cogging_torque, s.cogging_periods, s.cogging_phase)}"')


def mjcf(spec: DeviceSpec | None = None, root: str = "fixed", motors: list[str] | None = None) -> str:
    """MJCF text of the device. root: 'fixed' (held in the world) or 'free' (a freejoint). motors: per hinge,
    dcmotor attributes of its own (e.g. `motor_attributes` of that hinge's spec: the emulator's plant, whose
    hinges differ); None: every hinge the default class's."""
    if root not in ("fixed", "free"):
        raise ValueError(f"root must be 'fixed' or 'free', not {root!r}")
    s = spec or load_spec()
    r = s.root_flap
    lim = math.degrees(s.hinge_limit)
    left = _chain(s, list(range(r - 1, -1, -1)), 3, root)
    right = _chain(s, list(range(r + 1, s.n_flaps)), 3, root)
    root_body = _flap_body(s, r, "    ", "\n".join(c for c in (left, right) if c), root)
    hinges = range(s.n_hinges)
    extra = [""] * s.n_hinges if motors is None else [" " + m for m in motors]
    actuators = "\n".join(f'    <dcmotor name="motor{k}" class="gearmotor" joint="{motor_joint(s, k)}"{extra[k]}/>'
                          for k in hinges)
    sensors = "\n".join(
        f'    <actuatorpos name="encoder{k}" actuator="motor{k}"/>\n'
        f'    <jointpos name="angle{k}" joint="hinge{k}"/>\n'
        f'    <jointvel name="speed{k}" joint="hinge{k}"/>\n'
        f'    <jointactuatorfrc name="torque{k}" joint="{motor_joint(s, k)}"/>'
        for k in hinges
    )
    excludes = "\n".join(f'    <exclude body1="flap{i}" body2="flap{i + 1}"/>' for i in range(s.n_flaps - 1))
    flat_qpos = ([0, 0, 0, 1, 0, 0, 0] if root == "free" else []) + [0] * (s.n_hinges * (2 if has_backlash(s) else 1))
    N = s.gear_ratio
    return f"""<!-- VRScroll: {s.n_flaps} hinged flaps turned by DC gearmotors (generated by twin/device/mjcf.py
     from models/vrscroll/spec.toml; regenerate with `vrscroll model --write`, do not edit).

     Frame: x along the row of flaps, y along the hinge axes, z the touch-surface normal;
     the origin (anchor) is the centre of the root flap's touch surface. Hinge k joins
     flap k and flap k+1 on the touch surface; positive angle bends the touch surface
     concave. Units: SI. Root: {root}. -->
<mujoco model="vrscroll">
  <compiler angle="degree" autolimits="true"/>

  <!-- one physics step per firmware tick (spec [simulation] timestep). The constraint solver (Newton) starts
       from the unconstrained acceleration, not the last step's, and solves the device as one: its few rows
       (a backlash stop per hinge, and contacts only where flaps meet) converge in a few iterations either way,
       and warm starts and constraint islands cost more than they save (measured: benchmarks/bench_twin.py) -->
  <option timestep="{_f(s.timestep)}" integrator="implicitfast">
    <flag warmstart="disable" island="disable"/>
  </option>

  <default>
    <default class="vrscroll">
      <!-- the flaps' hinges: range from spec [geometry] hinge_limit; their friction is the gearbox's,
           on the gear joints -->
      <joint type="hinge" range="{_f(-lim, lim)}"/>
      <default class="hinge"/>
      <default class="gear">
        <joint limited="false"/>
      </default>
      <default class="backlash">
        <!-- range in rad (MuJoCo does not convert tendon lengths): spec [motor] backlash / 2 -->
        <tendon limited="true" range="{_f(-s.backlash / 2, s.backlash / 2)}" solreflimit="{_f(*BACKLASH_SOLREF)}"
          solimplimit="{_f(*BACKLASH_SOLIMP)}"/>
      </default>
      <!-- {_f(s.rated_voltage)} V micro metal gearmotor, {_f(N)}:1 (spec [motor]) on the gearbox output joint gearK.
           K from the datasheet's no-load point; R is the winding's and the driver's FETs' (spec
           [power] driver_on_resistance); armature is the rotor, reflected by gear^2. Input: the
           voltage behind R, set each tick by the drive model (twin/sim/drive.py: pack, PWM, decay,
           current limit); the gearbox's efficiency is applied there too. Friction at the output
           (spec [motor] gear_stiction, gear_friction, stribeck_speed, friction_stiffness,
           friction_damping; gear_damping), written motor side: torque / N, speed * N, stiffness / N^2. -->
      <dcmotor gear="{_f(N)}" {motor_attributes(s)}/>
      <default class="gearmotor"/>
      <default class="flap_visual">
        <geom type="box" group="2" contype="0" conaffinity="0" density="0" material="flap"/>
      </default>
      <!-- flap-on-flap contacts between flaps two or more apart (neighbours are excluded below) -->
      <default class="flap_collision">
        <geom type="box" group="3" friction="0.6 0.005 0.0001" material="collision"/>
      </default>
      <default class="motor">
        <geom type="cylinder" size="{_f(s.motor_diameter / 2, s.motor_length / 2)}" euler="90 0 0" group="2" contype="0" conaffinity="0"
          mass="{_f(s.mass_motor)}" material="motor"/>
      </default>
      <default class="electronics">
        <geom type="box" group="2" contype="0" conaffinity="0" material="electronics"/>
      </default>
      <default class="surface">
        <site type="sphere" size="0.002" group="4" rgba="1 0.3 0.3 1"/>
      </default>
    </default>
  </default>

  <asset>
    <material name="flap" rgba="0.85 0.85 0.82 1"/>
    <material name="collision" rgba="0.3 0.5 0.9 0.4"/>
    <material name="motor" rgba="0.6 0.6 0.65 1"/>
    <material name="electronics" rgba="0.15 0.35 0.2 1"/>
  </asset>

  <worldbody>
{root_body}
  </worldbody>

{_backlash(s)}

  <!-- neighbours meet at their hinge and never collide; MuJoCo's parent filter alone
       misses the root's children, since the root is welded to the world -->
  <contact>
{excludes}
  </contact>

  <actuator>
{actuators}
  </actuator>

  <!-- encoderK: the motor shaft angle (rad); the firmware quantizes it to
       spec [encoder] counts_per_motor_rev counts per turn -->
  <sensor>
{sensors}
  </sensor>

  <keyframe>
    <key name="flat" qpos="{_f(*flat_qpos)}"/>
  </keyframe>
</mujoco>
"""


def load_model(spec: DeviceSpec | None = None, root: str = "fixed", mount: str = DEFAULT_MOUNT,
               motors: list[str] | None = None) -> mujoco.MjModel:
    """Compile the device model from a spec (the default spec if None), held as `mount` (twin.device.mount.MOUNTS):
    'flat' adds a table just under the flat device, which the flaps rest on and cannot fold through; 'stand' turns
    gravity along the hinges' axes (the device's y). motors: as `mjcf`'s."""
    check_mount(mount)
    s = spec or load_spec()
    text = mjcf(s, root, motors)
    if mount == "flat":
        text = text.replace("  <worldbody>\n", '  <worldbody>\n    <geom name="table" type="plane" size="0.5 0.5 0.01" '
                                             f'pos="0 0 {table_height(s)!r}" material="collision"/>\n', 1)
    model = mujoco.MjModel.from_xml_string(text)
    if mount == "stand":
        g = float(abs(model.opt.gravity[2]))
        model.opt.gravity[:] = (0.0, -g, 0.0)
    return model


def scene_mjcf() -> str:
    """MJCF text of the scene: the device (vrscroll.xml, included) with a floor, a light and a camera,
    as MuJoCo Menagerie lays out a model. The floor does not collide: it is for the eye."""
    return f"""<!-- VRScroll in a scene: the device (vrscroll.xml) with a floor, a light and a camera, for
     MuJoCo's viewer (generated by twin/device/mjcf.py; regenerate with `vrscroll model --write`). -->
<mujoco model="vrscroll scene">
  <include file="{MJCF_PATH.name}"/>

  <statistic center="0 0 -0.05" extent="0.35"/>

  <asset>
    <texture name="grid" type="2d" builtin="checker" rgb1="0.2 0.3 0.4" rgb2="0.1 0.2 0.3" width="300" height="300"/>
    <material name="grid" texture="grid" texrepeat="8 8" reflectance="0.1"/>
  </asset>

  <worldbody>
    <light name="top" pos="0 0 1" dir="0 0 -1" directional="true"/>
    <geom name="floor" type="plane" size="0.5 0.5 0.01" pos="0 0 -0.4" material="grid" contype="0" conaffinity="0"/>
    <camera name="overview" pos="0.25 -0.35 0.25" xyaxes="0.81 0.58 0 -0.3 0.42 0.86"/>
  </worldbody>
</mujoco>
"""


def generated_files() -> dict:
    """Path -> the text the spec generates for it: the device MJCF and its scene."""
    return {MJCF_PATH: mjcf(load_spec()), SCENE_PATH: scene_mjcf()}


def write_mjcf() -> list[str]:
    """Regenerate the committed MJCF (device and scene) from the spec; returns the paths written."""
    for path, text in generated_files().items():
        path.write_text(text)
    return [str(p) for p in generated_files()]
