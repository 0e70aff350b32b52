"""``svolsdf export OUT``: each output opened by the library its ecosystem reads it with
(pycolmap for the COLMAP model, plyfile and trimesh for PLY, json + numpy for nerfstudio's
transforms.json), checked against the run's own cameras and files; bad input refused in one line
with nothing written."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from tests.pipeline.tiny_pipeline import (
    cli,
    cli_exit,
    copy_run,
    make_small_sphere_scene,
    small_field_run,
)

from svolsdf.io.runfolder import file_record
from svolsdf.scene.loaders import load_scene


def _listing(folder: Path) -> dict[str, dict]:
    """{relative path: file_record} of every file under ``folder``."""
    return {p.relative_to(folder).as_posix(): file_record(p) for p in sorted(folder.rglob("*"))
            if p.is_file() and p.name != ".svolsdf.lock"}


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """(run folder, scene folder, OUT/export, the run's files before the export)."""
    d = tmp_path_factory.mktemp("export")
    scene = make_small_sphere_scene(d / "scene")
    out = small_field_run(scene, d)
    before = _listing(out)
    cli(["export", out])
    return out, scene, out / "export", before


def _input_cameras(out: Path, scene: Path):
    """The run's input cameras at the photos' size, as the scene's reader gives them."""
    views = json.loads((out / "views.json").read_text())["inputs"]
    return load_scene(scene, views=views, load_images=False), views


def test_export_writes_every_output_and_leaves_the_run_as_it_was(exported):
    out, _, dest, before = exported
    assert {p.name for p in dest.iterdir()} >= {
        "images", "transforms.json", "sparse", "cameras.json", "points.ply", "meshes",
        "mesh_coloured.ply", "mesh_textured.obj", "mesh_textured.mtl", "mesh_textured.png"}
    after = _listing(out)
    assert {k: v for k, v in after.items() if not k.startswith("export/")} == before


def test_transforms_json_is_nerfstudio_camera_to_world_in_opengl_axes(exported):
    out, scene, dest, _ = exported
    head, views = _input_cameras(out, scene)
    t = json.loads((dest / "transforms.json").read_text())
    assert t["camera_model"] == "OPENCV" and len(t["frames"]) == len(views)
    assert (t["w"], t["h"]) == (head.width, head.height)
    assert (dest / t["ply_file_path"]).is_file()
    rng = np.random.default_rng(0)
    centre = head.normalization.center.numpy()
    x = centre + rng.normal(scale=30.0, size=(20, 3))  # world points near the object
    for k, fr in enumerate(t["frames"]):
        assert (dest / fr["file_path"]).is_file()
        c2w = np.asarray(fr["transform_matrix"])
        assert c2w.shape == (4, 4)
        np.testing.assert_allclose(c2w[:3, 3], head.cameras.centers[k].numpy(), atol=1e-6)
        # nerfstudio's projection: OpenGL camera (y up, looking down -z), pixel centres at +0.5
        cam = (np.linalg.inv(c2w) @ np.c_[x, np.ones(len(x))].T).T[:, :3]
        u = fr["fl_x"] * cam[:, 0] / -cam[:, 2] + fr["cx"]
        v = fr["fl_y"] * -cam[:, 1] / -cam[:, 2] + fr["cy"]
        uv, _ = head.cameras[k].project(torch.from_numpy(x)[None])
        np.testing.assert_allclose(np.c_[u, v], uv[0].numpy() + 0.5, atol=1e-3)


def test_colmap_model_opens_in_pycolmap_and_reads_back_as_the_scene(exported):
    import pycolmap

    out, scene, dest, _ = exported
    head, views = _input_cameras(out, scene)
    rec = pycolmap.Reconstruction(str(dest / "sparse" / "0"))
    assert rec.num_images() == len(views) and rec.num_cameras() == len(views)
    by_name = {im.name: im for im in rec.images.values()}
    for k, p in enumerate(head.image_paths):
        im = by_name[p.name]
        np.testing.assert_allclose(im.projection_center(), head.cameras.centers[k].numpy(),
                                   atol=1e-6)
        K = rec.cameras[im.camera_id].calibration_matrix()
        np.testing.assert_allclose(K[:2, 2], head.cameras.K[k, :2, 2].numpy() + 0.5, atol=1e-6)
    from svolsdf.io.ply import read_ply

    pts = read_ply(out / "points.ply")
    assert rec.num_points3D() == len(pts["points"])
    # tracks: the views whose final depth agrees; each observation is the point's projection
    tracked = [p for p in rec.points3D.values() if p.track.length() > 0]
    assert len(tracked) > 0.5 * rec.num_points3D()
    for p in tracked[:50]:
        for el in p.track.elements:
            im = rec.images[el.image_id]
            uv = rec.cameras[im.camera_id].img_from_cam(im.cam_from_world() * p.xyz)
            np.testing.assert_allclose(uv, im.points2D[el.point2D_idx].xy, atol=1e-6)
    # the export is a COLMAP scene: svolsdf's own reader gives the input cameras back
    again = load_scene(dest, load_images=False)
    order = [views[k] for k in np.argsort([p.name for p in head.image_paths])]
    for k, v in enumerate(order):
        i = views.index(v)
        np.testing.assert_allclose(again.cameras.K[k], head.cameras.K[i], atol=1e-6)
        np.testing.assert_allclose(again.cameras.w2c[k], head.cameras.w2c[i], atol=1e-6)


def test_cameras_json_holds_k_r_t_in_the_world_frame_and_units(exported):
    out, scene, dest, _ = exported
    head, views = _input_cameras(out, scene)
    c = json.loads((dest / "cameras.json").read_text())
    assert c["units"] == head.units and "OpenCV" in c["convention"]
    assert [v["id"] for v in c["views"]] == views
    for k, v in enumerate(c["views"]):
        np.testing.assert_allclose(v["K"], head.cameras.K[k].numpy(), atol=1e-9)
        np.testing.assert_allclose(v["R"], head.cameras.w2c[k, :3, :3].numpy(), atol=1e-9)
        np.testing.assert_allclose(v["t"], head.cameras.w2c[k, :3, 3].numpy(), atol=1e-9)
        assert (dest / v["file"]).is_file()


def test_points_ply_has_outward_unit_normals(exported):
    from plyfile import PlyData

    out, scene, dest, _ = exported
    v = PlyData.read(str(dest / "points.ply"))["vertex"].data
    assert {"x", "y", "z", "nx", "ny", "nz", "red", "green", "blue"} <= set(v.dtype.names)
    p = np.stack([v["x"], v["y"], v["z"]], 1).astype(np.float64)
    n = np.stack([v["nx"], v["ny"], v["nz"]], 1).astype(np.float64)
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-4)
    from scipy.spatial import cKDTree

    gt = PlyData.read(str(scene / "gt_points.ply"))["vertex"].data
    g = np.stack([gt["x"], gt["y"], gt["z"]], 1).astype(np.float64)
    centre = g.mean(0)  # the sphere's centre
    radius = np.linalg.norm(g - centre, axis=1).mean()
    # judged where the tiny run's points lie on the sphere (within 5 % of its radius): the
    # others are the few-step field's noise, whose "outward" means nothing
    on = cKDTree(g).query(p)[0] < 0.05 * radius
    assert on.sum() > 100, on.sum()
    outward = ((p - centre) * n).sum(1) > 0
    assert outward[on].mean() > 0.95, outward[on].mean()


