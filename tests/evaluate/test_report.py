"""The HTML report: its 3D view, pictures and tables, `svolsdf report`, and the page in a real
browser (headless Chromium; skipped with the reason when no Chromium is installed)."""

from __future__ import annotations

import base64
import importlib.util
import json
import os
import re
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from headless_browser import browser_part_missing, chromium_path, load_page
from svolsdf.cli import main
from svolsdf.evaluate.run_report import write_run_report
from svolsdf.evaluate.viewer import (
    ViewerConfig,
    cluster_decimate,
    frustum_lines,
    scene_figure,
    subsample,
)
from svolsdf.io.ply import read_ply, write_mesh_ply, write_points_ply
from svolsdf.scene.loaders import load_scene
from svolsdf.scene.synthetic import SynthConfig, make_synthetic_scene

W, H = 64, 48


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A run folder on a synthetic scene, made from its ground truth (no reconstruction): noisy
    points, the ground-truth mesh with vertex colours, depth maps, renders and metrics."""
    root = tmp_path_factory.mktemp("report")
    scene = root / "scene"
    make_synthetic_scene(scene, SynthConfig(views=4, width=W, height=H, seed=3, supersample=1,
                                            gt_points=4000))
    out = root / "run"
    for d in ("depth", "normals", "renders", "renders_ibr"):
        (out / d).mkdir(parents=True)
    rng = np.random.default_rng(0)
    gt = read_ply(scene / "gt_points.ply")["points"]
    pts = gt + rng.normal(0, 1.0, gt.shape)
    write_points_ply(out / "points.ply", pts, rgb=rng.integers(0, 255, (len(pts), 3), np.uint8))
    m = read_ply(scene / "gt_mesh.ply")
    write_mesh_ply(out / "mesh.ply", m["points"], m["faces"],
                   vertex_colors=np.full((len(m["points"]), 3), 180, np.uint8))
    for v in (0, 1, 2):
        d = np.load(scene / "gt_depth" / f"{v:03d}.npy")
        np.save(out / "depth" / f"{v}.npy", (d * (1 + 0.01 * rng.standard_normal(d.shape)))
                .astype(np.float32))
        Image.fromarray(np.full((H, W, 3), 128, np.uint8)).save(out / "normals" / f"{v}.png")
    s = load_scene(scene, views=[3])
    img = (s.images[0].permute(1, 2, 0).numpy() * 255).astype(np.uint8)
    Image.fromarray(img).save(out / "renders" / "3.png")
    Image.fromarray(255 - img).save(out / "renders_ibr" / "3.png")
    (out / "config.yaml").write_text(f"scene:\n  path: {scene}\n  views: [0, 1, 2]\n")
    (out / "views.json").write_text(json.dumps({"inputs": [0, 1, 2], "test": [3]}))
    (out / "timing.json").write_text(json.dumps({"field": {"seconds": 12.5}}))
    (out / "field").mkdir()
    (out / "field" / "losses.csv").write_text("step,total,rgb,eikonal,beta\n" + "".join(
        f"{s},{1 / s},{0.5 / s},{0.1},{0.01}\n" for s in range(10, 110, 10)))
    (out / "run.json").write_text(json.dumps({
        "command": "svolsdf reconstruct scene -o run", "version": "0.1.0", "device": "cpu",
        "torch": "2.13.0", "date": "2026-12-07T04:00:00+00:00"}))
    metrics = {"chamfer": {"accuracy": 1.2, "completeness": 1.5, "overall": 1.35},
               "fscore": 0.8, "fscore_threshold": 2.0,
               "images": {"psnr": {"mean": 20.0, "per_view": {"3": 20.0}}},
               "timing": {"mvs1": {"seconds": 3.5}, "field": {"seconds": 12.5},
                          "fusion": {"seconds": 1.25}, "total": {"seconds": 17.5}},
               "settings": {}}
    (out / "metrics.json").write_text(json.dumps(metrics))
    return out


def _decode(spec: dict) -> np.ndarray:
    return np.frombuffer(base64.b64decode(spec["bdata"]), np.dtype(spec["dtype"]))


def test_report_sections_and_offline(run, capsys):
    main(["report", str(run)])
    assert f"report {run / 'report.html'}" in capsys.readouterr().out
    page = (run / "report.html").read_text()
    for section in ("3D view", "Metrics", "Input views and the mesh", "Depth maps and depth "
                    "error", "Normal maps", "The mesh from an orbit", "Novel views",
                    "Run configuration", "Timing"):
        assert f"<h2>{section}" in page, section
    assert page.count("Plotly.newPlot(") == 1
    assert len(re.findall(r"<script>", page)) == 2  # plotly.js once, the figure once
    # nothing is fetched: no external script, style, image or font (outside the plotly.js
    # bundle, whose code holds link strings it never loads; the browser test runs offline)
    own = re.sub(r"<script>.*?</script>", "", page, count=1, flags=re.S)
    assert "plotly.js" not in own.split("<body>")[0]
    assert not re.search(r"""(src|href)\s*=\s*["']?(https?:)?//""", own)
    assert not re.search(r"""url\(\s*['"]?https?:""", own)
    assert "<td>Chamfer overall (points)</td><td>1.35</td><td>mm</td>" in page
    assert "mean of accuracy and completeness" in page
    assert page.count('class="cbar"') >= 3 + 1  # depth, depth error (x3), novel-view error
    assert "view 3: ground truth | volume rendering | IBR | |error| volume | |error| IBR" in page
    assert "volume: psnr 20" in page


