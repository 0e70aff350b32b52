"""The ``svolsdf`` command: argument parsing only; the work happens in the package.

Each sub-command maps its options onto the package's functions / dataclass configs. Bad input
(`svolsdf.errors.InputError` and its subclasses, missing files) ends with exit status 2 and one
line naming the file and the problem; ``--debug`` shows the traceback instead.
"""

from __future__ import annotations

import logging
import signal
import sys
from pathlib import Path
from typing import Annotated

import typer

from svolsdf.errors import InputError, RunInterrupted

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    help="S-VolSDF: surfaces, point clouds and novel views from a few calibrated photos.",
    pretty_exceptions_enable=False,
)

_STATE = {"debug": False}


class _Stopped(Exception):
    """A run that Ctrl-C stopped, with its message (typer would turn the `RunInterrupted`, a
    KeyboardInterrupt, into a bare exit status 130)."""


def _run_pipeline(pipeline) -> dict:
    try:
        return pipeline.run()
    except RunInterrupted as e:
        raise _Stopped(str(e)) from None


@app.callback()
def _root(
    debug: Annotated[bool, typer.Option("--debug", help="Show tracebacks on errors.")] = False,
    verbose: Annotated[bool, typer.Option("--verbose", "-v", help="More log output.")] = False,
) -> None:
    _STATE["debug"] = debug
    logging.basicConfig(
        level=logging.DEBUG if verbose else logging.INFO,
        format="%(levelname)s %(name)s: %(message)s",
    )


# --------------------------------------------------------------------------- commands
# Each command lives in its own section below; keep sections independent.


# --------------------------------------------------------------------------- info
def _parse_views(text: str | None) -> list[int] | None:
    """'25,22,28' or '25 22 28' -> [25, 22, 28]; None -> None."""
    if text is None:
        return None
    out = []
    for tok in text.replace(",", " ").split():
        try:
            v = int(tok)
        except ValueError:
            raise InputError(f"--views: '{tok}' is not a view id (give integers, e.g. "
                             f"--views 25,22,28)") from None
        if v in out:
            raise InputError(f"--views {text}: view {v} is given twice (give each view once)")
        out.append(v)
    if not out:
        raise InputError("--views: no view ids given (e.g. --views 25,22,28)")
    return out


def _parse_auto_views(text: str | None) -> int | None:
    """'auto' -> 3, 'auto 5' -> 5; anything else -> None (view ids)."""
    if text is None:
        return None
    tok = text.replace(",", " ").split()
    if not tok or tok[0].lower() != "auto":
        return None
    if len(tok) > 2 or (len(tok) == 2 and not tok[1].isdigit()):
        raise InputError(f"--views: '{text}' is neither view ids nor 'auto [N]' (e.g. --views "
                         f"auto 3)")
    n = int(tok[1]) if len(tok) == 2 else 3
    if n < 2:
        raise InputError(f"--views auto {n}: need at least 2 views")
    return n


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
    from svolsdf.scene.loaders import load_scene

    light: int | str = int(lighting) if lighting.isdigit() else lighting
    s = load_scene(scene, views=_parse_views(views), load_images=False, lighting=light)
    typer.echo(describe_scene(s))
    if sheet is not None:
        out = contact_sheet(s, sheet)
        typer.echo(f"contact sheet {out}")