def test_each_mesh_method_side_by_side_and_mesh_ply_kept(exported):
    import trimesh

    out, _, dest, before = exported
    assert file_record(out / "mesh.ply") == before["mesh.ply"]
    made = sorted(p.stem for p in (dest / "meshes").glob("*.ply"))
    # every registered method (tests elsewhere in the process may have registered more)
    assert {"field", "poisson", "tsdf"} <= set(made), made
    # the run's own mesh (the fast preset's poisson) is mesh.ply itself
    assert file_record(dest / "meshes" / "poisson.ply") == before["mesh.ply"]
    for name in made:
        m = trimesh.load(dest / "meshes" / f"{name}.ply", process=False)
        assert len(m.faces) > 100, name


def test_coloured_mesh_has_vertex_colours_from_the_photos(exported):
    import trimesh
    from plyfile import PlyData

    out, _, dest, _ = exported
    ply = PlyData.read(str(dest / "mesh_coloured.ply"))
    v = ply["vertex"].data
    assert all(v.dtype[c] == np.uint8 for c in ("red", "green", "blue"))
    m = trimesh.load(dest / "mesh_coloured.ply", process=False)
    ref = trimesh.load(out / "mesh.ply", process=False)
    np.testing.assert_allclose(m.vertices, ref.vertices)
    cols = np.asarray(m.visual.vertex_colors)[:, :3]
    assert cols.shape == (len(ref.vertices), 3)
    assert (np.abs(cols.astype(int) - 128).max(1) > 3).mean() > 0.3  # not all "unseen" grey


def test_textured_obj_opens_with_its_atlas(exported):
    import trimesh

    out, _, dest, _ = exported
    m = trimesh.load(dest / "mesh_textured.obj", process=False)
    ref = trimesh.load(out / "mesh.ply", process=False)
    assert isinstance(m.visual, trimesh.visual.TextureVisuals)
    assert len(m.faces) == len(ref.faces)
    np.testing.assert_allclose(m.vertices[m.faces], ref.vertices[ref.faces], atol=1e-5)
    tex = np.asarray(m.visual.material.image.convert("RGB"))
    assert (np.abs(tex.astype(int) - 128).max(-1) > 3).mean() > 0.2  # photo colours, not grey


