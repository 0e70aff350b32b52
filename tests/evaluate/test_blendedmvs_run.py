"""``svolsdf evaluate RUN --protocol blendedmvs --gt-points GT [--volsdf VOLSDF_RUN]``
(svolsdf.evaluate.blendedmvs_run) on runs of a synthetic scene written in the BlendedMVS layout
(its mask folder holds views 0, 1 and 3 of five; the runs use views 0, 1, 2): the masked and
unmasked Chamfer recorded and printed are those of the protocol's functions called directly,
the relative improvement over a VolSDF run, the scale from --scan, and the refusals."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from tests.evaluate.bmvs_layout import MASKED, write_bmvs_layout, write_ground_truth

from svolsdf.cli import main
from svolsdf.evaluate.blendedmvs import (
    blendedmvs_chamfer,
    fit_ground_plane,
    protocol,
    relative_improvement,
)
from svolsdf.io.ply import read_ply
from svolsdf.scene.loaders import load_scene

VIEWS = [0, 1, 2]  # view 2 has no mask: the runs use none, the evaluation the folder's


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """{"scene", "src" (the IDR synthetic scene it was written from), "gt", "run" (mvs-only),
    "volsdf" (mode volsdf, 10 steps)}: seconds-long runs of the BlendedMVS-layout scene, and
    its ground truth with the table (gt.ply)."""
    root = tmp_path_factory.mktemp("bmvs_runs")
    scene, src = write_bmvs_layout(root, "bmvs_synthetic")  # no scan in its name
    write_ground_truth(src, root / "gt.ply")
    out = {"scene": scene, "src": src, "gt": root / "gt.ply"}
    for name, mode in (("run", "mvs-only"), ("volsdf", "volsdf")):
        mesh = ("" if mode == "mvs-only" else  # the field's own coarse mesh: fast
                "mesh: {resolution: 24, method: field, fit_points: 0, free_space: false, "
                "support: 0.0}\n")
        (root / f"{name}.yaml").write_text(
            f"scene: {{path: {scene}, views: {VIEWS}}}\n"
            "field: {grid_start_resolution: 16, grid_resolution: 16}\n" + mesh +
            "fusion: {unguided: false}\n"
            f"train: {{rays: 32, checkpoint_every: 0, steps: 10, mode: {mode}}}\n")
        main(["reconstruct", "-o", str(root / name), "--config", str(root / f"{name}.yaml"),
              "--no-progress"])
        out[name] = root / name
    return out


def _direct(runs, run: str, max_dist: float = 20.0, masked_views: list[int] = MASKED,
            masks=None) -> tuple[dict, tuple]:
    """The protocol's functions called on the files: (blendedmvs_chamfer's result, plane);
    the masks of ``masked_views`` from the layout's folder, or with ``masks`` the IDR scene's."""
    gt = read_ply(runs["gt"])["points"].astype(np.float64)
    pred = read_ply(runs[run] / "points.ply")["points"]
    centre = load_scene(runs["scene"], load_images=False).cameras.centers.numpy().mean(0)
    unit = max_dist / 20  # the plane's band and margin: 1 and 2 DTU-like millimetres
    plane = fit_ground_plane(gt, centre, threshold=unit)
    ev = load_scene(runs["scene"] if masks is None else masks, views=masked_views)
    masked = {"K": ev.cameras.K.numpy(), "w2c": ev.cameras.w2c.numpy(),
              "masks": [m[0].numpy() > 0.5 for m in ev.masks]}
    return blendedmvs_chamfer(pred, gt, plane, 2 * unit, max_dist, masked=masked), plane


def _same(block: dict, res: dict) -> None:
    for k in ("accuracy", "completeness", "overall", "n_pred", "n_gt"):
        assert block[k] == pytest.approx(res[k], rel=1e-9), k


def _evaluate(runs, *extra, report: bool = False) -> dict:
    main(["evaluate", str(runs["run"]), "--protocol", "blendedmvs", "--gt-points",
          str(runs["gt"]), "--report" if report else "--no-report", *map(str, extra)])
    return json.loads((runs["run"] / "metrics.json").read_text())


def test_masked_and_unmasked_chamfer_are_the_protocols(runs, capsys):
    m = _evaluate(runs, "--max-dist", 20)
    printed = capsys.readouterr().out
    res, plane = _direct(runs, "run")
    b = m["blendedmvs"]
    _same(b["unmasked"], res["unmasked"])
    _same(b["masked"], res["masked"])
    assert b["unmasked"]["protocol"] == m["chamfer"]["protocol"] == "blendedmvs"
    assert b["masked"]["protocol"] == "blendedmvs-masked"
    assert m["chamfer"]["overall"] == b["unmasked"]["overall"]
    assert b["plane"]["normal"] == pytest.approx(plane[0].tolist(), abs=1e-9)
    assert b["plane"]["margin"] == 2.0 and b["max_dist"] == 20.0 and b["scan"] is None
    # the partial mask folder: the masks of views 0, 1, 3 of five; they remove points
    assert b["masked_views"] == MASKED
    assert b["masked"]["n_pred"] < b["unmasked"]["n_pred"]
    assert b["unmasked"]["n_gt"] < 6000  # the table (4000 points) is gone
    assert b["volsdf"] is None and b["relative_improvement"] is None
    assert m["missing"]["fscore"] == "the BlendedMVS protocol has no F-score"
    # each printed number says which protocol it follows
    u, k = b["unmasked"], b["masked"]
    assert ("points.ply Chamfer [BlendedMVS protocol, unmasked: the ground plane fitted to "
            "--gt-points") in printed and f"overall {u['overall']:.4g}" in printed
    assert (f"[BlendedMVS protocol, masked: as unmasked, both clouds kept inside the evaluation "
            f"masks of the views that see them (docs/method.md 8.2)]: accuracy "
            f"{k['accuracy']:.4g}, completeness {k['completeness']:.4g}, overall "
            f"{k['overall']:.4g}") in printed


def test_relative_improvement_over_a_volsdf_run_scored_the_same_way(runs, capsys):
    m = _evaluate(runs, "--max-dist", 20, "--volsdf", runs["volsdf"], report=True)
    printed = capsys.readouterr().out
    b = m["blendedmvs"]
    ours, _ = _direct(runs, "run")
    theirs, _ = _direct(runs, "volsdf")
    assert b["volsdf"]["run"] == str(runs["volsdf"])
    for key in ("unmasked", "masked"):
        _same(b[key], ours[key])
        _same(b["volsdf"][key], theirs[key])
        assert b["relative_improvement"][key] == pytest.approx(relative_improvement(
            ours[key]["overall"], theirs[key]["overall"]), rel=1e-9)
    rel = b["relative_improvement"]
    page = (runs["run"] / "report.html").read_text()
    assert "relative improvement over VolSDF (masked)" in page and \
        "Chamfer overall (points, masked)" in page
    assert (f"relative improvement over VolSDF, (VolSDF - run) / VolSDF of the overall Chamfer "
            f"[BlendedMVS protocol]: unmasked {100 * rel['unmasked']:.1f} %, masked "
            f"{100 * rel['masked']:.1f} %") in printed


def test_evaluation_masks_from_their_own_folder(runs, tmp_path):
    # the released data keeps BlendedMVS' evaluation masks apart from the scans: --eval-masks
    folder = tmp_path / "eval_mask"
    folder.mkdir()
    for v in (0, 4):
        shutil.copy(runs["scene"] / "mask" / f"{v:08d}.png" if v in MASKED else
                    runs["src"] / "mask" / f"{v:03d}.png", folder / f"{v:08d}.png")
    m = _evaluate(runs, "--max-dist", 20, "--eval-masks", folder)
    b = m["blendedmvs"]
    assert b["masked_views"] == [0, 4] and b["masks_from"] == "--eval-masks"
    res, _ = _direct(runs, "run", masked_views=[0, 4], masks=runs["src"])
    _same(b["masked"], res["masked"])
    _same(b["unmasked"], res["unmasked"])
    # an empty mask of a view that sees the whole object: no masked score, and why; the
    # unmasked score stands
    from PIL import Image

    empty = tmp_path / "empty"
    empty.mkdir()
    Image.new("L", (96, 72)).save(empty / "00000000.png")
    b = _evaluate(runs, "--max-dist", 20, "--eval-masks", empty)["blendedmvs"]
    assert b["masked"]["overall"] is None
    assert "0 ground-truth points above the ground plane and inside the evaluation masks" in \
        b["masked"]["missing"]
    _same(b["unmasked"], res["unmasked"])
    # masks of two sizes: refused before any work
    Image.new("L", (48, 36)).save(empty / "00000001.png")
    with pytest.raises(SystemExit) as e:
        _evaluate(runs, "--max-dist", 20, "--eval-masks", empty)
    assert e.value.code == 2


def test_the_cut_off_is_20_mm_at_the_scans_scale(runs):
    m = _evaluate(runs, "--scan", 3)
    b = m["blendedmvs"]
    scale = protocol(3)["relative_scale"]
    assert b["scan"] == 3 and b["relative_scale"] == scale
    assert b["max_dist"] == pytest.approx(20 * scale) and b["plane"]["margin"] == pytest.approx(
        2 * scale)
    # this millimetre scene is no BlendedMVS scan: at scan 3's scale every distance is beyond
    # the cut-off, and the record says so instead of a number
    assert b["unmasked"]["overall"] is None and "max_dist" in b["unmasked"]["missing"]


def test_a_run_without_points_is_refused(runs, tmp_path, capsys):
    run = tmp_path / "run"
    shutil.copytree(runs["volsdf"], run, ignore=shutil.ignore_patterns(".svolsdf.lock"))
    (run / "points.ply").unlink()  # mesh.ply left: a run folder still
    with pytest.raises(SystemExit) as e:
        main(["evaluate", str(run), "--protocol", "blendedmvs", "--gt-points",
              str(runs["gt"]), "--max-dist", "20"])
    err = capsys.readouterr().err
    assert e.value.code == 2 and f"{run / 'points.ply'}: no such file" in err
    assert len(err.strip().splitlines()) == 1 and not (run / "metrics.json").exists()


@pytest.mark.parametrize("argv, msg", [
    (["--protocol", "blendedmvs"], "--protocol blendedmvs needs --gt-points FILE"),
    (["--protocol", "blendedmvs", "--gt-points", "GT"], "pass --scan N (1-9) or --max-dist"),
    (["--protocol", "blendedmvs", "--gt-points", "GT", "--scan", "12"], "--scan 12: "),
    (["--protocol", "blendedmvs", "--gt-points", "GT", "--max-dist", "20", "--volsdf", "RUN"],
     "not a VolSDF run (its config.yaml has train.mode mvs-only)"),
    (["--protocol", "blendedmvs", "--gt-points", "GT", "--max-dist", "20", "--volsdf",
      "NOPE"], "--volsdf"),
    (["--gt-points", "GT", "--volsdf", "VOLSDF"], "add --protocol blendedmvs"),
    (["--protocol", "dtu"], "--protocol 'dtu': expected 'auto' or 'blendedmvs'"),
    (["--gt-points", "GT", "--eval-masks", "MASKS"], "add --protocol blendedmvs"),
    (["--protocol", "blendedmvs", "--gt-points", "GT", "--max-dist", "20", "--eval-masks",
      "MASKS"], "masks of views [7] that scene"),
])
def test_bad_input_exits_2_with_one_line_before_any_work(runs, capsys, tmp_path, argv, msg):
    masks = tmp_path / "masks"  # view 7 is no view of the five-view scene
    masks.mkdir()
    shutil.copy(runs["scene"] / "mask" / "00000000.png", masks / "00000007.png")
    names = {"GT": runs["gt"], "RUN": runs["run"], "VOLSDF": runs["volsdf"],
             "NOPE": tmp_path / "nope", "MASKS": masks}
    before = {p.name: p.stat().st_mtime_ns for p in runs["run"].iterdir()}
    with pytest.raises(SystemExit) as e:
        main(["evaluate", str(runs["run"]), *[str(names.get(a, a)) for a in argv]])
    err = capsys.readouterr().err
    assert e.value.code == 2 and msg in err and len(err.strip().splitlines()) == 1, err
    assert {p.name: p.stat().st_mtime_ns for p in runs["run"].iterdir()} == before