# --------------------------------------------------------------------------- evaluate
@app.command("evaluate")
def evaluate(
    out: Annotated[Path, typer.Argument(help="Run folder (points.ply, mesh.ply, renders/, ...).")],
    gt_points: Annotated[Path | None, typer.Option(
        "--gt-points", help="Ground-truth points (.ply or (N,3) .npy) for the generic Chamfer "
                            "and F-score.")] = None,
    dtu_gt: Annotated[Path | None, typer.Option(
        "--dtu-gt", help="DTU ground-truth root (ObsMask/, Points/stl/): DTU Chamfer protocol."
    )] = None,
    scan: Annotated[int | None, typer.Option(
        "--scan", help="DTU scan number (default: from the scene).")] = None,
    scene: Annotated[Path | None, typer.Option(
        "--scene", help="Scene folder with the ground-truth images (default: from "
                        "OUT/config.yaml).")] = None,
    views: Annotated[str | None, typer.Option(
        "--views", help="View ids to evaluate, e.g. '1,2,9' (default: every "
                        "renders/<id>.png).")] = None,
    threshold: Annotated[float | None, typer.Option(
        "--threshold", help="F-score threshold in world units (default: 1% of the ground "
                            "truth's bounding-box diagonal).")] = None,
    lpips_net: Annotated[str, typer.Option(
        "--lpips-net", help="LPIPS backbone: vgg (the paper's) or alex.")] = "vgg",
    lpips_weights: Annotated[Path | None, typer.Option(
        "--lpips-weights", help="LPIPS weights file or folder (default: shared/weights/lpips)."
    )] = None,
    ssim_data_range: Annotated[float, typer.Option(
        "--ssim-data-range", help="SSIM data range; 2.0 reproduces the released code.")] = 1.0,
    no_report: Annotated[bool, typer.Option(
        "--no-report", help="Write metrics.json only.")] = False,
) -> None:
    """Chamfer / F-score and PSNR / SSIM / LPIPS of a run: OUT/metrics.json and OUT/report.html."""
    from svolsdf.evaluate.run import EvaluateConfig, evaluate_run

    cfg = EvaluateConfig(out=out, gt_points=gt_points, dtu_gt=dtu_gt, scan=scan, scene=scene,
                         views=_parse_views(views), threshold=threshold, lpips_net=lpips_net,
                         lpips_weights=lpips_weights, ssim_data_range=ssim_data_range,
                         report=not no_report)
    m = evaluate_run(cfg)
    c, im = m["chamfer"], m["images"]
    lp = im["lpips"]
    typer.echo(f"chamfer acc {c['accuracy']} comp {c['completeness']} overall {c['overall']}; "
               f"fscore {m['fscore']}; psnr {im['psnr']['mean']} ssim {im['ssim']['mean']} "
               f"lpips {lp['mean']}" + (f" ({lp['missing']})" if lp.get("missing") and
                                        im["psnr"]["mean"] is not None else ""))
    typer.echo(f"wrote {out / 'metrics.json'}" + ("" if no_report else
                                                   f" and {out / 'report.html'}"))


@app.command("report")
def report(
    out: Annotated[Path, typer.Argument(help="Run folder (points.ply, mesh.ply, renders/, ...).")],
    scene: Annotated[Path | None, typer.Option(
        "--scene", help="Scene folder with the input photos (default: from OUT/config.yaml).")
    ] = None,
) -> None:
    """Regenerate OUT/report.html from the run folder and OUT/metrics.json (no metrics computed:
    `svolsdf evaluate` computes them and writes the report too)."""
    from svolsdf.evaluate.run import write_run_report

    path = write_run_report(out, scene_path=scene)
    typer.echo(f"report {path}")


