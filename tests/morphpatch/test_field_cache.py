"""The fields' cache within bounds and never trusted (issues 37 and 40): a corrupted or foreign cache file is
rebuilt with a notice and never reaches compiled code; the disk cache is trimmed to its cap; a target too
large for the grid's points is built coarser, not in gigabytes; `vrscroll cache` shows and clears it."""

import numpy as np
import pytest
import trimesh

import twin.morphpatch.fields as module
from cli import vrscroll
from twin.device.spec import load_spec
from twin.morphpatch.approximation import approximate, pose_from_mm_deg
from twin.morphpatch.fields import build_fields, grid_spacing

SPACING, MARGIN = 0.006, 0.03  # m: a small grid, built in a fraction of a second


def corruptions(a: dict, other: dict) -> dict:
    """name -> the arrays of a cache file damaged one way (issue 40's attack 6, and more)."""
    def changed(**kw):
        return {**a, **kw}
    sdf = a["sdf"].copy()
    sdf[3, 4, 5] = np.nan
    index = a["edge_index"].copy()
    index[index >= 0] = len(a["edges"]) + 7
    return {
        "an edge index past its list": changed(edge_index=index),
        "a NaN in the SDF": changed(sdf=sdf),
        "empty edges, indices kept": changed(edges=np.zeros((0, 3))),
        "edges of the wrong shape": changed(edges=np.zeros((0,))),
        "an origin of 1e300": changed(origin=np.full(3, 1e300)),
        "a negated SDF": changed(sdf=-a["sdf"]),
        "a negative spacing": changed(spacing=np.array(-float(a["spacing"]))),
        "a zero spacing": changed(spacing=np.array(0.0)),
        "another mesh's file under this name": {**other, "key": a["key"]},
        "another mesh's key": changed(key=other["key"]),
        "an old version": changed(version=np.array(2)),
        "the SDF as integers": changed(sdf=a["sdf"].astype(np.int64)),
        "a curvature of another shape": changed(curvature=a["curvature"][:-1]),
        "an edge index of floats": changed(edge_index=a["edge_index"].astype(float)),
    }


def test_a_corrupted_or_foreign_cache_file_is_built_again(tmp_path, monkeypatch, capsys, spec):
    monkeypatch.setenv("VRSCROLL_CACHE", str(tmp_path))
    monkeypatch.setattr(module, "_MEMORY", {})
    box = trimesh.creation.box((0.06, 0.05, 0.04))
    other = trimesh.creation.icosphere(2, 0.03)
    fresh = build_fields(box, spacing=SPACING, margin=MARGIN)
    [path] = (tmp_path / "fields").glob("*.npz")
    build_fields(other, spacing=SPACING, margin=MARGIN)
    [other_path] = set((tmp_path / "fields").glob("*.npz")) - {path}
    good, foreign = dict(np.load(path)), dict(np.load(other_path))
    start = pose_from_mm_deg([0, 0, 60, 0, 0, 0])
    expected = approximate(fresh, start, spec, "refined")
    for name, arrays in corruptions(good, foreign).items():
        np.savez(path, **arrays)
        module._MEMORY.clear()
        capsys.readouterr()
        fields = build_fields(box, spacing=SPACING, margin=MARGIN)
        err = capsys.readouterr().err
        assert len(err.splitlines()) == 1 and "is not this target's fields" in err, (name, err)
        assert np.array_equal(fields.sdf, fresh.sdf) and np.array_equal(fields.edge_index, fresh.edge_index), name
        result = approximate(fields, start, spec, "refined")
        np.testing.assert_allclose(result.root_pose, expected.root_pose, atol=1e-12, err_msg=name)
        module._MEMORY.clear()
        build_fields(box, spacing=SPACING, margin=MARGIN)  # the rebuilt file is read back without a word
        assert capsys.readouterr().err == "", name


