"""Commands that make scenes and runs: info, config, reconstruct, demo, calibrate, mvs, synth."""

from __future__ import annotations

import contextlib
import os
from pathlib import Path
from typing import Annotated

import typer

from svolsdf.calibrate import CalibrateConfig
from svolsdf.cli.app import (
    _RECONSTRUCT_OPTIONS,
    VIEWS_HELP,
    _parse_auto_views,
    _parse_size,
    _parse_views,
    _run_pipeline,
    app,
    build_config,
)
from svolsdf.cli.flags import (
    CALIBRATE_FLAGS,
    MVS_FLAGS,
    RECONSTRUCT_FLAGS,
    SYNTH_FLAGS,
    dataclass_values,
    flag_help,
    flag_overrides,
    with_dataclass_flags,
    with_flags,
)
from svolsdf.commands.mvs import MVSJobConfig
from svolsdf.errors import InputError
from svolsdf.io.paths import input_dir, input_file, input_path, output_dir, output_file
from svolsdf.scene.synthetic import SynthConfig


@app.command("info")
def info(
    scene: Annotated[Path, typer.Argument(help="Scene folder (IDR/NeuS, DTU raw, MVSNet, "
                                               "COLMAP or transforms.json).")],
    views: Annotated[str | None, typer.Option(
        "--views", help="View ids to keep, in order, e.g. '25,22,28' (default: all).")] = None,
    sheet: Annotated[Path | None, typer.Option(
        "--sheet", help="Also write a contact sheet of the views with masks overlaid (PNG).")
    ] = None,
    lighting: Annotated[str, typer.Option(
        "--lighting", help="DTU raw lighting index 0..6 or 'max'.")] = "3",
) -> None:
    """Summarize a scene: format, views, image size, units, depth ranges, pairs, normalization."""
    from svolsdf.scene.info import contact_sheet, describe_scene
    from svolsdf.scene.loaders import load_scene, scene_folder

    scene = scene_folder(scene)
    if sheet is not None:
        sheet = output_file(sheet, "contact sheet", "--sheet", create=False)
    light: int | str = int(lighting) if lighting.isdigit() else lighting
    s = load_scene(scene, views=_parse_views(views), load_images=False, lighting=light)
    typer.echo(describe_scene(s))
    if sheet is not None:
        out = contact_sheet(s, sheet)
        typer.echo(f"contact sheet {out}")




@app.command("config")
def config_cmd(
    preset_name: Annotated[str | None, typer.Option(
        "--preset", help=flag_help("preset") + " With --config, the preset the file must "
                                               "name.")] = None,
    config: Annotated[Path | None, typer.Option(
        "--config", help="Show this config.yaml (e.g. OUT/config.yaml) instead of a preset.")
    ] = None,
    set_: Annotated[list[str] | None, typer.Option(
        "--set", help="Change options first, as reconstruct --set.")] = None,
) -> None:
    """Print every option as YAML, each with its documentation as a comment.

    Save it, edit it and pass it back with ``svolsdf reconstruct SCENE --config FILE``, or set
    single options with ``--set section.option=value``.
    """
    from svolsdf.cli.app import base_config
    from svolsdf.config import apply_overrides, config_yaml, parse_set

    cfg = base_config(None if config is None else input_file(config, "config file", "--config"),
                      preset_name)
    given = parse_set(set_)
    if given:
        apply_overrides(cfg, given, labels={k: f"--set {k}" for k in given}, skip_none=False)
    typer.echo(config_yaml(cfg), nl=False)