def test_scene_figure_layers(run):
    pts = read_ply(run / "points.ply")
    mesh = read_ply(run / "mesh.ply")
    K = np.array([[50.0, 0, 31.5], [0, 50, 23.5], [0, 0, 1]])
    w2c = np.eye(4)
    w2c[2, 3] = 500
    gt_err = (pts["points"][:100], np.linspace(0, 1, 100, dtype=np.float32), 1.0)
    fig, notes = scene_figure((pts["points"], pts["colors"]),
                              (mesh["points"], mesh["faces"], mesh["colors"]),
                              [(7, K, w2c, W, H)], gt_err, "mm",
                              ViewerConfig(max_points=500))
    kinds = [(t["type"], t["name"]) for t in fig["data"]]
    assert kinds[0][0] == "mesh3d" and kinds[-1] == ("scatter3d", "camera 7")
    assert any(n.startswith("points (") for _, n in kinds)
    assert any(n == "points: distance to ground truth" for _, n in kinds)
    assert any(f"500 of {len(pts['points']):,} points" in n for n in notes)
    cloud = next(t for t in fig["data"] if t["name"].startswith("points ("))
    origin = np.array(fig["layout"]["meta"]["origin"])
    x = _decode(cloud["x"]) + origin[0]
    assert len(x) == 500 and len(cloud["marker"]["color"]) == 500
    assert np.isin(np.round(x, 2), np.round(pts["points"][:, 0], 2)).all()
    m = fig["data"][0]
    assert len(_decode(m["i"])) == len(mesh["faces"]) and len(m["vertexcolor"]) == len(
        mesh["points"])
    json.dumps(fig, allow_nan=False)  # what the page embeds must be valid JSON


def test_scene_figure_checks_shapes():
    with pytest.raises(ValueError, match=r"points must be \(N, 3\)"):
        scene_figure((np.zeros((4, 2)), None))
    with pytest.raises(ValueError, match="4 points but 3 colours"):
        scene_figure((np.zeros((4, 3)), np.zeros((3, 3), np.uint8)))


def test_cluster_decimate_meets_budget():
    import trimesh

    s = trimesh.creation.icosphere(subdivisions=5)  # 20480 faces
    c = np.full((len(s.vertices), 3), 90, np.uint8)
    v, f, c2 = cluster_decimate(s.vertices, s.faces, 3000, c)
    assert 500 < len(f) <= 3000 and len(c2) == len(v) and (c2 == 90).all()
    assert np.abs(np.linalg.norm(v, axis=1) - 1).max() < 0.05  # still the unit sphere
    v, f, _ = cluster_decimate(s.vertices, s.faces, 10**6)
    assert len(f) == len(s.faces)