# --------------------------------------------------------------------------- benchmark
@app.command("benchmark")
def benchmark(
    scenes: Annotated[str, typer.Option(
        "--scenes", help="Scene folders: --scenes A B ... (or one quoted, space-separated "
                         "string).")],
    modes: Annotated[str, typer.Option(
        "--modes", help="Pipeline modes: --modes svolsdf mvs-only volsdf.")
    ] = "svolsdf mvs-only volsdf",
    out: Annotated[Path, typer.Option(
        "--out", "-o", help="Output folder: OUT/<scene>/<mode>/ runs and "
                            "OUT/benchmark.{md,csv,json}.")] = Path("benchmark"),
    preset_name: Annotated[str, typer.Option("--preset", help="Config preset: fast or paper.")
                           ] = "fast",
    steps: Annotated[int | None, typer.Option(
        "--steps", help="Optimization steps (default: the preset's).")] = None,
    views: Annotated[str | None, typer.Option(
        "--views", help="Input view ids for every scene, e.g. --views 25 22 28; several sets "
                        "separated by ';' each make a job: --views '25 22 28; 23 24 33' "
                        "(default: the pipeline's choice).")] = None,
    size: Annotated[str | None, typer.Option(
        "--size", help="Working image size WxH (default: the pipeline's).")] = None,
    device: Annotated[str | None, typer.Option(
        "--device", help="auto, cpu or cuda (default: the preset's).")] = None,
    dtu_gt: Annotated[Path | None, typer.Option(
        "--dtu-gt", help="DTU ground-truth root (ObsMask/, Points/stl/): DTU Chamfer for "
                         "scenes named scanNN (or --scan).")] = None,
    scan: Annotated[int | None, typer.Option(
        "--scan", help="DTU scan number for scenes whose name has none.")] = None,
    lpips_net: Annotated[str, typer.Option(
        "--lpips-net", help="LPIPS backbone: vgg or alex.")] = "vgg",
    report: Annotated[bool, typer.Option(
        "--report/--no-report", help="Also write each run's report.html.")] = False,
    render: Annotated[bool, typer.Option(
        "--render/--no-render", help="Render the held-out views (volume rendering and IBR) of "
                                     "runs with a field for PSNR / SSIM / LPIPS.")] = True,
    render_size: Annotated[str | None, typer.Option(
        "--render-size", help="Size WxH of those renders (default: the working size).")
    ] = None,
    executor: Annotated[str, typer.Option(
        "--executor", help="Where the jobs run: local (this process, one after another) or "
                           "ray (one Ray task per job; pip install \"svolsdf\\[cluster]\").")
    ] = "local",
    address: Annotated[str | None, typer.Option(
        "--address", help="Ray cluster to join, e.g. auto or ray://head:10001 (default: start "
                          "a local Ray). --executor ray only.")] = None,
    cpus_per_job: Annotated[float, typer.Option(
        "--cpus-per-job", help="CPUs Ray reserves per job (its torch threads). --executor ray "
                               "only.")] = 1.0,
    gpus_per_job: Annotated[float, typer.Option(
        "--gpus-per-job", help="GPUs Ray reserves per job (use with --device cuda). "
                               "--executor ray only.")] = 0.0,
) -> None:
    """Run the pipeline on scenes x modes (x view sets), evaluate, and tabulate like the paper's
    Table 1.

    Ground truth: synthetic scenes their own (what the input views observe, as evaluate), DTU's
    with --dtu-gt. Image metrics on the held-out views, rendered by each run with a field.
    Each job runs into OUT/<scene>/<mode>/; a rerun skips
    finished jobs and resumes interrupted ones. Writes OUT/benchmark.md, .csv, .json and .png.
    """
    from svolsdf.evaluate.benchmark import BenchmarkConfig, run_benchmark
    from svolsdf.evaluate.executors import ExecutorConfig
    from svolsdf.scene.size import parse_size

    sets = [_parse_views(t) for t in views.split(";")] if views is not None else [None]
    cfg = BenchmarkConfig(
        scenes=[Path(s) for s in scenes.split()],
        modes=modes.replace(",", " ").split(), out=out, preset=preset_name, steps=steps,
        views=sets[0] if len(sets) == 1 else None, view_sets=sets if len(sets) > 1 else None,
        size=None if size is None else parse_size(size),
        device=device, dtu_gt=dtu_gt, scan=scan, lpips_net=lpips_net, report=report,
        render=render, render_size=None if render_size is None else parse_size(render_size,
                                                                               "--render-size"),
        executor=ExecutorConfig(name=executor, address=address, cpus_per_job=cpus_per_job,
                                gpus_per_job=gpus_per_job))
    try:
        rows = run_benchmark(cfg)
    except RunInterrupted as e:  # the stage that stopped, not a bare status 130
        raise _Stopped(str(e)) from None
    failed = sum(r["status"] != "ok" for r in rows)
    typer.echo((out / "benchmark.md").read_text())
    typer.echo(f"wrote {out / 'benchmark.md'}, {out / 'benchmark.csv'}, "
               f"{out / 'benchmark.png'} and {out / 'benchmark.json'} ({len(rows)} runs" +
               (f", {failed} failed)" if failed else ")"))


