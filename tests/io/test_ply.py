"""PLY / OBJ writers and reader: round trips, atomic writes, clear errors."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from svolsdf.errors import InputError
from svolsdf.io.ply import read_ply, write_mesh_ply, write_obj, write_points_ply


def test_points_round_trip_uint8_and_normals(tmp_path):
    rng = np.random.default_rng(0)
    xyz = rng.normal(size=(500, 3)) * 300.0
    rgb = rng.integers(0, 256, size=(500, 3), dtype=np.uint8)
    nrm = rng.normal(size=(500, 3))
    p = write_points_ply(tmp_path / "p.ply", xyz, rgb, normals=nrm)
    d = read_ply(p)
    np.testing.assert_allclose(d["points"], xyz.astype(np.float32), rtol=0, atol=0)
    np.testing.assert_array_equal(d["colors"], rgb)
    np.testing.assert_allclose(d["normals"], nrm.astype(np.float32))
    assert d["faces"] is None
    assert d["points"].dtype == np.float64
    # binary little-endian with float xyz and uchar colours
    header = p.read_bytes()[:400].split(b"end_header")[0].decode()
    assert "format binary_little_endian 1.0" in header
    assert "property float x" in header and "property uchar red" in header
    assert list(tmp_path.iterdir()) == [p]  # no temporary file left


def test_points_float_colours_and_torch_input(tmp_path):
    xyz = torch.rand(10, 3, dtype=torch.float64)
    rgb = torch.tensor([[0.0, 0.5, 1.0]] * 10)
    d = read_ply(write_points_ply(tmp_path / "p.ply", xyz, rgb))
    assert d["colors"][0].tolist() == [0, 128, 255]
    d2 = read_ply(write_points_ply(tmp_path / "q.ply", xyz))
    assert d2["colors"] is None and d2["normals"] is None


def test_mesh_round_trip_ply_and_obj(tmp_path):
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=np.float64)
    f = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    c = np.array([[255, 0, 0], [0, 255, 0], [0, 0, 255], [9, 9, 9]], dtype=np.uint8)
    d = read_ply(write_mesh_ply(tmp_path / "m.ply", v, f, c))
    np.testing.assert_array_equal(d["faces"], f)
    np.testing.assert_array_equal(d["colors"], c)
    np.testing.assert_allclose(d["points"], v)
    o = write_obj(tmp_path / "m.obj", v, f, c)
    lines = o.read_text().splitlines()
    assert lines[0].startswith("v 0.000000 0.000000 0.000000 1.0000 0.0000 0.0000")
    assert lines[-1] == "f 2 3 4"
    with pytest.raises(ValueError, match="outside"):
        write_mesh_ply(tmp_path / "bad.ply", v, f + 10)


def test_atomic_write_keeps_old_file_on_failure(tmp_path):
    p = write_points_ply(tmp_path / "p.ply", np.zeros((3, 3)))
    before = p.read_bytes()
    with pytest.raises(ValueError):
        write_points_ply(p, np.zeros((3, 3)), rgb=np.zeros((4, 3)))  # row-count mismatch
    assert p.read_bytes() == before
    assert sorted(x.name for x in tmp_path.iterdir()) == ["p.ply"]

    # a failure while the file is being written leaves the old file and no temporary

    import svolsdf.io.ply as ply_mod

    orig = ply_mod.PlyData.write

    def failing_write(self, stream):
        with open(stream, "wb") as fh:
            fh.write(b"ply\nhalf")
        raise OSError("disk full")

    ply_mod.PlyData.write = failing_write
    try:
        # the one-line error names the file (exit 2), and no temporary is left
        with pytest.raises(InputError, match=r"p.ply: cannot write it \(disk full\)"):
            write_points_ply(p, np.ones((5, 3)))
    finally:
        ply_mod.PlyData.write = orig
    assert p.read_bytes() == before
    assert sorted(x.name for x in tmp_path.iterdir()) == ["p.ply"]


def test_bad_files_raise_input_error_naming_file(tmp_path):
    with pytest.raises(InputError, match="missing.ply"):
        read_ply(tmp_path / "missing.ply")
    junk = tmp_path / "junk.ply"
    junk.write_bytes(b"this is not a ply file\n")
    with pytest.raises(InputError, match="junk.ply"):
        read_ply(junk)
    trunc = tmp_path / "trunc.ply"
    full = write_points_ply(tmp_path / "full.ply", np.ones((100, 3))).read_bytes()
    trunc.write_bytes(full[: len(full) - 50])
    with pytest.raises(InputError, match="trunc.ply"):
        read_ply(trunc)


def test_read_ply_triangles_fast_and_polygons_fanned(tmp_path):
    from plyfile import PlyData, PlyElement

    v = np.random.default_rng(0).random((5, 3))
    tri = np.array([[0, 1, 2], [2, 3, 4]])
    write_mesh_ply(tmp_path / "t.ply", v, tri)
    assert np.array_equal(read_ply(tmp_path / "t.ply")["faces"], tri)
    vert = np.array([tuple(p) for p in v], dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    faces = np.empty(2, dtype=[("vertex_indices", "O")])
    faces["vertex_indices"][0] = np.array([0, 1, 2, 3], "i4")
    faces["vertex_indices"][1] = np.array([2, 3, 4], "i4")
    for text in (False, True):
        PlyData([PlyElement.describe(vert, "vertex"), PlyElement.describe(faces, "face")],
                text=text).write(tmp_path / "q.ply")
        got = read_ply(tmp_path / "q.ply")["faces"]
        assert np.array_equal(got, [[0, 1, 2], [0, 2, 3], [2, 3, 4]])
