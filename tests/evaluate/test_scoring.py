"""End-to-end test of `svolsdf evaluate` on a fake run folder built in tmp_path."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from PIL import Image

from conftest import shared_path
from svolsdf.cli import main
from svolsdf.errors import InputError
from svolsdf.evaluate.images import masked_psnr
from svolsdf.evaluate.scoring import EvaluateConfig, evaluate_run
from svolsdf.io.ply import write_mesh_ply, write_points_ply
from svolsdf.scene.loaders import load_scene

W, H = 48, 40


def _scene(root):
    """A three-view IDR scene with masks (random pixels; cameras only need to be valid)."""
    rng = np.random.default_rng(0)
    (root / "image").mkdir(parents=True)
    (root / "mask").mkdir()
    cams = {}
    for i in range(3):
        Image.fromarray((rng.random((H, W, 3)) * 255).astype(np.uint8)).save(
            root / "image" / f"{i:06d}.png")
        m = np.zeros((H, W), np.uint8)
        m[6:34, 8:40] = 255
        Image.fromarray(m).save(root / "mask" / f"{i:03d}.png")
        K = np.array([[60.0, 0, 24], [0, 60, 20], [0, 0, 1]])
        P = np.eye(4)
        P[:3] = K @ np.c_[np.eye(3), [i * 10.0, 0, 500]]
        cams[f"world_mat_{i}"] = P
        cams[f"scale_mat_{i}"] = np.diag([100.0, 100, 100, 1])
    np.savez(root / "cameras.npz", **cams)
    return root


def _run(tmp_path):
    scene = _scene(tmp_path / "scene")
    out = tmp_path / "out"
    for d in ("renders", "renders_ibr", "depth", "normals"):
        (out / d).mkdir(parents=True)
    (out / "config.yaml").write_text(f"scene:\n  path: {scene}\n  views: [0, 1]\n")
    (out / "timing.json").write_text(json.dumps({"optimize": 12.5, "mvs": 3.0}))
    g = np.stack(np.meshgrid(np.arange(10.0), np.arange(10.0), [0.0]), -1).reshape(-1, 3)
    np.save(tmp_path / "gt.npy", g)
    write_points_ply(out / "points.ply", g + [0, 0, 0.5],
                     rgb=np.full((len(g), 3), 200, np.uint8))
    v = np.array([[0, 0, 0], [9, 0, 0], [0, 9, 0], [9, 9, 0]], float)
    write_mesh_ply(out / "mesh.ply", v, np.array([[0, 1, 3], [0, 3, 2]]))
    gts = load_scene(scene, views=[1, 2])
    rng = np.random.default_rng(1)
    for k, vid in enumerate((1, 2)):
        pred = (gts.images[k] + 0.05 * torch.from_numpy(rng.standard_normal((3, H, W)))).clamp(
            0, 1)
        a = (pred.permute(1, 2, 0).numpy() * 255 + 0.5).astype(np.uint8)
        Image.fromarray(a).save(out / "renders" / f"{vid}.png")
        Image.fromarray(a).save(out / "renders_ibr" / f"{vid}.png")
    Image.fromarray(np.zeros((H, W, 3), np.uint8)).save(out / "depth" / "0.png")
    Image.fromarray(np.full((H, W, 3), 128, np.uint8)).save(out / "normals" / "0.png")
    return out, tmp_path / "gt.npy", scene


def test_evaluate_writes_metrics_and_report(tmp_path):
    out, gt, scene = _run(tmp_path)
    m = evaluate_run(EvaluateConfig(out=out, gt_points=gt, threshold=0.6, lpips_net="alex",
                                    lpips_weights=shared_path("weights", "lpips")))
    on_disk = json.loads((out / "metrics.json").read_text())
    assert on_disk == m
    assert set(m["chamfer"]) >= {"accuracy", "completeness", "overall"}
    assert m["chamfer"]["accuracy"] == pytest.approx(0.5)
    assert m["chamfer"]["overall"] == pytest.approx(0.5)
    assert m["fscore"] == 1.0 and m["fscore_threshold"] == 0.6
    assert m["chamfer_mesh"]["protocol"] == "generic-mesh"
    assert m["chamfer_mesh"]["overall"] < 0.2
    # Image metrics: per view, against the masked ground truth; view 1 is an input of the run
    # (config.yaml: views [0, 1]), scored under its own label, view 2 is the novel one.
    gts = load_scene(scene, views=[1, 2])
    for k, (vid, key) in enumerate(((1, "images_input_views"), (2, "images"))):
        pred = torch.from_numpy(np.array(Image.open(out / "renders" / f"{vid}.png"),
                                         np.float32) / 255).permute(2, 0, 1)
        want = masked_psnr(pred, gts.images[k], gts.masks[k])
        assert m[key]["psnr"]["per_view"][str(vid)] == pytest.approx(want, rel=1e-6)
    for key in ("psnr", "ssim", "lpips"):
        blk = m["images"][key]
        assert set(blk["per_view"]) == {"2"}
        assert set(m["images_input_views"][key]["per_view"]) == {"1"}
        assert blk["mean"] == pytest.approx(blk["per_view"]["2"])
        assert m["images_ibr"][key]["mean"] == pytest.approx(blk["mean"])
    assert m["views"] == {"inputs": [0, 1], "novel_scored": [2], "input_scored": [1]}
    assert m["settings"]["image_region"].startswith("inside the object mask")
    assert 0 < m["images"]["ssim"]["mean"] < 1 and m["images"]["lpips"]["mean"] > 0
    assert m["timing"]["optimize"] == 12.5 and m["timing"]["evaluate_seconds"] > 0
    page = (out / "report.html").read_text()
    assert '<table id="metrics">' in page and "Chamfer overall" in page
    assert "src=\"data:image/png;base64," in page
    for section in ("3D view", "Input views and the mesh", "Depth maps", "Normal maps",
                    "Novel views"):
        assert f"<h2>{section}" in page, section


def test_evaluate_without_ground_truth_gives_nulls(tmp_path):
    out = tmp_path / "points_only_run"
    out.mkdir()
    write_points_ply(out / "points.ply", np.random.default_rng(0).random((50, 3)))
    m = evaluate_run(EvaluateConfig(out=out, report=False))
    assert m["chamfer"]["overall"] is None and m["fscore"] is None
    assert m["images"]["psnr"] == {"mean": None, "per_view": {},
                                   "missing": "no renders/<view id>.png"}
    assert m["images"]["lpips"]["mean"] is None and "evaluate_seconds" in m["timing"]
    assert not (out / "report.html").exists()


def test_a_folder_that_is_not_a_run_is_refused_and_left_alone(tmp_path, capsys):
    scene = _scene(tmp_path / "scene")
    before = sorted(p.name for p in scene.rglob("*"))
    for folder in (scene, tmp_path / "empty"):
        folder.mkdir(exist_ok=True)
        with pytest.raises(SystemExit) as e:
            main(["evaluate", str(folder)])
        err = capsys.readouterr().err
        assert e.value.code == 2 and "not a run folder" in err and len(err.splitlines()) == 1
        assert not (folder / "metrics.json").exists() and not (folder / "report.html").exists()
    assert sorted(p.name for p in scene.rglob("*")) == before


def test_missing_default_lpips_weights_still_score_geometry_and_other_image_metrics(
        tmp_path, capsys, monkeypatch):
    import svolsdf.evaluate.lpips as lpips_module
    from svolsdf.errors import InputError as _InputError

    def nowhere(*args, **kwargs):
        raise _InputError("LPIPS weights not found; looked in nowhere")

    # no whole LPIPS weights beside the repository, and torchvision's backbone not downloadable
    monkeypatch.setattr(lpips_module, "default_lpips_dir", nowhere)
    monkeypatch.setattr(lpips_module, "backbone_file", nowhere)
    monkeypatch.delenv(lpips_module.BACKBONE_ENV, raising=False)
    out, gt, _ = _run(tmp_path)
    main(["evaluate", str(out), "--gt-points", str(gt), "--no-report"])  # returns: exit 0
    printed = capsys.readouterr().out
    m = json.loads((out / "metrics.json").read_text())
    assert m["chamfer"]["overall"] is not None and m["fscore"] is not None
    assert m["images"]["psnr"]["mean"] > 10 and m["images"]["ssim"]["mean"] > 0
    lp = m["images"]["lpips"]
    assert lp["mean"] is None and "looked in nowhere" in lp["missing"]
    assert "LPIPS" in lp["missing"]
    assert m["images"]["psnr"]["missing"] is None
    assert m["missing"]["images.lpips"] == lp["missing"] and "images.psnr" not in m["missing"]
    assert "not computed: images.lpips, images_ibr.lpips: LPIPS not computed" in printed


@pytest.mark.parametrize("kind", ["absent", "garbage", "folder_without_file"])
def test_unreadable_lpips_weights_given_are_an_error_naming_the_file(tmp_path, capsys, kind):
    """--lpips-weights that cannot be read: exit 2 naming the file, before any output, not a
    warning and a null LPIPS."""
    out, gt, _ = _run(tmp_path)
    weights = tmp_path / "w.pth"
    if kind == "garbage":
        weights.write_bytes(b"not a torch file")
    elif kind == "folder_without_file":
        weights = tmp_path / "weights_dir"
        weights.mkdir()
    with pytest.raises(SystemExit) as e:
        main(["evaluate", str(out), "--gt-points", str(gt), "--lpips-weights", str(weights),
              "--no-report"])
    err = capsys.readouterr().err
    assert e.value.code == 2 and len(err.strip().splitlines()) == 1
    assert str(weights) in err
    assert not (out / "metrics.json").exists()


def test_a_scene_folder_that_moved_says_which_metrics_are_missing_and_why(tmp_path, capsys):
    """A run whose scene folder is gone: every metric that needs it is null with the reason
    (the folder and the way out), in metrics.json and on the terminal; what does not need it
    is still scored."""
    out, gt, scene = _run(tmp_path)
    scene.rename(tmp_path / "scene_moved")
    main(["evaluate", str(out), "--no-report"])  # returns: exit 0
    printed = capsys.readouterr().out
    m = json.loads((out / "metrics.json").read_text())
    assert m["chamfer"]["overall"] is None and m["images"]["psnr"]["mean"] is None
    for key in ("chamfer", "fscore", "chamfer_mesh", "images.psnr", "images_ibr.lpips"):
        assert str(scene) in m["missing"][key] and "does not exist" in m["missing"][key], key
    assert m["chamfer"]["missing"] == m["missing"]["chamfer"]
    assert "--gt-points" in m["missing"]["chamfer"] and "--scene" in m["missing"]["images.ssim"]
    assert "not computed: chamfer, fscore, chamfer_mesh: " in printed and str(scene) in printed
    # with the ground truth given, geometry is scored and only the images stay missing
    main(["evaluate", str(out), "--gt-points", str(gt), "--no-report"])
    m = json.loads((out / "metrics.json").read_text())
    assert m["chamfer"]["overall"] is not None and m["chamfer"]["missing"] is None
    assert "chamfer" not in m["missing"] and "fscore" not in m["missing"]
    assert str(scene) in m["missing"]["images.psnr"]


def test_an_mvs_output_folder_is_scored_against_its_synthetic_scene(tmp_path, capsys):
    """The output folder of `svolsdf mvs` names its scene and views in mvs.json only: evaluate
    scores it against that synthetic scene's ground truth, not all nulls."""
    from svolsdf.commands.mvs import MVSJobConfig, run_mvs
    from svolsdf.scene.synthetic import SynthConfig, make_synthetic_scene

    scene = tmp_path / "syn"
    make_synthetic_scene(scene, SynthConfig(views=3, width=48, height=36, seed=2,
                                            object="sphere", supersample=1, gt_points=5000))
    out = tmp_path / "mvs_out"
    run_mvs(MVSJobConfig(scene=scene, out=out, views=[0, 1, 2]))
    assert not (out / "config.yaml").exists() and not (out / "views.json").exists()
    main(["evaluate", str(out), "--no-report"])
    printed = capsys.readouterr().out
    m = json.loads((out / "metrics.json").read_text())
    assert m["chamfer"]["protocol"] == "synthetic" and m["chamfer"]["overall"] is not None
    # each number says its protocol; a missing one says why, never a bare None
    assert "None" not in printed and "points.ply Chamfer [the synthetic scene's own" in printed
    for key in ("chamfer_mesh", "images.psnr", "images_ibr.ssim"):
        assert "an svolsdf mvs folder" in m["missing"][key], key
    assert "not computed: chamfer_mesh: no mesh.ply with faces in the run folder: an svolsdf " \
           "mvs folder" in printed
    assert m["settings"]["synthetic"]["input_views"] == [0, 1, 2]
    assert "chamfer" not in m["missing"] and m["fscore"] is not None
    # a scene that has no ground truth of its own: said so, with the way out
    other = tmp_path / "no_gt"
    _scene(other)
    (out / "mvs.json").write_text(json.dumps({"scene": str(other), "views": [0, 1]}))
    main(["evaluate", str(out), "--no-report"])
    assert "not a svolsdf synth scene" in capsys.readouterr().out
    m = json.loads((out / "metrics.json").read_text())
    assert str(other) in m["missing"]["chamfer"] and "--gt-points" in m["missing"]["chamfer"]


