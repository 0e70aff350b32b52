"""The tiny synthetic scene and the short fast-preset config of the pipeline's end-to-end tests
(tests/pipeline: test_stages.py, test_volsdf_mode.py, test_rundir.py)."""

from __future__ import annotations

import functools
import shutil
from pathlib import Path

from svolsdf.cli import main
from svolsdf.config import Config, load_config, preset
from svolsdf.pipeline import Pipeline
from svolsdf.scene.synthetic import SynthConfig, make_synthetic_scene


def make_tiny_scene(folder: Path) -> Path:
    """A three-view 160x120 synthetic scene of blobs (seed 5) written to ``folder``."""
    make_synthetic_scene(folder, SynthConfig(views=3, width=160, height=120, seed=5,
                                             object="blobs", supersample=1, gt_points=40_000))
    return folder


def tiny_cfg(scene, steps: int = 300) -> Config:
    """The fast preset, shortened for the tiny scene: ``steps`` steps of 256 rays, a 32 -> 64
    grid, the field's own 96^3 mesh."""
    cfg = preset("fast")
    cfg.scene.path = str(scene)
    cfg.train.steps = steps
    cfg.train.rays = 256
    cfg.train.checkpoint_every = 100
    cfg.field.grid_start_resolution = 32
    cfg.field.grid_resolution = 64
    cfg.mesh.resolution = 96
    # the mesh from the field alone: the key tests (test_stages.py) change fusion options, which the
    # fitted mesh follows (test_mesh_fitted_to_the_points covers it)
    cfg.mesh.fit_points = 0
    cfg.mesh.method = "field"  # the field's own mesh; Poisson has its own tests
    # free-space culling and support trimming read the fused points too, so fusion options
    # would rerun the mesh (test_tsdf_mesh_with_free_space_and_support covers them)
    cfg.mesh.free_space = False
    cfg.mesh.support = 0.0
    return cfg


def rerun_on_copy(out: Path, dest: Path, **options) -> Pipeline:
    """Copy the finished run ``out`` to ``dest``, set ``cfg.<section>.<key> = value`` for each
    ``section__key=value`` of ``options`` (``mesh__method="tsdf"``) and run the pipeline there
    (finished stages are reused); returns the Pipeline."""
    shutil.copytree(out, dest)
    cfg = load_config(out / "config.yaml")
    for k, v in options.items():
        *path, name = k.split("__")
        setattr(functools.reduce(getattr, path, cfg), name, v)
    p2 = Pipeline(cfg, dest, progress=False)
    p2.run()
    return p2


# --------------------------------------------------------------------------- through the CLI
def make_small_sphere_scene(folder: Path) -> Path:
    """A four-view 64x48 synthetic sphere (seed 2) written to ``folder``."""
    make_synthetic_scene(folder, SynthConfig(views=4, width=64, height=48, seed=2, supersample=1,
                                             gt_points=3000, object="sphere"))
    return folder


def small_field_run(scene: Path, folder: Path) -> Path:
    """``svolsdf reconstruct`` of views 0 1 2 of ``scene`` with a field of a 16^3 grid and 10
    steps (seconds) into FOLDER/run, its config FOLDER/small.yaml; returns the run folder."""
    (folder / "small.yaml").write_text(
        f"scene: {{path: {scene}, views: [0, 1, 2]}}\n"
        "field: {grid_start_resolution: 16, grid_resolution: 16}\n"
        "mesh: {resolution: 24}\nfusion: {unguided: false}\n"
        "train: {rays: 32, checkpoint_every: 0, steps: 10}\n")
    cli(["reconstruct", "-o", folder / "run", "--config", folder / "small.yaml",
         "--no-progress"])
    return folder / "run"


def cli(argv) -> None:
    """``svolsdf`` with ``argv`` (paths turned into strings), in this process."""
    main([str(a) for a in argv])


def cli_exit(argv, capsys):
    """``svolsdf`` with ``argv`` expected to exit: (its status, what it printed)."""
    import pytest

    with pytest.raises(SystemExit) as e:
        main([str(a) for a in argv])
    return e.value.code, capsys.readouterr()


def copy_run(src: Path, dest: Path) -> Path:
    """A copy of the run folder ``src`` at ``dest``, without its lock file."""
    shutil.copytree(src, dest, ignore=shutil.ignore_patterns(".svolsdf.lock"))
    return dest