def test_frustum_corners_project_to_image_corners():
    K = np.array([[80.0, 0, 40], [0, 80, 30], [0, 0, 1]])
    w2c = np.eye(4)
    w2c[:3, :3] = np.array([[0, 1, 0], [-1, 0, 0], [0, 0, 1.0]])
    w2c[:3, 3] = [1, 2, 3]
    ln = frustum_lines(K, w2c, 81, 61, depth=2.0)
    corners = ln[[1, 4, 7, 10]]
    cam = corners @ w2c[:3, :3].T + w2c[:3, 3]
    uv = (cam @ K.T)[:, :2] / cam[:, 2:]
    np.testing.assert_allclose(cam[:, 2], 2.0)
    np.testing.assert_allclose(uv, [[0, 0], [80, 0], [80, 60], [0, 60]], atol=1e-9)


def test_subsample():
    assert (subsample(5, 10) == np.arange(5)).all()
    i = subsample(1000, 10)
    assert len(np.unique(i)) == 10 and (np.diff(i) > 0).all()


def test_report_says_what_is_missing(run, tmp_path):
    import shutil

    out = tmp_path / "copy"
    shutil.copytree(run, out)
    (out / "metrics.json").unlink()
    page = write_run_report(out).read_text()
    assert "No metrics.json: run svolsdf evaluate" in page
    # the scene moved away: the page still comes, without photos, saying why
    (out / "config.yaml").write_text(f"scene:\n  path: {tmp_path / 'gone'}\n")
    page = write_run_report(out).read_text()
    assert "Inputs not shown" in page and "Novel views not shown" in page
    assert "<h2>3D view" in page and "<h2>Input views" not in page


def test_a_missing_browser_part_fails_when_the_browser_is_required(monkeypatch):
    """Issue 38: under SVOLSDF_REQUIRE_BROWSER a missing part (websocket-client too) fails the
    browser test instead of skipping it."""
    monkeypatch.setenv("SVOLSDF_REQUIRE_BROWSER", "1")
    with pytest.raises(pytest.fail.Exception, match="websocket-client"):
        browser_part_missing("websocket-client is missing")
    monkeypatch.delenv("SVOLSDF_REQUIRE_BROWSER")
    with pytest.raises(pytest.skip.Exception):
        browser_part_missing("websocket-client is missing")


@pytest.mark.slow  # a headless browser
def test_report_in_headless_chromium(run, tmp_path):
    """The page loads from disk with networking off, the 3D view makes its WebGL canvas, and
    nothing is logged as an error. The screenshot stays in tmp_path for debugging."""
    if chromium_path() is None:
        browser_part_missing("no chromium on PATH (apt-get install chromium; CI installs it)")
    if importlib.util.find_spec("websocket") is None:
        browser_part_missing("websocket-client is missing (the dev extra)")
    write_run_report(run)
    keep = os.environ.get("SVOLSDF_SCREENSHOT_DIR")  # e.g. a CI artifact folder
    shot = (Path(keep) if keep else tmp_path) / "report_in_chromium.png"
    shot.parent.mkdir(parents=True, exist_ok=True)
    page = load_page(run / "report.html", screenshot=shot, timeout=40, wait_for="""(() => {
        const n = document.querySelectorAll('#view3d canvas').length;
        const div = document.getElementById('view3d');
        return n ? {canvases: n, traces: div.data.map(t => t.name),
                    hidden: div.data.filter(t => t.visible === 'legendonly').length} : null;
    })()""")
    assert page.value, f"no canvas in the 3D view; see {shot}"
    assert not page.errors, f"{page.errors}; see {shot}"
    traces = page.value["traces"]
    assert traces[0].startswith("mesh") and "camera 0" in traces, traces
    assert "points: distance to ground truth" in traces and page.value["hidden"] >= 1
    assert "ground truth: distance to the points (completeness)" in traces
    assert shot.stat().st_size > 10_000
    img = np.asarray(Image.open(shot).convert("L"))
    assert img.std() > 5, f"blank page; see {shot}"


