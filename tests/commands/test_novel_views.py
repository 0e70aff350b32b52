"""svolsdf render: volume-rendered and image-based novel views of a tiny trained run, the orbit
path and video, another render size, and bad input."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from svolsdf.cli import main as cli_main
from svolsdf.commands.render import box_near_far, camera_normals, open_run, render_outputs
from svolsdf.config import preset
from svolsdf.errors import InputError
from svolsdf.evaluate.images import masked_psnr
from svolsdf.io.images import read_image
from svolsdf.pipeline import Pipeline
from svolsdf.scene.cameras import Cameras
from svolsdf.scene.loaders import load_scene
from svolsdf.scene.synthetic import SynthConfig, make_synthetic_scene


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    scene = tmp_path_factory.mktemp("syn") / "scene"
    make_synthetic_scene(scene, SynthConfig(views=5, width=64, height=48, seed=1, supersample=1,
                                            gt_points=20000))
    cfg = preset("fast")
    cfg.scene.path = str(scene)
    cfg.train.steps = 20
    cfg.train.rays = 256
    # 20 steps on a 24^3 grid (cells ~0.08 unit): end the beta anneal at 0.005, not the 768x576
    # default 0.0025 (1/30 of a cell here), so the tiny field keeps a renderable surface
    cfg.train.beta_end = 0.005
    cfg.field.grid_start_resolution = 24
    cfg.field.grid_resolution = 24
    cfg.mesh.resolution = 48
    out = tmp_path_factory.mktemp("run")
    Pipeline(cfg, out, progress=False).run()
    return scene, out


@pytest.fixture(scope="module")
def rendered(tiny_run):
    scene, out = tiny_run
    return render_outputs(out, ibr=True, progress=False)


def test_default_views_are_the_test_views(tiny_run, rendered):
    scene, out = tiny_run
    info = json.loads((out / "views.json").read_text())
    assert info["test"] and rendered["targets"] == info["test"]
    W, H = info["size"]
    for v in info["test"]:
        for f in (f"renders/{v}.png", f"renders/depth/{v}.png", f"renders/normals/{v}.png",
                  f"renders_ibr/{v}.png"):
            img = read_image(out / f)
            assert img.shape == (3, H, W), f
        d = np.load(out / "renders" / "depth" / f"{v}.npy")
        assert d.shape == (H, W) and np.isfinite(d).all() and (d >= 0).all()
    assert rendered["seconds_per_view"] > 0


def test_ibr_differs_from_volume_render_and_beats_grey(tiny_run, rendered):
    """On a held-out view: the IBR image is not the volume render, and its masked PSNR against
    the ground truth is no worse than that of a uniform grey image."""
    scene, out = tiny_run
    v = rendered["targets"][0]
    gt_scene = load_scene(scene, views=[v])
    gt = gt_scene.images[0]
    assert gt_scene.masks is not None  # the synthetic scene has object masks
    mask = gt_scene.masks[0, 0]
    vol = read_image(out / "renders" / f"{v}.png")
    ibr = read_image(out / "renders_ibr" / f"{v}.png")
    assert (vol - ibr).abs().max() > 1e-2
    grey = torch.full_like(gt, 0.5)
    assert float(masked_psnr(ibr, gt, mask)) >= float(masked_psnr(grey, gt, mask))
    assert float(masked_psnr(ibr, gt, mask)) > 10.0


def test_orbit_frames_video_and_size(tiny_run):
    scene, out = tiny_run
    res = render_outputs(out, path="orbit", frames=3, size=(32, 24), progress=False)
    frames = sorted((out / "renders" / "orbit").glob("*.png"))
    assert [f.name for f in frames] == ["000.png", "001.png", "002.png"]
    assert read_image(frames[0]).shape == (3, 24, 32)
    assert res["video"].is_file() and res["video"].suffix in (".mp4", ".gif")
    assert res["video"].stat().st_size > 100 and res["size"] == [32, 24]


def test_cli_views_and_size(tiny_run):
    scene, out = tiny_run
    inputs = json.loads((out / "views.json").read_text())["inputs"]
    cli_main(["render", str(out), "--views", str(inputs[0]), "--size", "40x30"])
    assert read_image(out / "renders" / f"{inputs[0]}.png").shape == (3, 30, 40)


def test_unfinished_run_is_an_input_error(tmp_path, tiny_run):
    with pytest.raises(InputError, match=str(tmp_path)):
        open_run(tmp_path)
    scene, out = tiny_run
    half = tmp_path / "half"
    half.mkdir()
    for f in ("config.yaml", "views.json"):
        (half / f).write_text((out / f).read_text())
    with pytest.raises(InputError, match="half"):
        render_outputs(half, progress=False)
    with pytest.raises(SystemExit) as e:
        cli_main(["render", str(half)])
    assert e.value.code == 2


def test_unknown_view_is_an_input_error(tiny_run):
    scene, out = tiny_run
    with pytest.raises(InputError, match="999"):
        render_outputs(out, views=[999], progress=False)


def test_box_near_far_and_normals():
    K = torch.tensor([[[50.0, 0, 16], [0, 50.0, 12], [0, 0, 1]]], dtype=torch.float64)
    w2c = torch.eye(4, dtype=torch.float64)[None].clone()
    w2c[0, 2, 3] = 5.0  # camera 5 units in front of the origin, looking down +z
    cam = Cameras(K, w2c, 32, 24)
    nf = box_near_far(cam, torch.tensor([[-1.0, -1, -1], [1, 1, 1]]))
    assert torch.allclose(nf, torch.tensor([[4.0, 6.0]]))
    n = torch.zeros(2, 2, 3)
    n[..., 2] = -2.0  # facing the camera, not unit length
    img = camera_normals(n, torch.ones(2, 2), w2c[0])
    assert torch.allclose(img[:, 0, 0], torch.tensor([0.5, 0.5, 0.0]))



def test_mesh_depth_fill_fills_only_the_holes():
    """A plane z = 2 as two triangles seen by a camera looking down +z: holes take its depth,
    rendered depths stay, pixels the mesh misses stay 0."""
    from svolsdf.commands.render import mesh_depth_fill

    K = torch.tensor([[[20.0, 0, 16], [0, 20.0, 12], [0, 0, 1]]])
    cams = Cameras(K, torch.eye(4)[None], 32, 24)
    v = np.array([[-0.5, -0.5, 2], [0.5, -0.5, 2], [0.5, 0.5, 2], [-0.5, 0.5, 2]], float)
    f = np.array([[0, 1, 2], [0, 2, 3]])
    depth = torch.zeros(1, 24, 24 + 8)
    depth[0, :, :4] = 5.0  # rendered surface outside the plane's footprint
    depth[0, 12, 16] = 3.0  # rendered surface inside it
    out = mesh_depth_fill(depth, cams, v, f)
    assert float(out[0, 12, 16]) == 3.0  # a rendered depth is kept
    inner = out[0, 9:15, 12:20]  # the plane covers u 11..21, v 7..17
    assert torch.allclose(inner[inner != 3.0], torch.tensor(2.0))
    assert (out[0, :, :4] == 5.0).all()
    assert float(out[0, 0, 31]) == 0.0  # neither rendered nor on the mesh


def test_ibr_holes_mesh_warps_the_photos_where_the_field_is_empty(tiny_run, tmp_path):
    """--ibr-holes mesh: the IBR records the choice in ibr.json and is no worse on a held-out
    view (the tiny field has few holes; `mesh_depth_fill` is checked exactly above); a run
    without mesh.ply is refused, with exit 2, before anything is rendered."""
    import shutil

    from svolsdf.ibr import IBRConfig

    scene, out = tiny_run
    v = json.loads((out / "views.json").read_text())["test"][0]
    a = render_outputs(out, views=[v], ibr=True, progress=False,
                       ibr_config=IBRConfig(hole_depth="mesh"))
    assert a["ibr_files"]
    rec = json.loads((out / "renders_ibr" / "ibr.json").read_text())
    assert rec["hole_depth"] == "mesh"
    gt_scene = load_scene(scene, views=[v])
    with_mesh = read_image(out / "renders_ibr" / f"{v}.png")
    render_outputs(out, views=[v], ibr=True, progress=False)
    without = read_image(out / "renders_ibr" / f"{v}.png")
    m = gt_scene.masks[0, 0]
    assert float(masked_psnr(with_mesh, gt_scene.images[0], m)) >= \
        float(masked_psnr(without, gt_scene.images[0], m)) - 0.5
    bare = tmp_path / "bare"
    shutil.copytree(out, bare)
    (bare / "mesh.ply").unlink()
    before = sorted(p.name for p in (bare / "renders_ibr").iterdir())
    with pytest.raises(InputError, match="mesh.ply"):
        render_outputs(bare, views=[v], ibr=True, progress=False,
                       ibr_config=IBRConfig(hole_depth="mesh"))
    assert sorted(p.name for p in (bare / "renders_ibr").iterdir()) == before
    with pytest.raises(SystemExit) as e:
        cli_main(["render", str(bare), "--ibr", "--ibr-holes", "mesh"])
    assert e.value.code == 2


def test_report_and_evaluate_after_a_mesh_only_change_need_no_new_render(tiny_run, tmp_path,
                                                                         capsys):
    """A rerun that changes only the mesh's options keeps the field, so the renders are still
    the run's: report and evaluate take them without a new render; once the field itself is
    trained again they are refused."""
    import shutil

    from svolsdf.config import load_config, save_config

    _, src = tiny_run
    out = tmp_path / "run"
    shutil.copytree(src, out)
    for d in ("renders", "renders_ibr"):  # other tests' renders (other sizes) go
        shutil.rmtree(out / d, ignore_errors=True)
    render_outputs(out, views=[3], progress=False)
    cfg = load_config(out / "config.yaml")
    cfg.mesh.resolution = 40
    save_config(cfg, out / "config.yaml")
    cli_main(["reconstruct", "-o", str(out), "--config", str(out / "config.yaml"),
              "--no-progress"])
    capsys.readouterr()
    cli_main(["report", str(out)])
    assert "report " in capsys.readouterr().out
    cli_main(["evaluate", str(out), "--no-report"])
    m = json.loads((out / "metrics.json").read_text())
    assert m["settings"]["provenance"]["renders"].startswith("the current field")
    assert "3" in m["images"]["psnr"]["per_view"]
    torch.save({"changed": 1}, out / "field" / "model.pt")  # another field
    with pytest.raises(SystemExit) as e:
        cli_main(["report", str(out)])
    assert e.value.code == 2 and "renders came from an earlier config" in capsys.readouterr().err
