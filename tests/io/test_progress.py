"""Progress bars: every slow loop shows one named after its stage, with an ETA, and the
command's --no-progress turns all of them off."""

from __future__ import annotations

import numpy as np
import torch
from tests.field.analytic import SphereSDF

from svolsdf.io.progress import progress_bar, show_progress
from svolsdf.scene.cameras import Cameras


def test_a_bar_names_its_stage_and_shows_the_time_left(capsys):
    with show_progress(True):
        for _ in progress_bar(range(3), desc="fusion"):
            pass
    err = capsys.readouterr().err
    assert "fusion:" in err and "/3 [" in err and "ETA" in err
    with show_progress(False):
        for _ in progress_bar(range(3), desc="fusion"):
            pass
    assert capsys.readouterr().err == ""


def test_mvs_fusion_rendering_and_tsdf_show_their_bars(tmp_path, capsys):
    """The stages that had no bar: MVS per view (each stage), fusion, the field's rendering of
    several views (the guide, IBR's inputs), the TSDF grid and the Poisson mesh's steps."""
    from svolsdf.commands.mvs import MVSJobConfig, run_mvs
    from svolsdf.fusion.meshing import poisson_mesh
    from svolsdf.fusion.tsdf import tsdf_grid
    from svolsdf.io.ply import read_ply
    from svolsdf.render.samplers import error_bound_sample
    from svolsdf.render.views import render_field_views
    from svolsdf.scene.loaders import load_scene
    from svolsdf.scene.synthetic import SynthConfig, make_synthetic_scene

    scene = tmp_path / "syn"
    make_synthetic_scene(scene, SynthConfig(views=3, width=48, height=36, seed=2,
                                            object="sphere", supersample=1, gt_points=2000))
    capsys.readouterr()
    K = torch.tensor([[10.0, 0.0, 7.5], [0.0, 10.0, 5.5], [0.0, 0.0, 1.0]])
    w2c = torch.eye(4)
    w2c[2, 3] = 2.5
    cams = Cameras(K[None].expand(2, 3, 3), w2c[None].expand(2, 4, 4), 16, 12)
    with show_progress(True):
        run_mvs(MVSJobConfig(scene=scene, out=tmp_path / "mvs", views=[0, 1, 2]))
        render_field_views(SphereSDF(1.0, beta=0.01), error_bound_sample, cams, chunk=64,
                           keys=("depth",), desc="guide: render the input views")
        tsdf_grid([torch.full((12, 16), 2.0)], cams[[0]], np.full(3, -1.0), 0.5, (4, 4, 4),
                  trunc=0.5, chunk=16)
        poisson_mesh(read_ply(scene / "gt_points.ply")["points"], None,
                     SphereSDF(1.0, beta=0.01), load_scene(scene), depth=5, trim=0.0)
    err = capsys.readouterr().err
    for name in ("MVS stage 1 (plane sweep)", "MVS stage 2 (plane sweep)",
                 "MVS stage 3 (plane sweep)", "fusion", "guide: render the input views",
                 "mesh: TSDF", "mesh: Poisson"):
        assert f"{name}:" in err, name
    assert "ETA" in err


def test_no_progress_turns_off_every_stage_bar(tmp_path, capsys):
    """`svolsdf reconstruct --no-progress`: the pipeline's progress flag reaches the bars of
    the components, not only the optimization's."""
    from svolsdf.cli.app import _run_pipeline

    class Stand:
        def __init__(self, progress):
            self.progress, self.out, self.device = progress, tmp_path, "cpu"

        def run(self):
            bar = progress_bar(range(2), desc="MVS stage 1")
            self.shown = not bar.disable
            bar.close()
            return {"out": str(self.out)}

    with show_progress(True):  # as on a terminal
        off, on = Stand(progress=False), Stand(progress=True)
        _run_pipeline(off)
        assert not off.shown
        Stand.run(on)
        assert on.shown
    assert capsys.readouterr().err.count("MVS stage 1:") == 1
    # the finished run records what made it, for the report
    import json

    from svolsdf import __version__

    info = json.loads((tmp_path / "run.json").read_text())
    assert info["version"] == __version__ and info["device"] == "cpu"
    assert set(info) == {"command", "version", "device", "torch", "date"}
