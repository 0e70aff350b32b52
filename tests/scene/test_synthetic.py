"""Synthetic scenes: determinism, speed, layout, and ground truth that agrees with the cameras."""

from __future__ import annotations

import hashlib
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from tests.conftest import shared_path

from svolsdf.cli import main as cli_main
from svolsdf.errors import InputError
from svolsdf.io.ply import read_ply
from svolsdf.scene.loaders import load_scene
from svolsdf.scene.synthetic import SynthConfig, make_synthetic_scene, parse_size


@pytest.fixture(autouse=True)
def _one_thread():
    # The machine is shared: one thread is faster than two contended ones for these small ops.
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def _digest(root: Path) -> dict[str, str]:
    return {p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def scene96(tmp_path_factory) -> tuple[Path, float]:
    """A default 3-view 96x72 scene and the seconds it took (speed: benchmarks/synth_speed.py)."""
    out = tmp_path_factory.mktemp("synth") / "s96"
    t0 = time.perf_counter()
    make_synthetic_scene(out, SynthConfig(views=3, width=96, height=72, seed=5))
    return out, time.perf_counter() - t0


def test_layout_and_loader(scene96):
    out, _ = scene96
    for rel in ("cameras.npz", "pair.txt", "gt_points.ply", "gt_mesh.ply", "scene.json"):
        assert (out / rel).is_file(), rel
    for i in range(3):
        assert (out / "image" / f"{i:06d}.png").is_file()
        assert (out / "mask" / f"{i:03d}.png").is_file()
        assert (out / "gt_depth" / f"{i:03d}.npy").is_file()
    s = load_scene(out)
    assert s.format == "idr"
    assert s.view_ids == [0, 1, 2]
    assert s.images.shape == (3, 3, 72, 96)
    assert s.masks is not None and s.masks.shape == (3, 1, 72, 96)
    assert 0.01 < float(s.masks.mean()) < 0.9  # the object is in view, not filling it
    pts = read_ply(out / "gt_points.ply")["points"]
    assert pts.shape[1] == 3 and len(pts) > 1000
    # depth range of the loader brackets the object's ground-truth depth
    for i in range(3):
        gt = np.load(out / "gt_depth" / f"{i:03d}.npy")
        obj = gt[s.masks[i, 0].numpy() > 0.5]
        near, far = s.depth_range[i].tolist()
        assert near < obj.min() and obj.max() < far


def test_gt_depth_agrees_with_cameras(scene96):
    """Back-project object pixels with gt_depth, reproject into another view: same 3D point."""
    out, _ = scene96
    s = load_scene(out)
    cams = s.cameras.to(dtype=torch.float64)
    depth = [torch.from_numpy(np.load(out / "gt_depth" / f"{i:03d}.npy")).double()
             for i in range(3)]
    # the gt points lie on surfaces the depth maps see: project them into view 0
    pts = torch.from_numpy(read_ply(out / "gt_points.ply")["points"]).double()
    uv, z = cams[0].project(pts)
    uv, z = uv[0], z[0]
    u, v = uv[:, 0].round().long(), uv[:, 1].round().long()
    inside = (u >= 1) & (u < 95) & (v >= 1) & (v < 71)
    d = torch.zeros_like(z)
    d[inside] = depth[0][v[inside], u[inside]]
    seen = inside & ((d - z).abs() < 0.01 * z)
    assert int(seen.sum()) > 200, "few gt points are seen by view 0 at their gt depth"

    # pixel centres of view 0 with object depth -> view 1 -> compare with view 1's gt depth
    m0 = s.masks[0, 0] > 0.5
    ys, xs = torch.nonzero(m0, as_tuple=True)
    sel = torch.linspace(0, len(ys) - 1, 50).long()
    uv0 = torch.stack([xs[sel], ys[sel]], -1).double()
    X = cams[0].unproject(uv0[None], depth[0][ys[sel], xs[sel]][None])[0]
    assert torch.allclose(cams[0].project(X[None])[0][0], uv0, atol=1e-6)
    uv1, z1 = cams[1].project(X)
    uv1, z1 = uv1[0], z1[0]
    # nearest-pixel lookup: compare within the depth change over one pixel on the surface
    u1, v1 = uv1[:, 0].round().long(), uv1[:, 1].round().long()
    ok = (u1 >= 0) & (u1 < 96) & (v1 >= 0) & (v1 < 72)
    d1 = depth[1][v1[ok], u1[ok]]
    agree = ((d1 - z1[ok]).abs() < 0.02 * z1[ok]).float().mean()
    assert agree > 0.6, f"only {float(agree):.0%} of reprojected points agree (occlusions aside)"


def test_deterministic_for_a_seed(tmp_path):
    cfg = SynthConfig(views=2, width=40, height=30, seed=3, gt_points=2000, supersample=1)
    a = make_synthetic_scene(tmp_path / "a", cfg)
    b = make_synthetic_scene(tmp_path / "b", cfg)
    da, db = _digest(a), _digest(b)
    assert da == db
    c = make_synthetic_scene(tmp_path / "c", SynthConfig(views=2, width=40, height=30, seed=4,
                                                         gt_points=2000, supersample=1))
    assert _digest(c)["image/000000.png"] != da["image/000000.png"]


def test_bad_input(tmp_path):
    with pytest.raises(InputError, match="object kind"):
        SynthConfig(object="teapot")
    with pytest.raises(InputError, match="WIDTHxHEIGHT"):
        parse_size("96by72")
    (tmp_path / "x").mkdir()
    (tmp_path / "x" / "keep.txt").write_text("mine")
    with pytest.raises(InputError, match="not a synthetic scene"):
        make_synthetic_scene(tmp_path / "x", SynthConfig(views=1, width=16, height=16))


def test_cli_synth(tmp_path, capsys):
    out = tmp_path / "cli"
    cli_main(["synth", str(out), "--views", "2", "--size", "32x24", "--seed", "1",
              "--object", "sphere"])
    assert (out / "gt_depth" / "001.npy").is_file()
    assert np.load(out / "gt_depth" / "000.npy").shape == (24, 32)
    with pytest.raises(SystemExit) as e:
        cli_main(["synth", str(tmp_path / "bad"), "--size", "32"])
    assert e.value.code == 2
    assert "WIDTHxHEIGHT" in capsys.readouterr().err


def test_cli_synth_refuses_a_negative_seed_in_one_line(tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        cli_main(["synth", str(tmp_path / "neg"), "--seed", "-1", "--views", "2",
                  "--size", "32x24"])
    err = capsys.readouterr().err
    assert e.value.code == 2 and len(err.strip().splitlines()) == 1
    assert "--seed" in err and "-1" in err
    assert not (tmp_path / "neg").exists()


def test_cameras_from_a_real_scene(tmp_path):
    dtu = shared_path("data", "dtu_scan65")
    out = make_synthetic_scene(tmp_path / "b", SynthConfig(
        width=64, height=48, cameras_from=str(dtu), camera_views=[25, 22], gt_points=2000,
        supersample=1))
    s = load_scene(out)
    real = load_scene(dtu, views=[25, 22], image_size=(64, 48), load_images=False)
    assert torch.allclose(s.cameras.K.double(), real.cameras.K.double(), rtol=1e-5, atol=1e-4)
    assert torch.allclose(s.cameras.w2c.double(), real.cameras.w2c.double(), atol=1e-3)


def test_info_reads_the_units_scene_json_declares(scene96, capsys):
    """A synthetic scene's scene.json says "units": "mm": the loader and `svolsdf info` say mm,
    not "units unknown"; a scene.json that names none leaves them unknown."""
    import json
    import shutil

    out, _ = scene96
    assert json.loads((out / "scene.json").read_text())["units"] == "mm"
    assert load_scene(out, load_images=False).units == "mm"
    cli_main(["info", str(out)])
    printed = capsys.readouterr().out
    assert "units        mm" in printed and "unknown" not in printed
    other = out.parent / "no_units"
    shutil.copytree(out, other)
    meta = json.loads((other / "scene.json").read_text())
    meta["units"] = "as in cameras_from"
    (other / "scene.json").write_text(json.dumps(meta))
    assert load_scene(other, load_images=False).units == "unknown"


def test_a_specular_object_gains_a_highlight_that_moves_with_the_view(tmp_path):
    """``specular``: the object's pixels only, never darker, a white highlight in some views,
    where it sits depends on the view (not consistent across views, as on metal); scene.json
    records it, and a Lambertian scene is written as before the option existed."""
    base = dict(views=3, width=64, height=48, seed=2, gt_points=2000, supersample=1,
                object="sphere", soft_shadows=False)
    a = make_synthetic_scene(tmp_path / "a", SynthConfig(**base))
    b = make_synthetic_scene(tmp_path / "b", SynthConfig(**base, specular=0.8, shininess=20))
    sa, sb = load_scene(a), load_scene(b)
    obj = sa.masks[:, 0] > 0.5  # (V, H, W)
    diff = (sb.images - sa.images).mean(1)  # (V, H, W)
    assert float(diff[~obj].abs().max()) == 0.0, "the highlight left the object"
    assert float(diff.min()) >= 0.0
    assert float(diff[obj].max()) > 0.2
    # the highlight's brightest pixel, back-projected with the exact depth, is a different
    # surface point in each view (a Lambertian colour would stay on one point)
    peaks = []
    for v in range(3):
        d = diff[v].masked_fill(~obj[v], -1)
        i = int(d.argmax())
        y, x = divmod(i, d.shape[1])
        z = float(np.load(b / "gt_depth" / f"{v:03d}.npy")[y, x])
        cam = sb.cameras[[v]].to(dtype=torch.float64)
        peaks.append(cam.unproject(torch.tensor([[[x + 0.5, y + 0.5]]], dtype=torch.float64),
                                   torch.tensor([[z]], dtype=torch.float64))[0, 0])
    spread = max(float((p - q).norm()) for p in peaks for q in peaks)
    assert spread > 0.05 * float(np.linalg.norm(np.ptp(read_ply(b / "gt_points.ply")["points"],
                                                        axis=0)))
    import json

    assert json.loads((b / "scene.json").read_text())["config"]["specular"] == 0.8
    assert "specular" not in json.loads((a / "scene.json").read_text())["config"]
    from svolsdf.scene.synthetic import made_with

    assert made_with(a, SynthConfig(**base)) and not made_with(a, SynthConfig(**base, specular=0.8))
    assert made_with(b, SynthConfig(**base, specular=0.8, shininess=20))
    assert not made_with(b, SynthConfig(**base))
    with pytest.raises(InputError, match="--specular"):
        SynthConfig(specular=1.5)
    with pytest.raises(InputError, match="--shininess"):
        SynthConfig(shininess=0)