def test_export_again_replaces_the_earlier_export_and_reconstruct_accepts_it(exported,
                                                                             tmp_path):
    from svolsdf.scene.checks import check_output_folder

    out, scene, dest, _ = exported
    run = copy_run(out, tmp_path / "run")
    earlier = tmp_path / "elsewhere"
    shutil.copytree(dest, earlier)
    (earlier / "transforms.json").write_text("{}")  # the earlier export's, changed...
    record = json.loads((earlier / ".svolsdf-files.json").read_text())
    record["files"]["transforms.json"] = 2  # ...as that export wrote it
    (earlier / ".svolsdf-files.json").write_text(json.dumps(record))
    cli(["export", run, "-o", earlier])  # its own earlier export: replaced
    assert json.loads((earlier / "transforms.json").read_text())["frames"]
    check_output_folder(run, scene, "svolsdf reconstruct")  # OUT/export is the run's own


def _refused(argv, capsys, folder: Path):
    before = sorted(p.as_posix() for p in folder.rglob("*"))
    code, cap = cli_exit(argv, capsys)
    assert code == 2, cap
    lines = cap.err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), cap.err
    assert sorted(p.as_posix() for p in folder.rglob("*")) == before  # nothing written
    return lines[0]


def test_bad_input_one_line_exit_2_nothing_written(exported, tmp_path, capsys):
    out, scene, _, _ = exported
    # a scene folder, not a run
    sc = shutil.copytree(scene, tmp_path / "scene")
    assert "not a run folder" in _refused(["export", sc], capsys, tmp_path)
    # a run whose mesh stage has not finished
    run = copy_run(out, tmp_path / "run")
    shutil.rmtree(run / "export")
    st = json.loads((run / "stages.json").read_text())
    del st["mesh"]
    (run / "stages.json").write_text(json.dumps(st))
    assert "not finished" in _refused(["export", run], capsys, tmp_path)
    # a truncated points.ply
    run2 = copy_run(out, tmp_path / "run2")
    shutil.rmtree(run2 / "export")
    (run2 / "points.ply").write_bytes((run2 / "points.ply").read_bytes()[:200])
    assert "points.ply" in _refused(["export", run2], capsys, tmp_path)
    # an output folder holding the user's files
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("mine")
    assert "not empty" in _refused(["export", out, "-o", tmp_path / "mine"], capsys, tmp_path)
    # no such folder
    assert "does not exist" in _refused(["export", tmp_path / "nothing"], capsys, tmp_path)


def _grid(half: float, z: float, n: int) -> tuple[np.ndarray, np.ndarray]:
    """A square of side 2 ``half`` at depth ``z`` facing the camera, as an n x n vertex grid."""
    s = np.linspace(-half, half, n)
    xx, yy = np.meshgrid(s, s)
    v = np.c_[xx.ravel(), yy.ravel(), np.full(n * n, z)]
    i = np.arange(n * n).reshape(n, n)
    a, b, c, d = i[:-1, :-1].ravel(), i[:-1, 1:].ravel(), i[1:, :-1].ravel(), i[1:, 1:].ravel()
    return v, np.r_[np.c_[a, b, c], np.c_[b, d, c]]


def test_mesh_colours_come_from_the_views_that_see_each_vertex():
    from types import SimpleNamespace

    from svolsdf.commands.export import mesh_photo_colours
    from svolsdf.scene.cameras import Cameras

    # one camera at the origin looking down +z; a small square at z = 5 hides the middle of a
    # large one at z = 10
    front, ff = _grid(0.6, 5.0, 5)
    back, bf = _grid(3.0, 10.0, 13)
    v = np.r_[front, back]
    f = np.r_[ff, bf + len(front)]
    K = torch.tensor([[[40.0, 0, 31.5], [0, 40.0, 23.5], [0, 0, 1]]], dtype=torch.float64)
    cams = Cameras(K, torch.eye(4, dtype=torch.float64)[None], 64, 48)
    images = torch.zeros(1, 3, 48, 64)
    images[:, 0] = 1.0  # a red photo
    cols = mesh_photo_colours(v, f, SimpleNamespace(cameras=cams, images=images))
    hidden = len(front) + 6 * 13 + 6  # the back square's centre (0, 0, 10), behind the front
    seen = len(front) + 1 * 13 + 1  # (-2.5, -2.5, 10): in the image, beside the front square
    assert cols[hidden].tolist() == [128, 128, 128]  # no view sees it: grey, not the red
    assert cols[seen].tolist() == [255, 0, 0]
    assert cols[len(front) // 2].tolist() == [255, 0, 0]  # the front square's centre


def test_run_without_field_exports_cameras_and_points(exported, tmp_path):
    from plyfile import PlyData

    _, scene, _, _ = exported
    out = tmp_path / "mvs_only"
    cli(["reconstruct", scene, "-o", out, "--views", "0", "1", "2", "--mode", "mvs-only",
         "--no-progress"])
    cli(["export", out])
    names = {p.name for p in (out / "export").iterdir()}
    assert {"transforms.json", "sparse", "cameras.json", "points.ply", "images"} <= names
    assert not names & {"meshes", "mesh_coloured.ply", "mesh_textured.obj"}
    v = PlyData.read(str(out / "export" / "points.ply"))["vertex"].data
    assert {"nx", "ny", "nz"} <= set(v.dtype.names)
