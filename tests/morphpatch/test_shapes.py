"""The evaluation shapes and mesh-file loading (twin/morphpatch/shapes.py)."""

import numpy as np
import pytest
import trimesh

from twin.morphpatch.shapes import MeshError, load_mesh, load_shape, shape_names, shape_table

PAPER_SHAPES = ["cube", "torus", "arch", "cone", "cylinder", "ellipsoid", "stairs", "curved_stairs"]


def test_the_papers_eight_shapes_are_listed():
    assert shape_names() == PAPER_SHAPES
    for name, entry in shape_table().items():
        assert entry["description"], name
        assert len(entry["start"]) == 6, name


@pytest.mark.parametrize("name", PAPER_SHAPES)
def test_shape_is_a_closed_solid_of_device_size(name):
    mesh = load_shape(name)
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.volume > 0  # outward normals
    assert 0.1 <= mesh.extents.max() <= 0.5  # m: same order as the 188 x 175 mm device
    assert mesh.bounds[0, 2] == pytest.approx(0.0, abs=1e-9)  # rests on the ground


def test_known_volumes():
    t = shape_table()
    s = t["stairs"]
    steps = np.arange(1, s["steps"] + 1) * s["rise"]
    assert load_shape("stairs").volume == pytest.approx(s["run"] * s["width"] * steps.sum(), rel=1e-9)
    a = t["arch"]
    arch = np.pi / 2 * (a["outer_radius"] ** 2 - a["inner_radius"] ** 2) * a["depth"]
    assert load_shape("arch").volume == pytest.approx(arch, rel=2e-3)  # polygonal arcs
    assert load_shape("cube").volume == pytest.approx(np.prod(t["cube"]["size"]))


def test_unknown_shape():
    with pytest.raises(MeshError, match="unknown shape 'sphere'.*cube"):
        load_shape("sphere")


@pytest.mark.parametrize("ext", ["stl", "obj", "ply", "glb"])
def test_mesh_files_load(tmp_path, ext):
    path = tmp_path / f"torus.{ext}"
    load_shape("torus").export(path)
    mesh = load_mesh(path)
    assert mesh.is_watertight
    assert mesh.volume == pytest.approx(load_shape("torus").volume, rel=1e-6)


def _write(tmp_path, name, data):
    path = tmp_path / name
    path.write_text(data) if isinstance(data, str) else data.export(path)
    return path


@pytest.mark.parametrize("name, data, message", [
    ("empty.stl", "", "the file is empty"),
    ("text.stl", "hello, I am not a mesh\n", "no triangles|not a mesh"),
    ("nan.obj", "v 0 0 0\nv 0.1 0 0\nv nan 0.1 0\nv 0 0 0.1\nf 1 2 3\nf 1 2 4\nf 1 3 4\nf 2 3 4\n",
     "1 vertices are NaN"),
    ("tiny.stl", trimesh.creation.box((0.001, 0.001, 0.001)),
     r"largest extent 0.001 m \(1 mm, the file read in metres\) is below the 2 mm a target may span"),
    ("huge.stl", trimesh.creation.box((10.0, 1.0, 1.0)), r"largest extent 10 m \(1e\+04 mm.*above the 5 m"),
    ("open.stl", trimesh.Trimesh(*(lambda b: (b.vertices, b.faces[:-1]))(trimesh.creation.box((0.1, 0.1, 0.1)))),
     "not watertight"),
])
def test_bad_meshes_say_what_is_wrong(tmp_path, name, data, message):
    path = _write(tmp_path, name, data)
    with pytest.raises(MeshError, match=message):
        load_mesh(path)


def test_missing_file(tmp_path):
    with pytest.raises(MeshError, match="no such file"):
        load_mesh(tmp_path / "nothing.stl")


def test_mesh_error_is_a_value_error():
    assert issubclass(MeshError, ValueError)


def test_a_directory_is_not_reported_as_a_missing_file(tmp_path):
    with pytest.raises(MeshError, match="is a directory, not a mesh file"):
        load_mesh(tmp_path)


def test_an_inside_out_mesh_is_refused_in_one_line(tmp_path):
    """Its signed distances all flip: before, `approximate` reported MSD 206 mm and 100 % inside with exit 0."""
    from cli import vrscroll

    inverted = trimesh.creation.box((0.1, 0.08, 0.06))
    inverted.invert()
    assert inverted.is_watertight and inverted.volume < 0
    inverted.export(tmp_path / "inside_out.stl")
    with pytest.raises(MeshError, match="inside-out"):
        load_mesh(tmp_path / "inside_out.stl")
    out = vrscroll("approximate", "--mesh", str(tmp_path / "inside_out.stl"), "--variant", "full")
    assert out.returncode == 2 and "inside-out" in out.stderr and "Traceback" not in out.stderr
    assert len(out.stderr.strip().splitlines()) == 1 and out.stdout == ""
    inverted.invert()  # the same box, its faces flipped back: a target like any other
    inverted.export(tmp_path / "box.stl")
    assert load_mesh(tmp_path / "box.stl").volume > 0
