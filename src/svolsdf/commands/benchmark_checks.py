"""The checks of ``svolsdf benchmark`` before any job starts (`validate_benchmark`): scenes,
modes, view sets, the DTU ground truth, the output folder, and every job's config."""

from __future__ import annotations

from pathlib import Path

from svolsdf.commands.benchmark import (
    MODES,
    BenchmarkConfig,
    _ground_truth,
    _view_sets,
    benchmark_jobs,
    job_config,
    scan_number,
)
from svolsdf.errors import InputError
from svolsdf.io.paths import input_dir, output_dir
from svolsdf.scene.checks import check_outside_scenes

__all__ = ["validate_benchmark"]


def validate_benchmark(cfg: BenchmarkConfig) -> None:
    """Raise `InputError` for what `svolsdf.commands.benchmark.run_benchmark` cannot run;
    normalizes ``cfg``'s paths in place."""
    if not cfg.scenes:
        raise InputError("benchmark: give at least one scene (--scenes A B ...)")
    if not cfg.variants:
        if not cfg.modes:
            raise InputError(f"benchmark: give at least one mode (--modes {' '.join(MODES)})")
        bad = [m for m in cfg.modes if m not in MODES]
        if bad:
            raise InputError(f"benchmark: unknown mode(s) {bad} (choose from "
                             f"{', '.join(MODES)})")
        from svolsdf.config import parse_set

        if "train.mode" in parse_set(cfg.sets):
            raise InputError("--set train.mode: the benchmark runs every mode of --modes; "
                             "give the modes there")
        if cfg.config is not None:
            from svolsdf.io.paths import input_file

            cfg.config = input_file(cfg.config, "config file", "--config")
    if cfg.scene_views is not None and len(cfg.scene_views) != len(cfg.scenes):
        raise InputError(f"benchmark: {len(cfg.scene_views)} scene view lists for "
                         f"{len(cfg.scenes)} scenes")
    for vs in [*(cfg.view_sets or []), *(v for v in cfg.scene_views or [] if v is not None)]:
        if not vs:
            raise InputError("benchmark: an empty input view set (give view ids, e.g. "
                             "--views '25 22 28; 23 24 33')")
    if cfg.scan is not None and cfg.dtu_gt is None:
        raise InputError(f"--scan {cfg.scan}: only the DTU protocol uses it; add --dtu-gt ROOT")
    cfg.scenes = [input_dir(s, "scene folder", "--scenes") for s in cfg.scenes]
    if cfg.dtu_gt is not None:
        cfg.dtu_gt = input_dir(cfg.dtu_gt, "DTU ground-truth folder", "--dtu-gt")
        if cfg.scan is None:
            missing = [str(s) for s in cfg.scenes
                       if scan_number(s) is None and not (Path(s) / "gt_points.ply").is_file()]
            if missing:
                raise InputError(f"--dtu-gt: no DTU scan number in the name of {missing[0]} "
                                 "(name it like scan65 or pass --scan N)")
        _check_dtu_files(cfg)
    cfg.out = output_dir(cfg.out, "output folder", "-o", create=False)
    # the job folders OUT/<scene>/<mode>/ go neither into a scene nor among its files
    check_outside_scenes(cfg.out, cfg.scenes, "the benchmark")
    for job in benchmark_jobs(cfg):  # every run config is valid
        job_config(job)
    _check_view_sets(cfg)


def _check_dtu_files(cfg: BenchmarkConfig) -> None:
    """Each DTU scene's evaluation files exist under --dtu-gt (ObsMask, Plane, STL of its scan):
    a wrong --scan fails here, not after every job's reconstruction."""
    from svolsdf.evaluate.chamfer import find_dtu_files

    for scene in cfg.scenes:
        gt = _ground_truth(cfg, scene)
        if "dtu_gt" in gt:
            scan = scan_number(scene)
            how = f"scan {scan} from its name" if scan is not None else f"--scan {cfg.scan}"
            try:
                find_dtu_files(gt["dtu_gt"], gt["scan"])
            except InputError as e:
                raise InputError(f"--dtu-gt for {scene} ({how}): {e}") from None


def _check_view_sets(cfg: BenchmarkConfig) -> None:
    """Every input view set exists in every scene (the scene's view ids, read without its
    images), before any job starts; how many a set holds is the config's check."""
    from svolsdf.scene.loaders import load_scene

    for i, scene in enumerate(cfg.scenes):
        for views in _view_sets(cfg, i):
            if views is None:
                continue
            own = cfg.scene_views is not None and cfg.scene_views[i] is not None
            label = ("the experiment's scene_views " if own else "--views ") + " ".join(
                map(str, views))
            try:
                load_scene(scene, views=views, load_images=False)
            except InputError as e:
                raise InputError(f"{label}: {e}") from None