def reconstruct(
    scene: Annotated[Path | None, typer.Argument(
        help="Scene folder (any format `svolsdf info` reads); optional with --config.")] = None,
    out: Annotated[Path, typer.Option("--out", "-o", help="Output folder.")] = Path("out"),
    views: Annotated[str | None, typer.Option("--views", help=VIEWS_HELP)] = None,
    size: Annotated[str | None, typer.Option(
        "--size", help="Working size WxH (default: 768 wide, never upsampled).")] = None,
    preset_name: Annotated[str | None, typer.Option("--preset", help=flag_help("preset"))
                           ] = None,
    config: Annotated[Path | None, typer.Option(
        "--config", help="A config.yaml (e.g. from an earlier OUT) to start from.")] = None,
    fusion_network: Annotated[Path | None, typer.Option(
        "--fusion-network", help="Weights of a PatchmatchNet (TorchScript) to start from the "
                                 "field's depth and fuse as a further hypothesis "
                                 "(fusion.network).")] = None,
    set_: Annotated[list[str] | None, typer.Option(
        "--set", help="Any option as section.option=value (YAML value), repeatable, applied "
                      "last: --set train.steps=200 --set mesh.method=poisson; "
                      "`svolsdf config` lists them all.")] = None,
    no_progress: Annotated[bool, typer.Option("--no-progress", help="No progress bars.")] = False,
    from_stage: Annotated[str | None, typer.Option(
        "--from", help="Run this stage (fusion, mesh, ...) and the later ones again on a finished "
                       "OUT, reusing the earlier ones, which must be finished under the config "
                       "(without SCENE and --config: OUT/config.yaml, changed by --set).")
    ] = None,
    **options,  # the flags of RECONSTRUCT_FLAGS (`with_flags`), by parameter name
) -> None:
    """Reconstruct a scene: MVS, S-VolSDF optimization, guided MVS, fusion and mesh.

    Writes OUT/points.ply, OUT/mesh.ply, OUT/depth/<view>.npy (+ PNG), OUT/config.yaml, OUT/log
    and OUT/timing.json. A rerun reuses finished stages and resumes an interrupted optimization;
    ``-o OUT --from fusion --set mesh.method=tsdf`` fuses and meshes a finished run again.
    """
    from svolsdf.pipeline import Pipeline

    # the paths first, each refused with its cause; the scene's layout is the pipeline's
    # first check (`Pipeline.run`), also for a scene.path from --config
    if scene is not None:
        scene = input_dir(scene, "scene folder")
    if config is not None:
        config = input_file(config, "config file", "--config")
    out = output_dir(out, "output folder", "-o", create=False)
    if from_stage is not None:
        config = _from_config(from_stage, scene, config, out)
    if fusion_network is not None:
        fusion_network = input_file(fusion_network, "fusion network weights file",
                                    "--fusion-network")
    auto = _parse_auto_views(views)
    cfg = build_config(scene, config, preset_name, {
        "scene.views": None if auto else _parse_views(views),
        "scene.view_selection": "auto" if auto else None,
        "scene.num_views": auto or None, "scene.image_size": _parse_size(size),
        **flag_overrides(RECONSTRUCT_FLAGS, options),
        "fusion.network": None if fusion_network is None else "patchmatchnet",
        "fusion.network_weights": None if fusion_network is None else str(fusion_network),
    }, _RECONSTRUCT_OPTIONS, sets=set_)
    if auto:  # auto also replaces the views a --config file lists
        cfg.scene.views = None
    _check_run_memory(cfg)
    pipe = Pipeline(cfg, out, progress=not no_progress,
                    **({"start": from_stage} if from_stage is not None else {}))
    if auto:
        pipe.load()
        typer.echo(f"views auto: picked {pipe.views} of {len(pipe.all_view_ids)} views "
                   f"(reference {pipe.views[0]})")
    summary = _run_pipeline(pipe)
    typer.echo(f"points: {summary['points']}")
    if summary.get("mesh"):
        typer.echo(f"mesh:   {summary['mesh']}")
    typer.echo(f"total {summary['timing'].get('total', {}).get('seconds', 0):.0f} s; "
               f"details in {Path(out) / 'timing.json'}")


app.command("reconstruct")(with_flags(reconstruct, RECONSTRUCT_FLAGS))


