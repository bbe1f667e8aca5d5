"""The spec, the generated MJCF and the kinematics agree."""

import math
import re

import mujoco
import numpy as np
import pytest

from twin.cli import main
from twin.device.design import design_spec
from twin.device.kinematics import flap_frames
from twin.device.mjcf import MJCF_PATH, SCENE_PATH, load_model, mjcf, scene_mjcf
from twin.device.spec import SPEC_PATH, load_spec, spec_sources
from twin.sim.twin import Twin


def test_every_constant_has_a_source():
    sources = spec_sources()
    assert sources and all(s.split(":")[0] in ("paper", "datasheet", "assumption") for s in sources.values())


def test_spec_rejects_missing_and_unknown_fields(tmp_path):
    text = SPEC_PATH.read_text()
    bad = tmp_path / "spec.toml"
    bad.write_text(text.replace("loop_rate", "loop_rat"))
    with pytest.raises(ValueError, match="missing \\['loop_rate'\\], unknown \\['loop_rat'\\]"):
        load_spec(bad)


@pytest.mark.parametrize("line, value, says", [
    ("loop_rate      = { value = 1000,", "1e9", "loop_rate = 1e+09 Hz is outside the 100-10000 Hz"),
    ("length         = { value = 0.188,", "1e6", "length = 1e+06 m is over a hand-held display's 1 m"),
])
def test_a_spec_whose_sizes_the_twin_cannot_hold_is_refused_as_read(tmp_path, capsys, line, value, says):
    """A sweep's base spec of 1e6 m or 1e9 Hz (issue 40 attack 7) is refused where it is read, naming the file."""
    text = SPEC_PATH.read_text()
    assert line in text
    bad = tmp_path / "spec.toml"
    bad.write_text(text.replace(line, line.split("=")[0] + "= { value = " + value + ","))
    with pytest.raises(ValueError, match=re.escape(f"{bad}: {says}")):
        load_spec(bad)
    (tmp_path / "sweep.toml").write_text('spec = "spec.toml"\nshapes = ["cube"]\n')
    assert main(["sweep", str(tmp_path / "sweep.toml"), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert says in err and len(err.strip().splitlines()) == 1


def test_derived_values(spec):
    assert spec.n_hinges == 6
    assert spec.flap_pitch == pytest.approx(0.188 / 7)
    assert spec.counts_per_rev == pytest.approx(1204.44)
    assert spec.hinge_limit == pytest.approx(math.radians(112.5))
    assert spec.current(6.0, 0.0) == pytest.approx(1.6)  # stall current from the datasheet resistance


def test_committed_mjcf_is_generated_from_spec():
    assert MJCF_PATH.read_text() == mjcf(), "run `vrscroll model --write`"


def test_the_mjcfs_comments_follow_a_design(spec):
    """The generated MJCF's comments once fixed "seven flaps" and "100.37:1" though sweeps change both (issue 39):
    a design's own flap count, ratio and voltage are in its comments, the base's nowhere."""
    design = design_spec(spec, {"n_flaps": 5, "gear_ratio": 150.58, "rated_voltage": 12.0})
    comments = " ".join(re.findall(r"<!--(.*?)-->", mjcf(design), flags=re.S))
    assert "5 hinged flaps" in comments and "150.58:1" in comments and "12 V micro metal gearmotor" in comments
    assert f"{spec.n_flaps} hinged flaps" not in comments and f"{spec.gear_ratio:g}:1" not in comments


def test_compiled_model_matches_spec(spec):
    """Every number of the drive train in the compiled model is the spec's: a flap joint and a gearbox-output
    joint per hinge, the dcmotor on the gear joint (K, winding + driver R, armature, viscous and LuGre
    friction written motor side), the backlash dead zone between them."""
    m = mujoco.MjModel.from_xml_path(str(MJCF_PATH))
    N = spec.gear_ratio
    assert m.nu == m.ntendon == spec.n_hinges and m.njnt == 2 * spec.n_hinges
    assert m.nbody == spec.n_flaps + 1 + spec.n_hinges  # the flaps, the world, a rotor per hinge
    assert m.body_subtreemass[0] == pytest.approx(spec.mass_total, rel=1e-6)
    assert m.opt.timestep == pytest.approx(spec.firmware_dt)
    for k in range(spec.n_hinges):
        j, g, a = m.joint(f"hinge{k}"), m.joint(f"gear{k}"), m.actuator(f"motor{k}")
        assert np.degrees(j.range) == pytest.approx([-112.5, 112.5])
        assert j.frictionloss[0] == g.frictionloss[0] == 0.0  # no friction constraint rows: LuGre instead
        assert a.trnid[0] == g.id and a.gear[0] == pytest.approx(N)
        assert m.actuator_armature[a.id] == pytest.approx(spec.rotor_inertia)
        assert m.actuator_dyntype[a.id] == mujoco.mjtDyn.mjDYN_DCMOTOR
        assert a.gainprm[:2] == pytest.approx([spec.resistance + spec.driver_on_resistance, spec.motor_constant])
        assert m.actuator_damping[a.id] * N**2 == pytest.approx(spec.gear_damping)
        lugre = m.actuator_dynprm[a.id][5:7].tolist() + m.actuator_biasprm[a.id][3:6].tolist()
        assert lugre == pytest.approx([spec.friction_stiffness / N**2, spec.friction_damping / N**2,
                                       spec.gear_friction / N, spec.gear_stiction / N, spec.stribeck_speed * N])
        assert m.tendon_range[m.tendon(f"backlash{k}").id] == pytest.approx([-spec.backlash / 2, spec.backlash / 2])
    assert m.key("flat").qpos == pytest.approx(np.zeros(2 * spec.n_hinges))


def test_neighbours_never_collide_but_others_can(spec):
    m = load_model(spec)
    d = mujoco.MjData(m)
    # fold hinges 3 and 4 fully concave: flaps 5 and 6 swing back over the root side
    d.qpos[m.joint("hinge3").qposadr[0]] = spec.hinge_limit
    d.qpos[m.joint("hinge4").qposadr[0]] = spec.hinge_limit
    mujoco.mj_forward(m, d)
    pairs = {tuple(sorted((m.geom(c.geom1).name, m.geom(c.geom2).name))) for c in d.contact[: d.ncon]}
    flaps = [tuple(int(name[4]) for name in pair) for pair in pairs]
    assert flaps and all(abs(a - b) > 1 for a, b in flaps)
    for angle in (0.0, -spec.hinge_limit, spec.hinge_limit):  # flat, and every hinge at either limit
        bent = mujoco.MjData(m)
        bent.qpos[:] = angle
        mujoco.mj_forward(m, bent)
        names = [(m.geom(c.geom1).name, m.geom(c.geom2).name) for c in bent.contact[: bent.ncon]]
        assert all(abs(int(a[4]) - int(b[4])) > 1 for a, b in names), names
    one = mujoco.MjData(m)
    one.qpos[m.joint("hinge2").qposadr[0]] = -math.radians(40)  # root's neighbour bent convex
    mujoco.mj_forward(m, one)
    assert one.ncon == 0


@pytest.mark.parametrize("seed", range(3))
def test_kinematics_matches_mujoco(spec, seed):
    """The approximation's forward kinematics and the MJCF put every flap in the same place."""
    angles = np.random.default_rng(seed).uniform(-spec.hinge_limit, spec.hinge_limit, spec.n_hinges)
    m = load_model(spec)
    d = mujoco.MjData(m)
    for k in range(spec.n_hinges):
        d.qpos[m.joint(f"hinge{k}").qposadr[0]] = angles[k]
    mujoco.mj_forward(m, d)
    frames = flap_frames(spec, angles)
    for i in range(spec.n_flaps):
        site = m.site(f"surface{i}").id
        assert d.site_xpos[site] == pytest.approx(frames[i, :3, 3], abs=1e-9)
        assert d.site_xmat[site].reshape(3, 3) == pytest.approx(frames[i, :3, :3], abs=1e-9)


def test_free_root_model_loads(spec):
    m = load_model(spec, root="free")
    assert m.nq == 7 + 2 * spec.n_hinges and m.key("flat").qpos[3] == 1.0
    with pytest.raises(ValueError, match="root must be"):
        mjcf(spec, root="floating")


def test_scene_includes_the_device_and_adds_floor_and_light(capsys):
    assert SCENE_PATH.read_text() == scene_mjcf(), "run `vrscroll model --write`"
    device = mujoco.MjModel.from_xml_path(str(MJCF_PATH))
    scene = mujoco.MjModel.from_xml_path(str(SCENE_PATH))
    assert device.nlight == 0 and scene.nlight >= 1
    assert mujoco.mj_name2id(device, mujoco.mjtObj.mjOBJ_GEOM, "floor") == -1
    assert mujoco.mj_name2id(scene, mujoco.mjtObj.mjOBJ_GEOM, "floor") >= 0
    assert scene.nbody == device.nbody and scene.njnt == device.njnt and scene.nu == device.nu
    assert main(["model", "--check"]) == 0
    out = capsys.readouterr().out
    assert f"{MJCF_PATH} matches the spec" in out and f"{SCENE_PATH} matches the spec" in out


def test_a_morph_on_the_twin_raises_no_mujoco_warning(spec):
    """Random morphs across the whole hinge range (targets nobody tuned), flaps folding onto each other
    included: MuJoCo counts any warning (contact buffer, bad qacc, ...) in data.warning."""
    rng = np.random.default_rng(11)
    twin = Twin(spec)
    targets = [rng.uniform(-1, 1, spec.n_hinges) * spec.hinge_limit for _ in range(4)]
    targets.append(np.full(spec.n_hinges, spec.hinge_limit))  # every hinge at its stop: the row curls up
    for t in targets:
        twin.move_to(t, max_time=0.8, stop_when_settled=False)
        counts = {mujoco.mjtWarning(i).name: int(w.number) for i, w in enumerate(twin.data.warning) if w.number}
        assert counts == {}, counts