# --------------------------------------------------------------------------- reconstruct / demo
def _parse_size(text: str | None) -> list[int] | None:
    """'768x576' -> [768, 576]; None stays None (`svolsdf.scene.size.parse_size`)."""
    from svolsdf.scene.size import parse_size

    return None if text is None else list(parse_size(text))


def build_config(scene: Path | None, config: Path | None, preset_name: str | None,
                 overrides: dict, labels: dict[str, str] | None = None,
                 sets: list[str] | None = None) -> object:
    """Config from --config (or the preset), then the command-line overrides, then ``--set``
    items, validated (`svolsdf.config.validate_config`) before anything runs.

    Args:
        overrides: dotted config key -> value (None: not given).
        labels: dotted config key -> its option, for error messages.
        sets: ``--set section.option=value`` items (`svolsdf.config.parse_set`).
    """
    from svolsdf.config import apply_overrides, load_config, parse_set, preset

    if config is not None:
        cfg = load_config(config)
        if preset_name is not None and preset_name != cfg.preset:
            raise InputError(f"--preset {preset_name} contradicts {config} (preset "
                             f"{cfg.preset}); drop one of them")
    else:
        cfg = preset(preset_name or "fast")
    apply_overrides(cfg, {"scene.path": None if scene is None else str(scene), **overrides},
                    labels={"scene.path": "SCENE", **(labels or {})})
    given = parse_set(sets)
    if given:
        apply_overrides(cfg, given, labels={k: f"--set {k}" for k in given}, skip_none=False)
    if not cfg.scene.path:
        raise InputError("no scene given (pass SCENE or a --config with scene.path)")
    return cfg