def _from_config(stage: str, scene: Path | None, config: Path | None, out: Path) -> Path | None:
    """The config file of ``reconstruct --from STAGE``: ``config``, or OUT/config.yaml when
    neither SCENE nor --config is given (before anything is touched: exit 2 on a bad stage or
    an OUT that is no run folder)."""
    from svolsdf.pipeline.keys import STAGES

    if stage not in STAGES:
        raise InputError(f"--from {stage}: unknown stage (one of {', '.join(STAGES)})")
    if scene is not None or config is not None:
        return config
    if not (out / "config.yaml").is_file():
        raise InputError(f"--from {stage}: {out} is not a run folder (no config.yaml); run "
                         f"svolsdf reconstruct SCENE -o {out} first")
    return out / "config.yaml"


def _check_run_memory(cfg) -> None:
    """The memory check of `svolsdf.config.validate_config` again at the scene's working size
    (the cameras and one image header); a scene that cannot be read is left to the pipeline's
    message."""
    from svolsdf.config import check_memory
    from svolsdf.io.images import image_size
    from svolsdf.scene.loaders import read_source
    from svolsdf.scene.size import working_size

    try:
        width, height = image_size(read_source(cfg.scene.path, cfg.scene.lighting).image_paths[0])
    except (InputError, OSError):
        return
    size = working_size(width, height, image_size=cfg.scene.image_size)
    check_memory(cfg, size, len(cfg.scene.views) if cfg.scene.views else None,
                 labels=_RECONSTRUCT_OPTIONS)


@app.command("demo")
def demo(
    out: Annotated[Path, typer.Option("--out", "-o", help="Output folder.")] = Path(
        "svolsdf_demo"),
    size: Annotated[str, typer.Option("--size", help="Image size WxH of the synthetic scene.")
                    ] = "768x576",
    seed: Annotated[int, typer.Option("--seed", help="Synthetic scene seed.")] = 0,
    steps: Annotated[int | None, typer.Option("--steps", help="Optimization steps.")] = None,
    no_progress: Annotated[bool, typer.Option("--no-progress", help="No progress bars.")] = False,
) -> None:
    """Generate a synthetic scene, reconstruct it from 3 views with the fast preset, and score it.

    Prints where the outputs are and the Chamfer distance against the scene's ground truth, and
    writes OUT/scene/, OUT/run/metrics.json and OUT/run/report.html (open it in a browser). A
    rerun reuses the scene and the finished stages; with another --size or --seed the scene is
    made again and the reconstruction reruns on it.
    """
    import json

    from svolsdf.config import apply_overrides, preset
    from svolsdf.evaluate.synthetic import synthetic_chamfer
    from svolsdf.io.ply import read_ply
    from svolsdf.io.replace import check_replace
    from svolsdf.io.runfolder import RunFolder
    from svolsdf.pipeline import Pipeline
    from svolsdf.scene.checks import check_output_folder, check_outside_scenes
    from svolsdf.scene.synthetic import (
        SCENE_OUTPUT,
        SynthConfig,
        made_with,
        make_synthetic_scene,
    )

    out = output_dir(out, "output folder", "-o", create=False)
    w, h = _parse_size(size)
    scene_dir, run = out / "scene", out / "run"
    synth_cfg = SynthConfig(views=5, width=w, height=h, seed=seed)
    # the run's options and both folders first: a bad one fails before minutes of rendering,
    # and the demo writes into no scene folder and replaces no file it did not write
    cfg = apply_overrides(preset("fast"), {"scene.path": str(scene_dir), "train.steps": steps},
                          labels={"train.steps": "--steps"})
    check_outside_scenes(out, what="the demo", enclosing=True)
    remake = not made_with(scene_dir, synth_cfg)
    if out.is_dir():  # a new OUT (or a link to a folder not made yet) holds nothing to lose
        if remake:
            check_replace(scene_dir, SCENE_OUTPUT)
        check_output_folder(run, scene_dir, "svolsdf reconstruct")
    output_dir(out, "output folder", "-o")  # made now: also through a link to a new folder
    if remake:
        if (scene_dir / "scene.json").is_file():
            typer.echo(f"{scene_dir} holds a scene of other settings: it is made again, and "
                       "the reconstruction runs again on it")
        typer.echo(f"generating a synthetic scene ({w}x{h}, seed {seed}) in {scene_dir} ...")
        make_synthetic_scene(scene_dir, synth_cfg)
    typer.echo(f"reconstructing into {run} (fast preset) ...")
    summary = _run_pipeline(Pipeline(cfg, run, progress=not no_progress))
    run_views = RunFolder(run).views()
    views = run_views.inputs if run_views is not None else []
    lines = []
    result = {}
    for name in ("points", "mesh"):
        p = summary.get(name)
        if p and Path(p).is_file():
            d = read_ply(p)  # a mesh is scored by its surface (faces), not its vertices
            r = synthetic_chamfer(d["points"], scene_dir, views,
                                  faces=d["faces"] if name == "mesh" else None)
            result[name] = r
            lines.append(f"{name:6s} {p}: Chamfer accuracy {r['accuracy']:.3f} mm, completeness "
                         f"{r['completeness']:.3f} mm, overall {r['overall']:.3f} mm, F-score "
                         f"{r['fscore']:.3f} at {r['threshold']:.2f} mm")
    (run / "demo_metrics.json").write_text(json.dumps(result, indent=1))
    from svolsdf.evaluate.run_outputs import protocol_label

    lines.append(f"Chamfer protocol: {protocol_label('synthetic')}")
    typer.echo("\n".join(lines))
    typer.echo(f"total {summary['timing']['total']['seconds']:.0f} s; inputs {views}; "
               f"outputs in {run}")
    from svolsdf.evaluate.scoring import EvaluateConfig, evaluate_run

    evaluate_run(EvaluateConfig(out=run))
    typer.echo(f"report {run / 'report.html'}")