def test_metrics_table_says_how_the_mesh_was_scored():
    """The report's metrics say that the mesh was scored by its surface and at which spacing, or,
    for metrics of an older version, by its vertices."""
    from svolsdf.evaluate.report import _metrics_table

    block = {"accuracy": 1.0, "completeness": 2.0, "overall": 1.5}
    new = _metrics_table({"chamfer": {}, "chamfer_mesh": {**block, "sampled": "surface",
                                                          "density": 0.158}}, "mm")
    assert "<td>mesh scored by</td><td>its surface, sampled every 0.158 mm</td>" in new
    old = _metrics_table({"chamfer": {}, "chamfer_mesh": block}, "mm")
    assert "<td>mesh scored by</td><td>its vertices (metrics of an older version)</td>" in old
    assert "mesh scored by" not in _metrics_table({"chamfer": {}, "chamfer_mesh": {}}, "mm")


def test_depth_error_counts_inside_the_object_mask(run, tmp_path):
    """The report's depth error of a scene with masks is the object's: a background off by 50
    and an object off by 1 give a median of 1, and the caption says where it was measured."""
    import shutil

    from svolsdf.evaluate.report_pictures import depth_error

    out = tmp_path / "copy"
    shutil.copytree(run, out)
    scene = run.parent / "scene"
    g = np.load(scene / "gt_depth" / "000.npy").astype(np.float64)
    mask = np.asarray(Image.open(scene / "mask" / "000.png").convert("L")) > 127
    assert (g[~mask] > 0).sum() > mask.sum()  # more background with depth than object
    np.save(out / "depth" / "0.npy", np.where(mask, g + 1.0, g + 50.0).astype(np.float32))
    err, valid = depth_error(np.where(mask, g + 1.0, g + 50.0), g, mask)
    assert valid.sum() == (mask & (g > 0)).sum() and np.allclose(err[valid], 1.0, atol=1e-3)
    page = write_run_report(out).read_text()
    assert "view 0: |depth - ground truth| inside the object mask, median 1 mm" in page


def test_metrics_table_says_which_protocol_each_chamfer_follows():
    from svolsdf.evaluate.report import _metrics_table

    block = {"accuracy": 1.0, "completeness": 2.0, "overall": 1.5}
    page = _metrics_table({"chamfer": {**block, "protocol": "generic"},
                           "chamfer_mesh": {**block, "protocol": "dtu-mesh",
                                            "sampled": "surface", "density": 0.2}}, "mm")
    assert page.count("protocol: generic two-way Chamfer against the whole --gt-points") == 3
    assert page.count("protocol: DTU protocol on the mesh&#x27;s surface") == 3


def test_report_shows_how_the_run_went(run, tmp_path):
    """The loss curves, a chart of the stage times, the command, version, device and date, and
    the config collapsed."""
    page = write_run_report(run).read_text()
    for section in ("Run", "Loss curves", "Stage times", "Run configuration"):
        assert f"<h2>{section}</h2>" in page, section
    for row in ("<td>command</td><td class='val'>svolsdf reconstruct scene -o run</td>",
                "<td>svolsdf version</td><td class='val'>0.1.0</td>",
                "<td>device</td><td class='val'>cpu</td>",
                "<td>date (UTC)</td><td class='val'>2026-12-07T04:00:00+00:00</td>"):
        assert row in page, row
    assert 'alt="loss curves: field (10 logged steps)"' in page
    assert 'alt="time per stage (timing.json); total 17.5 s"' in page
    assert "<details id='config'><summary>config.yaml" in page
    assert "ground truth: distance to the points (completeness)" in page