@app.command("config")
def config_cmd(
    preset_name: Annotated[str, typer.Option(
        "--preset", help="fast (default) or paper.")] = "fast",
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
    from svolsdf.config import apply_overrides, config_yaml, load_config, parse_set, preset

    cfg = load_config(config) if config is not None else preset(preset_name)
    given = parse_set(set_)
    if given:
        apply_overrides(cfg, given, labels={k: f"--set {k}" for k in given}, skip_none=False)
    typer.echo(config_yaml(cfg), nl=False)


#: config key -> the `reconstruct` option that sets it (for error messages)
_RECONSTRUCT_OPTIONS = {
    "scene.views": "--views", "scene.image_size": "--size", "mvs.backbone": "--backbone",
    "mvs.weights": "--weights", "mvs.scale": "--mvs-scale", "train.mode": "--mode",
    "train.ablation": "--ablation", "train.steps": "--steps", "device": "--device",
    "output.mesh_resolution": "--mesh-resolution", "train.seed": "--seed",
    "field.background": "--background", "threads": "--threads",
    "output.fusion_network": "--fusion-network",
    "output.fusion_network_weights": "--fusion-network",
}


@app.command("reconstruct")
def reconstruct(
    scene: Annotated[Path | None, typer.Argument(
        help="Scene folder (any format `svolsdf info` reads); optional with --config.")] = None,
    out: Annotated[Path, typer.Option("--out", "-o", help="Output folder.")] = Path("out"),
    views: Annotated[str | None, typer.Option(
        "--views", help="Input view ids, e.g. --views 25 22 28, or --views auto [N]: N (3) views "
                        "with good overlap and baselines (default: DTU's 25 22 28, or a "
                        "central view and its two best source views).")] = None,
    size: Annotated[str | None, typer.Option(
        "--size", help="Working size WxH (default: 768 wide, never upsampled).")] = None,
    preset_name: Annotated[str | None, typer.Option(
        "--preset", help="fast (default: minutes on a CPU) or paper (METHOD.md constants).")
    ] = None,
    backbone: Annotated[str | None, typer.Option(
        "--backbone", help="MVS backbone: planesweep (default), casmvsnet, patchmatchnet.")
    ] = None,
    weights: Annotated[Path | None, typer.Option(
        "--weights", help="Weights of a learned MVS backbone.")] = None,
    mvs_scale: Annotated[float | None, typer.Option(
        "--mvs-scale", help="MVS at this multiple of the working size (mvs.scale; default: "
                            "the backbone's).")] = None,
    mode: Annotated[str | None, typer.Option(
        "--mode", help="svolsdf (default), mvs-only, or volsdf (no MVS prior).")] = None,
    ablation: Annotated[str | None, typer.Option(
        "--ablation", help="soft-consistency-only, mse, no-prob-volume or ce.")] = None,
    steps: Annotated[int | None, typer.Option("--steps", help="Optimization steps.")] = None,
    device: Annotated[str | None, typer.Option(
        "--device", help="auto (default), cpu or cuda.")] = None,
    threads: Annotated[int | None, typer.Option(
        "--threads", help="torch CPU threads (default: the cores this process may use).")] = None,
    config: Annotated[Path | None, typer.Option(
        "--config", help="A config.yaml (e.g. from an earlier OUT) to start from.")] = None,
    mesh_resolution: Annotated[int | None, typer.Option(
        "--mesh-resolution", help="Marching-cubes resolution.")] = None,
    seed: Annotated[int | None, typer.Option("--seed", help="Random seed.")] = None,
    background: Annotated[bool | None, typer.Option(
        "--background/--no-background",
        help="NeRF++ inverted-sphere background for unbounded scenes (METHOD.md 5.5).")] = None,
    fusion_network: Annotated[Path | None, typer.Option(
        "--fusion-network", help="Weights of a PatchmatchNet (TorchScript) to start from the "
                                 "field's depth and fuse as a further hypothesis "
                                 "(output.fusion_network).")] = None,
    set_: Annotated[list[str] | None, typer.Option(
        "--set", help="Any option as section.option=value (YAML value), repeatable, applied "
                      "last: --set train.steps=200 --set output.mesh_method=poisson; "
                      "`svolsdf config` lists them all.")] = None,
    no_progress: Annotated[bool, typer.Option("--no-progress", help="No progress bars.")] = False,
) -> None:
    """Reconstruct a scene: MVS, S-VolSDF optimization, guided MVS, fusion and mesh.

    Writes OUT/points.ply, OUT/mesh.ply, OUT/depth/<view>.npy (+ PNG), OUT/config.yaml, OUT/log
    and OUT/timing.json. A rerun reuses finished stages and resumes an interrupted optimization.
    """
    from svolsdf.pipeline import Pipeline

    auto = _parse_auto_views(views)
    cfg = build_config(scene, config, preset_name, {
        "scene.views": None if auto else _parse_views(views),
        "scene.view_selection": "auto" if auto else None,
        "scene.num_views": auto or None, "scene.image_size": _parse_size(size),
        "mvs.backbone": backbone, "mvs.weights": None if weights is None else str(weights),
        "mvs.scale": mvs_scale, "train.mode": mode, "train.ablation": ablation,
        "train.steps": steps, "device": device, "output.mesh_resolution": mesh_resolution,
        "train.seed": seed, "field.background": background, "threads": threads,
        "output.fusion_network": None if fusion_network is None else "patchmatchnet",
        "output.fusion_network_weights": None if fusion_network is None else str(fusion_network),
    }, _RECONSTRUCT_OPTIONS, sets=set_)
    if auto:  # auto also replaces the views a --config file lists
        cfg.scene.views = None
    pipe = Pipeline(cfg, out, progress=not no_progress)
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
    writes OUT/run/metrics.json and OUT/run/report.html (open it in a browser).
    """
    import json

    from svolsdf.config import apply_overrides, preset
    from svolsdf.evaluate.synthetic import synthetic_chamfer
    from svolsdf.io.ply import read_ply
    from svolsdf.pipeline import Pipeline
    from svolsdf.scene.synthetic import SynthConfig, make_synthetic_scene

    w, h = _parse_size(size)
    scene_dir = out / "scene"
    # the run's options first: a bad one fails before minutes of scene rendering
    cfg = apply_overrides(preset("fast"), {"scene.path": str(scene_dir), "train.steps": steps},
                          labels={"train.steps": "--steps"})
    if not (scene_dir / "gt_points.ply").is_file():
        typer.echo(f"generating a synthetic scene ({w}x{h}, seed {seed}) in {scene_dir} ...")
        make_synthetic_scene(scene_dir, SynthConfig(views=5, width=w, height=h, seed=seed))
    run = out / "run"
    typer.echo(f"reconstructing into {run} (fast preset) ...")
    summary = _run_pipeline(Pipeline(cfg, run, progress=not no_progress))
    views = json.loads((run / "views.json").read_text())["inputs"]
    lines = []
    result = {}
    for name in ("points", "mesh"):
        p = summary.get(name)
        if p and Path(p).is_file():
            r = synthetic_chamfer(read_ply(p)["points"], scene_dir, views)
            result[name] = r
            lines.append(f"{name:6s} {p}: Chamfer accuracy {r['accuracy']:.3f} mm, completeness "
                         f"{r['completeness']:.3f} mm, overall {r['overall']:.3f} mm, F-score "
                         f"{r['fscore']:.3f} at {r['threshold']:.2f} mm")
    (run / "demo_metrics.json").write_text(json.dumps(result, indent=1))
    typer.echo("\n".join(lines))
    typer.echo(f"total {summary['timing']['total']['seconds']:.0f} s; inputs {views}; "
               f"outputs in {run}")
    from svolsdf.evaluate.run import EvaluateConfig, evaluate_run

    evaluate_run(EvaluateConfig(out=run))
    typer.echo(f"report {run / 'report.html'}")


# --------------------------------------------------------------------------- render
@app.command("render")
def render(
    out: Annotated[Path, typer.Argument(help="Run folder of svolsdf reconstruct.")],
    views: Annotated[str | None, typer.Option(
        "--views", help="Scene view ids to render, e.g. --views 1 2 3 (default: the held-out "
                        "test views of OUT/views.json, else the inputs).")] = None,
    path: Annotated[str | None, typer.Option(
        "--path", help="'orbit': a camera path through the input views (frames + video) "
                       "instead of scene views.")] = None,
    frames: Annotated[int, typer.Option("--frames", help="Orbit frames.")] = 60,
    ibr: Annotated[bool, typer.Option(
        "--ibr", help="Also image-based rendering (METHOD.md 7) -> OUT/renders_ibr/.")] = False,
    size: Annotated[str | None, typer.Option(
        "--size", help="Render size WxH, e.g. 768x576 (default: the run's working size).")
    ] = None,
    chunk: Annotated[int, typer.Option("--chunk", help="Rays per batch.")] = 4096,
) -> None:
    """Novel views: OUT/renders/<id>.png (+ depth/, normals/), OUT/renders_ibr/<id>.png, orbit."""
    from svolsdf.render.novel import render_outputs

    res = render_outputs(out, views=_parse_views(views), path=path, ibr=ibr,
                         size=_parse_size(size), frames=frames, chunk=chunk, progress=True)
    w, h = res["size"]
    typer.echo(f"rendered {len(res['files'])} view(s) at {w}x{h} "
               f"({res['seconds_per_view']:.1f} s per view) -> {out / 'renders'}"
               + (f"; IBR -> {out / 'renders_ibr'}" if res["ibr_files"] else ""))
    for key in ("video", "video_ibr"):
        if res[key] is not None:
            typer.echo(f"video {res[key]}")


# --------------------------------------------------------------------------- calibrate
@app.command("calibrate")
def calibrate(
    inputs: Annotated[Path, typer.Argument(help="A folder of photos or a video file.")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Scene folder to write (COLMAP "
                                                          "model + images/).")],
    max_size: Annotated[int, typer.Option(
        "--max-size", help="Longest image side in pixels for SfM and the scene's images.")
    ] = 1600,
    matcher: Annotated[str, typer.Option(
        "--matcher", help="exhaustive (photos), sequential (video frames) or auto.")] = "auto",
    frames: Annotated[int, typer.Option("--frames", help="Frames sampled from a video.")] = 40,
    threads: Annotated[int, typer.Option(
        "--threads", help="CPU threads for structure from motion (-1: all cores).")] = -1,
    no_progress: Annotated[bool, typer.Option("--no-progress", help="No progress bars.")] = False,
) -> None:
    """Camera poses for your own photos or video (structure from motion with pycolmap).

    Writes OUT as a COLMAP scene that `svolsdf reconstruct OUT --views auto` reads: the registered
    photos (undistorted) in OUT/images/, cameras and sparse points in OUT/sparse/0/, and a summary
    in OUT/calibration.json.
    """
    from svolsdf.calibrate import CalibrateConfig
    from svolsdf.calibrate import calibrate as run_calibrate

    cfg = CalibrateConfig(max_size=max_size, matcher=matcher, frames=frames, threads=threads,
                          progress=not no_progress)
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


# --------------------------------------------------------------------------- mvs / synth
@app.command("mvs")
def mvs(
    scene: Annotated[Path, typer.Argument(help="Scene folder (any format `svolsdf info` reads).")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Output folder.")],
    views: Annotated[str | None, typer.Option(
        "--views", help="Input view ids, e.g. --views 25 22 28 (default: all views).")] = None,
    backbone: Annotated[str, typer.Option(
        "--backbone", help="planesweep (training-free, default), casmvsnet or patchmatchnet.")
    ] = "planesweep",
    weights: Annotated[Path | None, typer.Option(
        "--weights", help="Weights of casmvsnet (required) or patchmatchnet (default: "
                          "../shared/weights/patchmatchnet).")] = None,
    size: Annotated[str | None, typer.Option(
        "--size", help="Working size WxH (default: as reconstruct, at most 768 wide).")
    ] = None,
    depth_range: Annotated[str | None, typer.Option(
        "--depth-range", help="NEAR,FAR z-depth in world units for every view (default: the "
                              "scene's per-view ranges).")] = None,
    no_fuse: Annotated[bool, typer.Option("--no-fuse", help="Skip the fused points.ply.")
                       ] = False,
) -> None:
    """MVS alone: per-view depth, confidence and probability volumes, and a fused point cloud.

    Writes OUT/mvs/stage{1,2,3}/<view>.npz, OUT/depth/<view>.npy (+ PNG; stage-3 z-depth in
    world units at the backbone's MVS size, 2x the working size for the plane sweep),
    OUT/confidence/<view>.npy (+ PNG), OUT/points.ply and OUT/mvs.json.
    """
    from svolsdf.mvs.run import MVSJobConfig, run_mvs
    from svolsdf.scene.size import parse_size

    rng = None
    if depth_range is not None:
        try:
            near, far = (float(x) for x in depth_range.replace(",", " ").split())
        except ValueError:
            raise InputError(f"--depth-range must be NEAR,FAR (e.g. 425,931); got "
                             f"{depth_range!r}") from None
        rng = (near, far)
    cfg = MVSJobConfig(scene=scene, out=out, views=_parse_views(views), backbone=backbone,
                       weights=weights, size=None if size is None else parse_size(size),
                       depth_range=rng, fuse=not no_fuse)
    s = run_mvs(cfg)
    typer.echo(f"mvs ({s['backbone']}) on views {s['views']} at {s['size'][0]}x{s['size'][1]}: "
               f"{s['seconds']['total']:.1f} s")
    if "fusion" in s:
        typer.echo(f"points: {out / 'points.ply'} ({s['fusion']['points_total']} points)")
    typer.echo(f"depth:  {out / 'depth'}/<view>.npy, volumes in {out / 'mvs'}")


@app.command("synth")
def synth(
    out: Annotated[Path, typer.Argument(help="Output folder (new, empty, or an earlier "
                                             "synthetic scene).")],
    seed: Annotated[int, typer.Option("--seed", help="Random seed (same seed, same bytes).")
                    ] = 0,
    views: Annotated[int, typer.Option("--views", help="Number of views.")] = 9,
    size: Annotated[str, typer.Option("--size", help="Image size WxH.")] = "768x576",
    object_kind: Annotated[str, typer.Option(
        "--object", help="Object kind: random, sphere, box, torus, capsule or blobs.")
    ] = "random",
    cameras_from: Annotated[Path | None, typer.Option(
        "--cameras-from", help="Borrow the cameras of this IDR scene (cameras.npz or "
                               "cameras_sphere.npz, image/).")] = None,
) -> None:
    """Render a synthetic scene with exact ground truth (IDR layout, gt_depth/, gt_points.ply)."""
    from svolsdf.scene.size import parse_size
    from svolsdf.scene.synthetic import SynthConfig, make_synthetic_scene

    w, h = parse_size(size)
    cfg = SynthConfig(seed=seed, views=views, width=w, height=h, object=object_kind,
                      cameras_from=None if cameras_from is None else str(cameras_from))
    path = make_synthetic_scene(out, cfg)
    typer.echo(f"synthetic scene ({views} views, {w}x{h}, {object_kind}, seed {seed}): {path}")


_LIST_OPTIONS = ("--views", "--scenes", "--modes")


def join_list_options(argv: list[str]) -> list[str]:
    """``--views 25 22 28`` -> ``--views "25 22 28"`` (typer options take one value each).

    Tokens after a list option are joined until the next token that starts with ``-`` (a negative
    number still counts as a value) or, for ``--views``, is not an integer.
    """
    out: list[str] = []
    i = 0
    while i < len(argv):
        tok = argv[i]
        out.append(tok)
        i += 1
        if tok in _LIST_OPTIONS:
            vals = []
            while i < len(argv):
                t = argv[i]
                is_num = t.lstrip("-").replace(",", "").isdigit()
                if (t.startswith("-") and not is_num) or (tok == "--views" and vals and not is_num):
                    break
                vals.append(t)
                i += 1
            if vals:
                out.append(" ".join(vals))
    return out


def main(argv: list[str] | None = None) -> None:
    """Console entry point (``svolsdf``).

    Exit status: 0 done; 2 bad input, a bad option, or a file or folder that cannot be read or
    written (one line, ``--debug`` for the traceback); 130 Ctrl-C, 143 SIGTERM (one line; a
    stopped reconstruction names its stage, and a rerun resumes it).
    """
    argv = join_list_options(list(sys.argv[1:] if argv is None else argv))
    debug = "--debug" in argv
    got = []  # SIGTERM (a scheduler's or `kill`'s stop) is answered as Ctrl-C is, status 143

    def terminate(signum, frame):
        got.append(signum)
        raise KeyboardInterrupt

    try:
        previous = signal.signal(signal.SIGTERM, terminate)
    except ValueError:  # not the main thread: leave signals alone
        previous = None
    try:
        # without standalone mode typer returns the status of typer.Exit, and of Ctrl-C (130)
        code = app(args=argv, standalone_mode=False)
    except _Stopped as e:
        print(e, file=sys.stderr)
        raise SystemExit(128 + got[0] if got else 130) from None
    except (InputError, OSError) as e:  # OSError: a missing, unreadable or unwritable path
        if debug:
            raise
        msg = str(e) if not isinstance(e, OSError) or not e.filename else (
            f"{e.filename}: {e.strerror or e}"
        )
        print(f"error: {msg}", file=sys.stderr)
        raise SystemExit(2) from None
    except typer.Exit as e:
        raise SystemExit(e.exit_code) from None
    except typer.Abort:
        print("aborted", file=sys.stderr)
        raise SystemExit(130) from None
    except Exception as e:
        # click's usage errors (an unknown option, a bad value): the message, not a traceback.
        # Recognised by their interface: typer >= 0.2x raises its vendored copy of click's
        # classes, older typer the click package's own
        if callable(getattr(e, "show", None)) and isinstance(getattr(e, "exit_code", None), int):
            e.show()
            raise SystemExit(e.exit_code) from None
        raise
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
    if code == 130:
        print("terminated" if got else "interrupted", file=sys.stderr)
        code = 128 + got[0] if got else 130
    if isinstance(code, int) and code != 0:
        raise SystemExit(code)


if __name__ == "__main__":
    main()
