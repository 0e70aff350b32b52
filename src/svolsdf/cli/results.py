"""Commands over finished runs: evaluate, report, benchmark, render."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from svolsdf.cli.app import _STATE, _parse_size, _parse_views, _Stopped, app
from svolsdf.cli.flags import (
    EVALUATE_FLAGS,
    RENDER_IBR_FLAGS,
    dataclass_values,
    with_dataclass_flags,
)
from svolsdf.errors import RunInterrupted
from svolsdf.evaluate.scoring import EvaluateConfig
from svolsdf.ibr import IBRConfig
from svolsdf.io.paths import input_dir, input_file, input_path, output_dir


# --------------------------------------------------------------------------- evaluate
def evaluate(
    out: Annotated[Path, typer.Argument(help="Run folder (points.ply, mesh.ply, renders/, ...).")],
    views: Annotated[str | None, typer.Option(
        "--views", help="View ids to evaluate, e.g. '1,2,9' (default: every "
                        "renders/<id>.png).")] = None,
    **options,  # the flags of EVALUATE_FLAGS (`with_dataclass_flags`), by parameter name
) -> None:
    """Chamfer / F-score and PSNR / SSIM / LPIPS of a run: OUT/metrics.json and OUT/report.html."""
    from svolsdf.evaluate.run_outputs import check_views_rendered, metric_lines
    from svolsdf.evaluate.scoring import evaluate_run
    from svolsdf.scene.loaders import scene_folder

    values = dataclass_values(EVALUATE_FLAGS, options)
    gt_points, dtu_gt, scene = values["gt_points"], values["dtu_gt"], values["scene"]
    lpips_weights = values["lpips_weights"]
    out = input_dir(out, "run folder")
    if gt_points is not None:
        gt_points = input_file(gt_points, "ground-truth points file", "--gt-points")
    if dtu_gt is not None:
        dtu_gt = input_dir(dtu_gt, "DTU ground-truth folder", "--dtu-gt")
    if scene is not None:
        scene = scene_folder(scene, "--scene")
    if lpips_weights is not None:  # asked for: weights that cannot be read are an error
        lpips_weights = input_path(lpips_weights, "LPIPS weights file or folder",
                                   "--lpips-weights")
    check_views_rendered(out, _parse_views(views))
    cfg = EvaluateConfig(**{**values, "gt_points": gt_points, "dtu_gt": dtu_gt, "scene": scene,
                            "lpips_weights": lpips_weights}, out=out, views=_parse_views(views))
    m = evaluate_run(cfg)
    for line in metric_lines(m):
        typer.echo(line)
    typer.echo(f"wrote {out / 'metrics.json'}" + (f" and {out / 'report.html'}"
                                                   if cfg.report else ""))


app.command("evaluate")(with_dataclass_flags(evaluate, EvaluateConfig, EVALUATE_FLAGS))


@app.command("report")
def report(
    out: Annotated[Path, typer.Argument(help="Run folder (points.ply, mesh.ply, renders/, ...).")],
    scene: Annotated[Path | None, typer.Option(
        "--scene", help="Scene folder with the input photos (default: from OUT/config.yaml).")
    ] = None,
) -> None:
    """Regenerate OUT/report.html from the run folder and OUT/metrics.json (no metrics computed:
    `svolsdf evaluate` computes them and writes the report too)."""
    from svolsdf.evaluate.run_report import write_run_report
    from svolsdf.scene.loaders import scene_folder

    out = input_dir(out, "run folder")
    path = write_run_report(out, scene_path=None if scene is None else scene_folder(
        scene, "--scene"))
    typer.echo(f"report {path}")


# --------------------------------------------------------------------------- benchmark
_ALL_MODES = ("svolsdf", "mvs-only", "volsdf")


@app.command("benchmark")
def benchmark(
    scenes: Annotated[list[Path] | None, typer.Option(
        "--scenes", help="Scene folders, one argument each: --scenes A B ... or --scenes A "
                         "--scenes B (a quoted path with spaces is one folder).")] = None,
    modes: Annotated[list[str], typer.Option(
        "--modes", help="Pipeline modes: --modes svolsdf mvs-only volsdf (one argument each, "
                        "or comma-separated).")] = list(_ALL_MODES),  # noqa: B006, B008
    out: Annotated[Path, typer.Option(
        "--out", "-o", help="Output folder: OUT/<scene>/<mode>/ runs and "
                            "OUT/benchmark.{md,csv,json}.")] = Path("benchmark"),
    experiment: Annotated[Path | None, typer.Option(
        "--experiment", help="Experiment file (YAML: scenes, views, size, variants NAME: "
                             "{preset, set, config}): scenes x view sets x variants, with "
                             "OUT/experiment.{json,md,png} (instead of --scenes and --modes).")
    ] = None,
    data: Annotated[Path | None, typer.Option(
        "--data", help="Folder the experiment file's scenes are relative to (default: the "
                       "current folder).")] = None,
    preset_name: Annotated[str | None, typer.Option(
        "--preset", help="Config preset of every run: fast, draft, paper or released "
                         "(default fast).")] = None,
    config: Annotated[Path | None, typer.Option(
        "--config", help="Config file every run starts from (instead of --preset).")] = None,
    sets: Annotated[list[str] | None, typer.Option(
        "--set", help="section.option=value for every run, after the other options (repeat "
                      "for several).")] = None,
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
    threads: Annotated[int | None, typer.Option(
        "--threads", help="torch threads of every job (default: this machine's cores locally, "
                          "--cpus-per-job on Ray); the same count gives the same numbers under "
                          "both executors.")] = None,
) -> None:
    """Run the pipeline on scenes x modes (x view sets), evaluate, and tabulate like the paper's
    Table 1.

    Ground truth: synthetic scenes their own (what the input views observe, as evaluate), DTU's
    with --dtu-gt. Image metrics on the held-out views, rendered by each run with a field.
    Each job runs into OUT/<scene>/<mode>/; a rerun skips
    finished jobs and resumes interrupted ones. Writes OUT/benchmark.md, .csv, .json and .png.
    Exit status 1 when a job failed (each named on the last line), 2 for bad input.
    """
    import sys

    from svolsdf.commands.benchmark import BenchmarkConfig, run_benchmark
    from svolsdf.commands.executors import ExecutorConfig
    from svolsdf.errors import InputError
    from svolsdf.scene.loaders import scene_folder
    from svolsdf.scene.size import parse_size

    out = output_dir(out, "output folder", "-o", create=False)
    common = dict(
        out=out, device=device, scan=scan, lpips_net=lpips_net, report=report, render=render,
        render_size=None if render_size is None else parse_size(render_size, "--render-size"),
        executor=ExecutorConfig(name=executor, address=address, cpus_per_job=cpus_per_job,
                                gpus_per_job=gpus_per_job), threads=threads)
    if experiment is not None:
        from svolsdf.commands.experiment import experiment_config, public_command

        given = [o for o, v in (("--scenes", scenes), ("--modes", modes != list(_ALL_MODES)),
                                ("--views", views),
                                ("--preset", preset_name), ("--config", config),
                                ("--set", sets)) if v]
        if given:
            raise InputError(f"--experiment {experiment}: {', '.join(given)} would contradict "
                             "the experiment file; put them in the file (scenes, views, "
                             "variants)")
        cfg = experiment_config(
            experiment, data=data, steps=steps, size=None if size is None else parse_size(size),
            command=public_command(["svolsdf", *_STATE.get("argv", sys.argv[1:])]),
            dtu_gt=None if dtu_gt is None else input_dir(dtu_gt, "DTU ground-truth folder",
                                                         "--dtu-gt"), **common)
    else:
        if data is not None:
            raise InputError("--data: only with --experiment (the file's scenes are relative "
                             "to it)")
        if not scenes:
            raise InputError("benchmark: give scenes (--scenes A B ...) or an experiment file "
                             "(--experiment FILE)")
        # each scene is one argument as the shell gave it (`svolsdf.cli.expand_list_options`)
        scenes = [scene_folder(s, "--scenes") for s in scenes]
        if dtu_gt is not None:
            dtu_gt = input_dir(dtu_gt, "DTU ground-truth folder", "--dtu-gt")
        vsets = [_parse_views(t) for t in views.split(";")] if views is not None else [None]
        # mode names have no spaces, so a quoted "svolsdf volsdf" still names two
        names = [m for v in modes for m in v.replace(",", " ").split()]
        cfg = BenchmarkConfig(
            scenes=scenes, modes=names, preset=preset_name or "fast", steps=steps,
            views=vsets[0] if len(vsets) == 1 else None,
            view_sets=vsets if len(vsets) > 1 else None,
            size=None if size is None else parse_size(size), dtu_gt=dtu_gt,
            sets=list(sets or []), config=config, **common)
    try:
        rows = run_benchmark(cfg)
    except RunInterrupted as e:  # the stage that stopped, not a bare status 130
        raise _Stopped(str(e)) from None
    failed = [r for r in rows if r["status"] != "ok"]
    typer.echo((out / "benchmark.md").read_text())
    typer.echo(f"wrote {out / 'benchmark.md'}, {out / 'benchmark.csv'}, "
               f"{out / 'benchmark.png'} and {out / 'benchmark.json'} ({len(rows)} runs" +
               (f", {len(failed)} failed)" if failed else ")"))
    if cfg.experiment is not None:
        typer.echo(f"experiment record {out / 'experiment.json'}, rendered as "
                   f"{out / 'experiment.md'} and {out / 'experiment.png'}")
    if failed:  # the tables keep the other jobs' rows; the status says the benchmark is not whole
        jobs = "; ".join(f"{r['scene']} / {r['mode']} ({r['status']})" for r in failed)
        typer.echo(f"error: {len(failed)} of {len(rows)} job(s) failed: {jobs}; a rerun runs "
                   "only those again", err=True)
        raise typer.Exit(1)




# --------------------------------------------------------------------------- render
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
        "--ibr", help="Also image-based rendering (the input photos reprojected onto the "
                      "surface and blended) -> OUT/renders_ibr/.")] = False,
    size: Annotated[str | None, typer.Option(
        "--size", help="Render size WxH, e.g. 768x576 (default: the run's working size).")
    ] = None,
    chunk: Annotated[int, typer.Option("--chunk", help="Rays per batch.")] = 4096,
    **options,  # the flags of RENDER_IBR_FLAGS (`with_dataclass_flags`), by parameter name
) -> None:
    """Novel views: OUT/renders/<id>.png (+ depth/, normals/), OUT/renders_ibr/<id>.png, orbit."""
    from svolsdf.commands.render import render_outputs
    from svolsdf.errors import InputError

    values = dataclass_values(RENDER_IBR_FLAGS, options)
    if values["unseen"] not in ("render", "inpaint"):
        raise InputError(f"--ibr-unseen {values['unseen']!r}: expected 'render' or 'inpaint'")
    if values["hole_depth"] not in ("none", "mesh"):
        raise InputError(f"--ibr-holes {values['hole_depth']!r}: expected 'none' or 'mesh'")
    out = input_dir(out, "run folder")
    res = render_outputs(out, views=_parse_views(views), path=path, ibr=ibr,
                         size=_parse_size(size), frames=frames, chunk=chunk, progress=True,
                         ibr_config=IBRConfig(**values))
    w, h = res["size"]
    typer.echo(f"rendered {len(res['files'])} view(s) at {w}x{h} "
               f"({res['seconds_per_view']:.1f} s per view) -> {out / 'renders'}"
               + (f"; IBR -> {out / 'renders_ibr'}" if res["ibr_files"] else ""))
    for key in ("video", "video_ibr"):
        if res[key] is not None:
            typer.echo(f"video {res[key]}")


app.command("render")(with_dataclass_flags(render, IBRConfig, RENDER_IBR_FLAGS))


# --------------------------------------------------------------------------- export
@app.command("export")
def export(
    out: Annotated[Path, typer.Argument(help="Finished run folder of svolsdf reconstruct.")],
    dest: Annotated[Path | None, typer.Option(
        "--output", "-o", help="Where to write the export (default: OUT/export).")] = None,
) -> None:
    """The run for other tools: cameras (nerfstudio transforms.json, a COLMAP model, plain
    JSON), points with normals, each mesh method's mesh, the mesh coloured from the photos
    (PLY vertex colours, OBJ with a texture)."""
    from svolsdf.commands.export import export_run

    res = export_run(out, dest, progress=True)
    for what, why in res.skipped.items():
        typer.echo(f"not made: {what}: {why}")
    typer.echo(f"exported {', '.join(res.files)} -> {res.dest}")
