"""The one PLY reader/writer (presim.formats.ply): known bytes, ASCII and binary round trips with
colours and normals, point clouds, and BOP millimetre models read into metres."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from presim.datasets.objects import ObjectModel, load_model, write_model_ply_mm
from presim.formats.ply import PlyMesh, read_ply, write_ply

# A right triangle in the z = 0 plane, normals +z, one primary colour per corner.
V = np.array([[0.0, 0.0, 0.0], [1.5, 0.0, 0.0], [0.0, 2.25, 0.0]], dtype=np.float32)
F = np.array([[0, 1, 2]])
N = np.array([[0.0, 0.0, 1.0]] * 3, dtype=np.float32)
C = np.array([[255, 0, 0], [0, 255, 0], [0, 0, 255]], dtype=np.uint8)


def test_ascii_file_is_exactly_the_expected_text(tmp_path):
    p = tmp_path / "tri.ply"
    write_ply(p, V, F, colors=C, normals=N, comment="known answer", binary=False)
    assert p.read_text() == (
        "ply\nformat ascii 1.0\ncomment known answer\nelement vertex 3\n"
        "property float x\nproperty float y\nproperty float z\n"
        "property float nx\nproperty float ny\nproperty float nz\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\n"
        "element face 1\nproperty list uchar int vertex_indices\nend_header\n"
        "0 0 0 0 0 1 255 0 0\n1.5 0 0 0 0 1 0 255 0\n0 2.25 0 0 0 1 0 0 255\n3 0 1 2\n")


def test_binary_file_layout(tmp_path):
    p = tmp_path / "tri.ply"
    write_ply(p, V, F, colors=C, normals=N)
    data = p.read_bytes()
    head = data[: data.index(b"end_header\n") + len(b"end_header\n")]
    assert head.startswith(b"ply\nformat binary_little_endian 1.0\nelement vertex 3\n")
    # 3 vertices x (6 float32 + 3 uchar) + 1 face x (uchar count + 3 int32).
    assert len(data) - len(head) == 3 * (6 * 4 + 3) + (1 + 3 * 4)
    assert data[len(head) + 4: len(head) + 8] == np.float32(0.0).tobytes()          # y of vertex 0
    assert data[len(head) + 27: len(head) + 31] == np.float32(1.5).tobytes()        # x of vertex 1
    assert data[-13:] == bytes([3]) + np.array([0, 1, 2], "<i4").tobytes()


@pytest.mark.parametrize("binary", [True, False])
def test_round_trip_with_colours_and_normals(tmp_path, binary):
    p = tmp_path / "tri.ply"
    write_ply(p, V, F, colors=C, normals=N, binary=binary)
    m = read_ply(p)
    np.testing.assert_array_equal(m.vertices, V)
    np.testing.assert_array_equal(m.faces, F)
    np.testing.assert_array_equal(m.normals, N)
    np.testing.assert_array_equal(m.colors, C)
    assert m.texture_uv is None
    # An independent reader agrees (trimesh keeps the order with process=False).
    ref = trimesh.load(p, process=False, force="mesh")
    np.testing.assert_array_equal(ref.vertices, V)
    np.testing.assert_array_equal(ref.faces, F)
    np.testing.assert_array_equal(np.asarray(ref.visual.vertex_colors)[:, :3], C)


def test_random_values_survive_ascii_and_binary_identically(tmp_path):
    rng = np.random.default_rng(1)
    v = rng.normal(size=(50, 3)).astype(np.float32) * 1000
    n = rng.normal(size=(50, 3)).astype(np.float32)
    f = rng.integers(0, 50, size=(20, 3))
    for binary in (True, False):
        write_ply(tmp_path / f"r{binary}.ply", v, f, normals=n, binary=binary)
    a, b = read_ply(tmp_path / "rTrue.ply"), read_ply(tmp_path / "rFalse.ply")
    np.testing.assert_array_equal(a.vertices, v)     # binary: the float32 values, exactly
    # ASCII: the reader parses the text as float64 (as it reads BOP's ASCII models); "%.9g" text
    # rounds back to the same float32, and the float64 value is within half a float32 step.
    np.testing.assert_array_equal(b.vertices.astype(np.float32), v)
    np.testing.assert_array_equal(b.normals.astype(np.float32), n)
    np.testing.assert_allclose(b.vertices, v, rtol=2 ** -24, atol=0)
    np.testing.assert_array_equal(a.faces, b.faces)


def test_point_cloud_has_no_faces(tmp_path):
    p = tmp_path / "pts.ply"
    write_ply(p, V)
    m = read_ply(p)
    assert m.faces is None and m.normals is None and m.colors is None
    np.testing.assert_array_equal(m.vertices, V)


def test_scaled_converts_units():
    m = PlyMesh(vertices=np.array([[100.0, -20.0, 5.0]]))
    np.testing.assert_allclose(m.scaled(1e-3).vertices, [[0.1, -0.02, 0.005]], rtol=1e-15)


def test_bop_model_mm_written_and_read_back_in_metres(tmp_path):
    """A 100 x 60 x 40 mm box model: the file holds millimetres, load_model(unit='mm') metres."""
    box = trimesh.creation.box((0.1, 0.06, 0.04))
    model = ObjectModel(4, "box", np.asarray(box.vertices), np.asarray(box.faces),
                        colors=np.full((8, 3), 200, np.uint8))
    path = tmp_path / "obj_000004.ply"
    write_model_ply_mm(model, path)
    assert path.read_bytes().startswith(b"ply\nformat binary_little_endian 1.0\ncomment PreSim BOP model, "
                                        b"millimetres\nelement vertex 8\n")
    raw = read_ply(path)
    np.testing.assert_allclose(raw.vertices.max(0), [50.0, 30.0, 20.0], rtol=1e-6)
    back = load_model(path, 4, unit="mm")
    np.testing.assert_allclose(back.vertices_m.max(0), [0.05, 0.03, 0.02], rtol=1e-6)
    np.testing.assert_array_equal(back.faces, model.faces)
    np.testing.assert_array_equal(back.colors, model.colors)
    # Normals of a box corner: area-weighted mean of its three faces' normals, unit length.
    np.testing.assert_allclose(np.linalg.norm(back.normals, axis=1), 1.0, atol=1e-6)


def test_writer_errors(tmp_path):
    with pytest.raises(ValueError, match="one line"):
        write_ply(tmp_path / "x.ply", V, F, comment="two\nlines")