# --------------------------------------------------------------------------- calibrate
def calibrate(
    inputs: Annotated[Path, typer.Argument(help="A folder of photos or a video file.")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Scene folder to write (COLMAP "
                                                          "model + images/).")],
    **options,  # the flags of CALIBRATE_FLAGS (`with_dataclass_flags`), by parameter name
) -> None:
    """Camera poses for your own photos or video (structure from motion with pycolmap).

    Writes OUT as a COLMAP scene that `svolsdf reconstruct OUT --views auto` reads: the registered
    photos (undistorted) in OUT/images/, cameras and sparse points in OUT/sparse/0/, and a summary
    in OUT/calibration.json. OUT may hold the folder of the photos (OUT/photos, not OUT/images);
    a rerun replaces only what an earlier calibrate wrote, once the new calibration is complete.
    """
    from svolsdf.calibrate import calibrate as run_calibrate

    inputs = input_path(inputs, "folder of photos or video file")
    out = output_dir(out, "scene folder", "-o", create=False)
    cfg = CalibrateConfig(**dataclass_values(CALIBRATE_FLAGS, options))
    s = run_calibrate(inputs, out, cfg)
    n_in, n_reg = s["num_inputs"], len(s["registered"])
    kind = "frames" if s["video"] else "photos"
    typer.echo(f"registered {n_reg} of {n_in} {kind} at {s['size'][0]}x{s['size'][1]} "
               f"({'one shared camera' if s['shared_camera'] else 'one camera per photo'}, "
               f"{s['matcher']} matching, reprojection error "
               f"{s['mean_reprojection_error_px']} px) in {s['seconds']['total']:.0f} s")
    if s["unregistered"]:
        more = " ..." if len(s["unregistered"]) > 10 else ""
        typer.echo(f"not registered: {', '.join(s['unregistered'][:10])}{more}")
    typer.echo(f"scene {out}; next: svolsdf reconstruct {out} --views auto -o RUN")


app.command("calibrate")(with_dataclass_flags(calibrate, CalibrateConfig, CALIBRATE_FLAGS))