def test_cli_errors_are_one_line(tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        main(["evaluate", str(tmp_path / "nope")])
    assert e.value.code == 2
    assert "run folder does not exist" in capsys.readouterr().err
    write_points_ply(tmp_path / "points.ply", np.random.default_rng(0).random((50, 3)))
    with pytest.raises(InputError, match="ObsMask9_10.mat"):
        evaluate_run(EvaluateConfig(out=tmp_path, dtu_gt=tmp_path, scan=9, report=False))


def test_a_synthetic_scene_scores_itself(tmp_path):
    """Without --gt-points / --dtu-gt, a run on a `svolsdf synth` scene is scored against the
    ground truth its input views (OUT/views.json) observe, as the benchmarks do."""
    from svolsdf.evaluate.synthetic import observed_gt_points, synthetic_chamfer
    from svolsdf.scene.synthetic import SynthConfig, make_synthetic_scene

    scene = tmp_path / "syn"
    make_synthetic_scene(scene, SynthConfig(views=4, width=64, height=48, seed=2,
                                            object="sphere", supersample=1, gt_points=5000))
    out = tmp_path / "run"
    out.mkdir()
    (out / "config.yaml").write_text(f"scene:\n  path: {scene}\n")
    (out / "views.json").write_text(json.dumps({"inputs": [0, 2, 3], "test": [1]}))
    gt = observed_gt_points(scene, [0, 2, 3])
    diag = float(np.linalg.norm(gt.max(0) - gt.min(0)))
    pred = gt[::2] + [0.0, 0.0, 0.002 * diag]  # half the observed surface, shifted
    write_points_ply(out / "points.ply", pred)
    m = evaluate_run(EvaluateConfig(out=out, report=False))
    want = synthetic_chamfer(pred, scene, [0, 2, 3])
    assert m["chamfer"]["protocol"] == "synthetic" and m["chamfer"]["source"] == "points.ply"
    for k in ("accuracy", "completeness", "overall"):
        assert m["chamfer"][k] == pytest.approx(want[k], rel=1e-5)  # PLY stores float32
    assert m["chamfer"]["accuracy"] == pytest.approx(0.002 * diag, rel=0.05)
    assert m["chamfer"]["overall_dtu_rule"] == pytest.approx(
        synthetic_chamfer(pred, scene, [0, 2, 3], rule="exclude")["overall"], rel=1e-5)
    assert m["fscore"] == pytest.approx(want["fscore"], abs=1e-3)
    assert m["settings"]["synthetic"]["input_views"] == [0, 2, 3]
    assert m["chamfer_mesh"]["overall"] is None  # no mesh.ply
    # an explicit --gt-points still wins
    np.save(tmp_path / "gt.npy", gt)
    m2 = evaluate_run(EvaluateConfig(out=out, gt_points=tmp_path / "gt.npy", report=False))
    assert m2["chamfer"]["protocol"] == "generic"


def test_a_mesh_is_scored_by_its_surface_with_a_flap_charged(tmp_path):
    """`svolsdf evaluate` scores mesh.ply by its surface (`mesh_surface_points` at
    `mesh_density` of the observed ground truth's diagonal, through `synthetic_chamfer`), says
    so in metrics.json, and so charges a large triangle extrapolated past the object's
    silhouette that vertex scoring, the old way, hardly sees."""
    from svolsdf.evaluate.chamfer import mesh_density
    from svolsdf.evaluate.synthetic import observed_gt_points, synthetic_chamfer
    from svolsdf.io.ply import read_ply
    from svolsdf.scene.synthetic import SynthConfig, make_synthetic_scene

    scene = tmp_path / "syn"
    make_synthetic_scene(scene, SynthConfig(views=4, width=64, height=48, seed=2,
                                            object="sphere", supersample=1, gt_points=5000))
    views = [0, 2, 3]
    gt = observed_gt_points(scene, views)
    diag = float(np.linalg.norm(gt.max(0) - gt.min(0)))
    m = read_ply(scene / "gt_mesh.ply")
    v, f = m["points"].astype(np.float64), m["faces"]
    cap = f[v[f].mean(1)[:, 2] > v[:, 2].max() - 2]  # the sphere's top, ~800 mm^2
    used = np.unique(cap)
    rim = used[[np.argmin(v[used, 1]), np.argmax(v[used, 1])]]  # the cap's -y and +y ends
    tip = v[rim].mean(0) + [60.0, 0.0, 0.0]  # ~40 mm past the silhouette, above the table
    v_flap = np.concatenate([v, tip[None]])
    f_flap = np.concatenate([cap, [[rim[0], rim[1], len(v)]]])
    out = tmp_path / "run"
    out.mkdir()
    (out / "config.yaml").write_text(f"scene:\n  path: {scene}\n")
    (out / "views.json").write_text(json.dumps({"inputs": views, "test": [1]}))
    write_mesh_ply(out / "mesh.ply", v_flap, f_flap)
    metrics = evaluate_run(EvaluateConfig(out=out, report=False))
    cm = metrics["chamfer_mesh"]
    assert cm["protocol"] == "synthetic" and cm["source"] == "mesh.ply"
    assert cm["sampled"] == "surface"
    assert cm["density"] == pytest.approx(mesh_density(diag)) == pytest.approx(diag / 1000)
    v32 = v_flap.astype(np.float32)  # the PLY holds float32
    want = synthetic_chamfer(v32, scene, views, faces=f_flap, on_empty="clip")
    for k in ("accuracy", "completeness", "overall", "overall_dtu_rule"):
        assert cm[k] == pytest.approx(want[k], rel=1e-9)
    no_flap = synthetic_chamfer(v, scene, views, faces=cap)
    assert want["accuracy"] > no_flap["accuracy"] + 0.7  # half of the surface, off the object
    assert want["overall"] > no_flap["overall"] + 0.3
    by_vertices = [synthetic_chamfer(x, scene, views)["accuracy"]
                   for x in (v[used], np.concatenate([v[used], tip[None]]))]
    assert abs(by_vertices[1] - by_vertices[0]) < 0.05  # one vertex among ~300
    assert metrics["settings"]["synthetic"]["input_views"] == views


@pytest.mark.parametrize("kind", ["nan", "inf", "empty", "one_point"])
def test_unusable_ground_truth_is_refused_naming_the_file_and_the_problem(tmp_path, capsys,
                                                                         kind):
    """NaN, infinite, empty or sizeless ground truth: one line naming the file and what is wrong
    with it, not 'F-score threshold must be > 0, got nan' or an unnamed 'no points'."""
    out, _, _ = _run(tmp_path)
    g = np.random.default_rng(0).random((20, 3))
    if kind == "nan":
        g[3, 1] = np.nan
    elif kind == "inf":
        g[5, 0] = np.inf
    elif kind == "empty":
        g = g[:0]
    else:
        g = g[:1]
    gt = tmp_path / f"gt_{kind}.npy"
    np.save(gt, g)
    with pytest.raises(SystemExit) as e:
        main(["evaluate", str(out), "--gt-points", str(gt), "--no-report"])
    err = capsys.readouterr().err
    assert e.value.code == 2 and len(err.strip().splitlines()) == 1
    assert f"gt_{kind}.npy" in err
    want = {"nan": "NaN or infinite", "inf": "NaN or infinite", "empty": "no points",
            "one_point": "one position"}[kind]
    assert want in err and "threshold must be" not in err
    assert not (out / "metrics.json").exists()
    if kind != "one_point":  # the same check guards a PLY file
        write_points_ply(tmp_path / "gt.ply", g)
        with pytest.raises(InputError, match=f"gt.ply.*{want}"):
            evaluate_run(EvaluateConfig(out=out, gt_points=tmp_path / "gt.ply", report=False))


def test_evaluate_during_a_running_reconstruct_names_the_lock_not_a_stopped_run(tmp_path,
                                                                                capsys):
    """While a reconstruction writes the folder (a rerun with new options: config.yaml is new,
    points.ply the last config's; or a first run with no outputs yet), evaluate and report say
    the run is in progress and who holds the lock, not that it stopped or is not a run; render
    too."""
    import subprocess
    import sys

    out, gt, _ = _run(tmp_path)
    (out / "stages.json").write_text(json.dumps(
        {"provenance": {"fusion": {"config": "an earlier config"},
                        "mesh": {"config": "an earlier config"}}}))
    fresh = tmp_path / "fresh"
    fresh.mkdir()
    (fresh / "config.yaml").write_text((out / "config.yaml").read_text())
    holders = []
    try:
        for folder in (out, fresh):
            p = subprocess.Popen([sys.executable, "-c", (
                "import fcntl, os, sys, time\n"
                f"f = open({str(folder / '.svolsdf.lock')!r}, 'a+')\n"
                "fcntl.flock(f.fileno(), fcntl.LOCK_EX)\n"
                "f.write(f'svolsdf reconstruct, pid {os.getpid()}'); f.flush()\n"
                "print('held', flush=True); time.sleep(120)\n")],
                stdout=subprocess.PIPE, text=True)
            holders.append(p)
            assert p.stdout.readline().strip() == "held"
            for argv in (["evaluate", str(folder), "--gt-points", str(gt)],
                         ["report", str(folder)], ["render", str(folder)]):
                with pytest.raises(SystemExit) as e:
                    main(argv)
                err = capsys.readouterr().err
                assert e.value.code == 2 and len(err.strip().splitlines()) == 1, err
                assert "in progress" in err and f"svolsdf reconstruct, pid {p.pid}" in err
                assert str(folder / ".svolsdf.lock") in err
                assert "stopped" not in err and "not a run folder" not in err
            assert not (folder / "metrics.json").exists()
    finally:
        for p in holders:
            p.kill()
            p.wait()
    # once the run has ended the lock is free: the earlier-config refusal is what remains
    with pytest.raises(InputError, match="earlier config"):
        evaluate_run(EvaluateConfig(out=out, gt_points=gt, report=False))


def test_input_views_rendered_back_are_never_scored_as_novel_views(tmp_path, capsys):
    """Three views, all inputs: `render` falls back to them. Their scores go under their own
    label, no novel-view mean counts them (null, with the reason), metrics.json says which views
    were inputs, and neither the terminal nor the report calls them novel views."""
    out, gt, scene = _run(tmp_path)
    (out / "config.yaml").write_text(f"scene:\n  path: {scene}\n  views: [0, 1, 2]\n")
    main(["evaluate", str(out), "--gt-points", str(gt)])
    printed = capsys.readouterr().out
    m = json.loads((out / "metrics.json").read_text())
    assert m["views"] == {"inputs": [0, 1, 2], "novel_scored": [], "input_scored": [1, 2]}
    for key in ("images", "images_ibr"):
        for metric in ("psnr", "ssim", "lpips"):
            assert m[key][metric]["mean"] is None and m[key][metric]["per_view"] == {}
            assert "input view" in m["missing"][f"{key}.{metric}"]
        assert set(m[f"{key}_input_views"]["psnr"]["per_view"]) == {"1", "2"}
        assert m[f"{key}_input_views"]["psnr"]["mean"] > 20
    assert "input views (trained on, not novel), volume rendering [1, 2]" in printed
    assert "novel views," not in printed and "None" not in printed
    page = (out / "report.html").read_text()
    assert "<h2>Novel views" not in page and "<h2>Input views rendered back" in page
    assert "PSNR mean (input views, volume rendering)" in page
    assert "input view (trained on)" in page and "novel (held out)" not in page
    assert "[inside the object mask" in printed and "; inside the object mask" in page
    assert "mean absolute RGB error (inside the object mask)" in page
