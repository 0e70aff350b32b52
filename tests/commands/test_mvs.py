"""``svolsdf mvs`` (`svolsdf.commands.mvs`): the MVS cascade alone on a scene, its outputs on
disk, its options and its command line."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from svolsdf.cli import main as cli_main
from svolsdf.commands.mvs import MVSJobConfig, run_mvs
from svolsdf.errors import InputError
from svolsdf.io.ply import read_ply
from svolsdf.scene.synthetic import SynthConfig, make_synthetic_scene


@pytest.fixture(autouse=True)
def _one_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory):
    out = tmp_path_factory.mktemp("mvsjob") / "scene"
    return make_synthetic_scene(out, SynthConfig(views=3, width=64, height=48, seed=2,
                                                 gt_points=2000, supersample=1,
                                                 azimuth_span=30.0, elevation=(35.0, 50.0)))


def test_run_mvs_outputs(tiny_scene, tmp_path):
    out = tmp_path / "out"
    s = run_mvs(MVSJobConfig(scene=tiny_scene, out=out, views=[0, 1, 2]))
    assert s["size"] == [64, 48] and s["views"] == [0, 1, 2]
    assert s["hypotheses"] == {"1": 192, "2": 32, "3": 8}
    # the plane sweep's MVS size is 2x the working size (mvs_size, docs/method.md 9.2.2)
    assert s["stage_sizes"] == {"1": [32, 24], "2": [64, 48], "3": [128, 96]}
    for v in (0, 1, 2):
        for rel in (f"depth/{v}.npy", f"depth/{v}.png", f"confidence/{v}.npy",
                    f"confidence/{v}.png", f"mvs/stage1/{v}.npz", f"mvs/stage3/{v}.npz"):
            assert (out / rel).is_file(), rel
        d = np.load(out / "depth" / f"{v}.npy")
        near, far = s["depth_range"][str(v)]
        assert d.shape == (96, 128) and np.isfinite(d).all()
        # finer stages are not clamped to the range (docs/method.md 2.5): allow their half-widths
        slack = (16 + 2) * (far - near) / 192
        assert (d > near - slack).all() and (d < far + slack).all()
    pts = read_ply(out / "points.ply")["points"]
    assert len(pts) == s["fusion"]["points_total"] > 0
    assert json.loads((out / "mvs.json").read_text())["backbone"] == "planesweep"


def test_run_mvs_size_and_bad_input(tiny_scene, tmp_path):
    s = run_mvs(MVSJobConfig(scene=tiny_scene, out=tmp_path / "o", views=[2, 0], size=(32, 24),
                             depth_range=(300.0, 900.0), fuse=False))
    assert s["size"] == [32, 24] and s["views"] == [2, 0] and "fusion" not in s
    assert s["depth_range"]["2"] == [300.0, 900.0]
    assert np.load(tmp_path / "o" / "depth" / "2.npy").shape == (48, 64)
    with pytest.raises(InputError, match="0 < near < far"):
        run_mvs(MVSJobConfig(scene=tiny_scene, out=tmp_path / "p", depth_range=(5.0, 1.0)))
    with pytest.raises(InputError, match="at least 2 views"):
        run_mvs(MVSJobConfig(scene=tiny_scene, out=tmp_path / "p", views=[1]))
    with pytest.raises(InputError, match="unknown MVS backbone"):
        run_mvs(MVSJobConfig(scene=tiny_scene, out=tmp_path / "p", backbone="colmap"))


def test_cli_mvs(tiny_scene, tmp_path, capsys):
    out = tmp_path / "cli"
    cli_main(["mvs", str(tiny_scene), "--views", "1", "0", "-o", str(out), "--size", "32x24",
              "--no-fuse"])
    assert (out / "depth" / "1.npy").is_file() and (out / "depth" / "0.npy").is_file()
    assert "mvs (planesweep)" in capsys.readouterr().out
    with pytest.raises(SystemExit) as e:
        cli_main(["mvs", str(tiny_scene), "--views", "0", "9", "-o", str(out)])
    assert e.value.code == 2
    assert "view id 9 does not exist" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        cli_main(["mvs", str(tiny_scene), "-o", str(out), "--backbone", "casmvsnet"])
    assert e.value.code == 2
    assert "--weights" in capsys.readouterr().err


def test_a_stopped_mvs_job_resumes_from_its_finished_stages(tiny_scene, tmp_path, monkeypatch,
                                                            capsys):
    """Killed after its stage 1, the job once kept nothing: each stage's volumes are marked
    finished as they are written, and the rerun reads them back and computes only the rest, with
    the outputs of a job that never stopped."""
    import svolsdf.mvs.cascade as cascade

    whole = tmp_path / "whole"
    run_mvs(MVSJobConfig(scene=tiny_scene, out=whole, views=[0, 1, 2]))
    out = tmp_path / "out"
    real, ran, stop = cascade.run_cascade, [], [True]

    def stop_at_stage_2(backbone, scene, stages, **kw):
        ran.append(stages)
        if stages == (2,) and stop[0]:
            raise KeyboardInterrupt
        return real(backbone, scene, stages=stages, **kw)

    monkeypatch.setattr(cascade, "run_cascade", stop_at_stage_2)
    argv = ["mvs", str(tiny_scene), "-o", str(out), "--views", "0", "1", "2"]
    with pytest.raises(SystemExit) as e:
        cli_main(argv)
    assert e.value.code == 130 and "interrupted" in capsys.readouterr().err
    state = json.loads((out / "mvs" / "stages.json").read_text())
    assert "stage1" in state and "stage2" not in state and not (out / "mvs.json").exists()
    stage1 = (out / "mvs" / "stage1" / "1.npz").read_bytes()
    ran.clear()
    stop[0] = False
    cli_main(argv)  # resumed: stage 1 read back
    assert ran == [(2,), (3,)]
    assert (out / "mvs" / "stage1" / "1.npz").read_bytes() == stage1
    for rel in ("depth/1.npy", "confidence/1.npy", "mvs/stage3/1.npz", "points.ply"):
        assert (out / rel).read_bytes() == (whole / rel).read_bytes(), rel
    # a stage-1 volume cut short: found by its record, stage 1 and the later ones run again
    f = out / "mvs" / "stage1" / "0.npz"
    f.write_bytes(f.read_bytes()[:100])
    ran.clear()
    cli_main(argv)
    assert ran == [(1,), (2,), (3,)]
    # a changed option runs the stages again
    ran.clear()
    cli_main(argv + ["--depth-range", "300,900"])
    assert ran == [(1,), (2,), (3,)]