# --------------------------------------------------------------------------- mvs / synth
def mvs(
    scene: Annotated[Path, typer.Argument(help="Scene folder (any format `svolsdf info` reads).")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Output folder.")],
    views: Annotated[str | None, typer.Option("--views", help=VIEWS_HELP)] = None,
    size: Annotated[str | None, typer.Option(
        "--size", help="Working size WxH (default: as reconstruct, at most 768 wide).")
    ] = None,
    depth_range: Annotated[str | None, typer.Option(
        "--depth-range", help="NEAR,FAR z-depth in world units for every view (default: the "
                              "scene's per-view ranges).")] = None,
    **options,  # the flags of MVS_FLAGS (`with_dataclass_flags`), by parameter name
) -> None:
    """MVS alone: per-view depth, confidence and probability volumes, and a fused point cloud.

    Writes OUT/mvs/stage{1,2,3}/<view>.npz, OUT/depth/<view>.npy (+ PNG; stage-3 z-depth in
    world units at the backbone's MVS size, 2x the working size for the plane sweep),
    OUT/confidence/<view>.npy (+ PNG), OUT/points.ply and OUT/mvs.json. A stopped job resumes:
    the rerun reads back the stages that finished.
    """
    from svolsdf.commands.mvs import run_mvs
    from svolsdf.scene.loaders import scene_folder
    from svolsdf.scene.size import parse_size

    values = dataclass_values(MVS_FLAGS, options)
    weights = values["weights"]
    scene = scene_folder(scene)
    out = output_dir(out, "output folder", "-o", create=False)
    if weights is not None:
        weights = input_file(weights, "weights file", "--weights")
    rng = None
    if depth_range is not None:
        try:
            near, far = (float(x) for x in depth_range.replace(",", " ").split())
        except ValueError:
            raise InputError(f"--depth-range must be NEAR,FAR (e.g. 425,931); got "
                             f"{depth_range!r}") from None
        rng = (near, far)
    cfg = MVSJobConfig(**{**values, "weights": weights}, scene=scene, out=out,
                       views=_input_views(scene, views), depth_range=rng,
                       size=None if size is None else parse_size(size))
    _check_mvs_inputs(cfg)
    with _own_output_folder(out, "svolsdf mvs"):
        s = run_mvs(cfg)
        if "fusion" in s and not s["fusion"]["points_total"]:
            (out / "points.ply").unlink(missing_ok=True)
            raise InputError(f"{out}: fusion kept no point: no pixel's depth agrees between "
                             f"the views {s['views']}; check that the cameras look at the "
                             "object and overlap (svolsdf info SCENE --sheet sheet.png)")
    typer.echo(f"mvs ({s['backbone']}) on views {s['views']} at {s['size'][0]}x{s['size'][1]}: "
               f"{s['seconds']['total']:.1f} s")
    if "fusion" in s:
        typer.echo(f"points: {out / 'points.ply'} ({s['fusion']['points_total']} points)")
    typer.echo(f"depth:  {out / 'depth'}/<view>.npy, volumes in {out / 'mvs'}")


app.command("mvs")(with_dataclass_flags(mvs, MVSJobConfig, MVS_FLAGS))


def _input_views(scene: Path, views: str | None) -> list[int]:
    """The input views ``--views`` names (ids or ``auto [N]``), by default those reconstruct
    takes (`svolsdf.pipeline.views.default_views`)."""
    from svolsdf.pipeline.views import auto_views, default_views
    from svolsdf.scene.loaders import load_scene

    auto = _parse_auto_views(views)
    if views is not None and not auto:
        return _parse_views(views)
    probe = load_scene(scene, load_images=False)
    return auto_views(probe, auto) if auto else default_views(probe)


def _check_mvs_inputs(cfg) -> None:
    """The checks of reconstruct before any work (`svolsdf.scene.checks`): an output that is
    the scene, inside it or another command's folder; images below the cascade's size and
    cameras that see nothing in common (headers and cameras only: no pixel is read)."""
    from svolsdf.scene.checks import check_output_folder, check_scene
    from svolsdf.scene.loaders import load_scene
    from svolsdf.scene.size import working_size

    check_output_folder(cfg.out, cfg.scene, "svolsdf mvs")
    probe = load_scene(cfg.scene, views=cfg.views, load_images=False)
    size = working_size(probe.width, probe.height, image_size=cfg.size)
    if len(probe) >= 2:  # fewer: run_mvs says so
        check_scene(load_scene(cfg.scene, views=cfg.views, load_images=False,
                               image_size=size), use_masks=False)


@contextlib.contextmanager
def _own_output_folder(out: Path, command: str):
    """Create OUT if needed and hold its lock (`svolsdf.io.runfolder.folder_lock`) while
    ``command`` writes it; a folder this call created is removed again when the command fails
    before writing anything into it."""
    import shutil

    from svolsdf.io.paths import output_dir
    from svolsdf.io.runfolder import LOCK_NAME, folder_lock

    new = not out.exists()
    output_dir(out)
    ok = False
    try:
        with folder_lock(out, command):
            yield
            ok = True
    finally:
        if not ok and new and {p.name for p in out.iterdir()} <= {LOCK_NAME}:
            # OUT, or the folder a link OUT points to (the link stays as it was)
            shutil.rmtree(os.path.realpath(out), ignore_errors=True)


def synth(
    out: Annotated[Path | None, typer.Option(
        "--out", "-o", help="Scene folder to write (new, empty, or an earlier synthetic "
                            "scene).")] = None,
    old_out: Annotated[Path | None, typer.Argument(hidden=True, show_default=False)] = None,
    size: Annotated[str, typer.Option("--size", help="Image size WxH.")] = "768x576",
    cameras_from: Annotated[Path | None, typer.Option(
        "--cameras-from", help="Borrow the cameras of this IDR scene (cameras.npz or "
                               "cameras_sphere.npz, image/).")] = None,
    camera_views: Annotated[str | None, typer.Option(
        "--camera-views", help="With --cameras-from: the view ids to borrow, e.g. "
                               "'25 22 28 1 10 23' (default: --views evenly spaced ids).")
    ] = None,
    **options,  # the flags of SYNTH_FLAGS (`with_dataclass_flags`), by parameter name
) -> None:
    """Render a synthetic scene with exact ground truth (IDR layout, gt_depth/, gt_points.ply)."""
    from svolsdf.scene.size import parse_size
    from svolsdf.scene.synthetic import make_synthetic_scene

    values = dataclass_values(SYNTH_FLAGS, options)
    if (out is None) == (old_out is None):  # the positional OUT of earlier versions still works
        raise InputError("give the scene folder to write as -o OUT" if out is None else
                         f"two scene folders given ({old_out} and -o {out}): give -o OUT only")
    out = out if out is not None else old_out

    out = output_dir(out, "scene folder", "-o", create=False)
    if cameras_from is not None:
        cameras_from = input_dir(cameras_from, "IDR scene folder", "--cameras-from")
    w, h = parse_size(size)
    ids = None
    if camera_views is not None:
        if cameras_from is None:
            raise InputError("--camera-views needs --cameras-from")
        try:
            ids = [int(t) for t in camera_views.replace(",", " ").split()]
        except ValueError:
            raise InputError(f"--camera-views: expected view ids, got {camera_views!r}") from None
        values["views"] = len(ids)
    cfg = SynthConfig(**values, width=w, height=h,
                      cameras_from=None if cameras_from is None else str(cameras_from),
                      camera_views=ids)
    path = make_synthetic_scene(out, cfg)
    typer.echo(f"synthetic scene ({cfg.views} views, {w}x{h}, {cfg.object}, seed {cfg.seed}): "
               f"{path}")


app.command("synth")(with_dataclass_flags(synth, SynthConfig, SYNTH_FLAGS))