def test_random_damage_to_a_cache_file_never_reaches_compiled_code(tmp_path, monkeypatch, capsys, spec):
    """Fuzz: values in a random array of the file replaced by extremes (NaN, inf, 1e300, -1, huge indices),
    or its bytes cut or flipped: each load rebuilds or reads a file identical to the fresh one."""
    monkeypatch.setenv("VRSCROLL_CACHE", str(tmp_path))
    monkeypatch.setattr(module, "_MEMORY", {})
    mesh = trimesh.creation.icosphere(2, 0.03)
    fresh = build_fields(mesh, spacing=SPACING, margin=MARGIN)
    [path] = (tmp_path / "fields").glob("*.npz")
    good, raw = dict(np.load(path)), path.read_bytes()
    rng = np.random.default_rng(40)
    extremes = np.array([np.nan, np.inf, -np.inf, 1e300, -1e300, -1.0, 0.0, 2 ** 40])
    for trial in range(40):
        if trial % 4 == 3:
            data = bytearray(raw)
            for k in rng.integers(0, len(data), 8):
                data[k] ^= int(rng.integers(1, 256))
            path.write_bytes(bytes(data))
        else:
            name = rng.choice(sorted(module.CACHE_ARRAYS))
            arrays = {k: v.copy() for k, v in good.items()}
            v = arrays[name]
            if v.dtype.kind in "fiu" and v.size:
                flat = v.reshape(-1)
                flat[rng.integers(0, flat.size, 3)] = rng.choice(extremes).astype(v.dtype) \
                    if v.dtype.kind == "f" else rng.choice([-2, 2 ** 30, -2 ** 30])
            else:
                arrays[name] = np.array("x" * 40)
            np.savez(path, **arrays)
        module._MEMORY.clear()
        fields = build_fields(mesh, spacing=SPACING, margin=MARGIN)
        assert np.array_equal(fields.sdf, fresh.sdf) and np.array_equal(fields.edge_index, fresh.edge_index), trial
        approximate(fields, pose_from_mm_deg([0, 0, 80, 0, 0, 0]), spec, "full")


def test_the_disk_cache_is_trimmed_to_its_cap_least_recently_used_first(tmp_path, monkeypatch):
    monkeypatch.setenv("VRSCROLL_CACHE", str(tmp_path))
    monkeypatch.setattr(module, "_MEMORY", {})
    meshes = [trimesh.creation.box((0.04, 0.04, 0.04), trimesh.transformations.translation_matrix((0.001 * k, 0, 0)))
              for k in range(4)]  # four meshes, their files alike in size
    build_fields(meshes[0], spacing=SPACING, margin=MARGIN)
    [first] = (tmp_path / "fields").glob("*.npz")
    monkeypatch.setattr(module, "CACHE_CAP", int(first.stat().st_size * 2.5))
    for m in meshes[1:]:
        build_fields(m, spacing=SPACING, margin=MARGIN)
    files = list((tmp_path / "fields").glob("*.npz"))
    assert len(files) == 2 and first not in files and sum(f.stat().st_size for f in files) <= module.CACHE_CAP


def test_a_target_too_large_for_the_grid_is_built_coarser(capsys):
    """A 1 m box at 3 mm would be 64 million grid points (7.6 GB to build); it is built within MAX_GRID_POINTS,
    said on one line."""
    box = trimesh.creation.box((1.0, 1.0, 1.0))
    spacing = grid_spacing(box)
    points = np.prod(np.ceil((box.extents + 2 * module.MARGIN) / spacing) + 1)
    assert points <= module.MAX_GRID_POINTS and spacing > module.GRID_SPACING
    assert np.prod(np.ceil((box.extents + 2 * module.MARGIN) / (spacing - 1e-4)) + 1) > module.MAX_GRID_POINTS
    assert "grid, not 3 mm" in capsys.readouterr().err
    assert grid_spacing(trimesh.creation.box((0.2, 0.2, 0.2))) == module.GRID_SPACING


def test_vrscroll_cache_shows_and_clears(tmp_path):
    env = {"VRSCROLL_CACHE": str(tmp_path)}
    (tmp_path / "fields").mkdir()
    (tmp_path / "fields" / "a.npz").write_bytes(b"x" * 2500)
    (tmp_path / "firmware").mkdir()
    (tmp_path / "firmware" / "core.so").write_bytes(b"x" * 10)
    out = vrscroll("cache", env=env)
    assert out.returncode == 0 and "fields: 1 file(s), 2.5 kB" in out.stdout and "firmware: 1 file(s), 10 B" in out.stdout
    out = vrscroll("cache", "clear", "--kind", "fields", env=env)
    assert out.returncode == 0 and "cleared 1 file(s), 2.5 kB" in out.stdout
    assert not (tmp_path / "fields" / "a.npz").exists() and (tmp_path / "firmware" / "core.so").exists()
    out = vrscroll("cache", "clear", "--kind", "nothing", env=env)
    assert out.returncode == 2 and "no such kind" in out.stderr and len(out.stderr.splitlines()) == 1
    assert vrscroll("cache", "clear", env=env).returncode == 0 and not (tmp_path / "firmware" / "core.so").exists()
