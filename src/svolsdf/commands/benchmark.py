"""``svolsdf benchmark``: the pipeline over scenes x modes (x input view sets), evaluated, as a
table like Table 1.

Every (scene, mode, input views) is a job (`BenchmarkJob`, `benchmark_jobs`); one job function,
`run_job`, runs the reconstruction pipeline into the job's own folder, ``OUT/<scene>/<mode>/``
(``OUT/<scene>/views-<ids>/<mode>/`` with several view sets), then `evaluate_run` scores it:

- geometry: the DTU protocol (docs/method.md 8.1) when ``dtu_gt`` is given and the scan number is
  known (from the scene's name, e.g. ``scan65``, or ``scan``); otherwise the generic two-way Chamfer
  against the scene's ``gt_points.ply`` (synthetic scenes, `make_synthetic_scene`); otherwise
  none. The fused point cloud (``points.ply``) is scored for every mode, as in the paper.
- images: PSNR / SSIM / LPIPS (docs/method.md 8.3) of the held-out views named in the run's
  ``views.json`` (``"test"``) that have a render in ``renders/``; none when there are none.

The jobs run on an executor (`svolsdf.commands.executors`): ``local``, one after another in this
process, or ``ray``, one Ray task each on a local or remote Ray cluster; both run `run_job` and
write the same tables. A job leaves its row in ``benchmark_row.json`` in its folder: a rerun does
not run finished jobs again, and an interrupted one resumes its pipeline's finished stages.

Results go to ``OUT/benchmark.md`` and ``OUT/benchmark.csv`` (rows: scenes, then the mean; per
mode: accuracy, completeness, overall Chamfer, PSNR when any run has it, time), a bar chart of
them to ``OUT/benchmark.png`` (`svolsdf.evaluate.benchmark_tables`, re-exported here), and every
run's numbers to ``OUT/benchmark.json``. The files are rewritten after each job, so an
interrupted benchmark keeps the finished rows. A job that fails is recorded (``status``, the
error) and the benchmark goes on.

Time is the sum of the pipeline's stage times from the run's ``timing.json`` (so a resumed run
still reports the compute its stages took), or the job's elapsed time without one.
"""
from __future__ import annotations

import hashlib
import json
import logging
import re
import time
from dataclasses import dataclass, field
from pathlib import Path

from svolsdf.commands.executors import ExecutorConfig, job_threads
from svolsdf.config import choices
from svolsdf.errors import InputError, raise_if_interrupted
from svolsdf.evaluate.benchmark_tables import benchmark_csv, benchmark_markdown, benchmark_plot
from svolsdf.io.paths import output_dir
from svolsdf.io.runfolder import RunFolder

__all__ = [
    "MODES",
    "METRIC_KEYS",
    "ROW_FILE",
    "BenchmarkConfig",
    "BenchmarkJob",
    "Variant",
    "benchmark_csv",
    "benchmark_jobs",
    "benchmark_markdown",
    "benchmark_plot",
    "failed_row",
    "finished_row",
    "job_config",
    "run_benchmark",
    "run_job",
    "run_metrics",
    "scan_number",
]

log = logging.getLogger(__name__)

MODES = choices("train.mode")
"""The pipeline's modes (``cfg.train.mode``'s choices, in the schema's order)."""

METRIC_KEYS = ("accuracy", "completeness", "overall", "overall_dtu_rule", "fscore", "psnr",
               "ssim", "lpips", "psnr_ibr", "ssim_ibr", "lpips_ibr", "mesh_accuracy",
               "mesh_completeness", "mesh_overall", "mesh_overall_dtu_rule", "time_s")
"""Numeric keys of a per-run metrics dict (None when not computed)."""


@dataclass
class Variant:
    """One configuration of an experiment (``svolsdf benchmark --experiment``): a preset or a
    config file, then ``--set`` items; its runs are a column of the table."""

    name: str
    """The column's name (the experiment file's key)."""
    preset: str = "fast"
    """Config preset (ignored with ``config``, whose own preset counts)."""
    sets: list[str] = field(default_factory=list)
    """``section.option=value`` items, as ``--set`` (`svolsdf.config.parse_set`)."""
    config: Path | None = None
    """A config.yaml to start from instead of the preset."""
    tuned_on: str | None = None
    """The scenes this configuration's choices were tuned on (None: its preset's,
    `svolsdf.commands.experiment.PRESET_TUNED_ON`)."""


@dataclass
class BenchmarkConfig:
    """Options of ``svolsdf benchmark``."""

    scenes: list[Path]
    """Scene folders (any format the pipeline reads)."""
    modes: list[str] = field(default_factory=lambda: list(MODES))
    """Pipeline modes to run on every scene: svolsdf, mvs-only, volsdf."""
    out: Path = Path("benchmark")
    """Output folder: OUT/<scene>/<mode>/ runs, OUT/benchmark.{md,csv,json}."""
    preset: str = "fast"
    """Config preset of every run (fast or paper)."""
    steps: int | None = None
    """Optimization steps (default: the preset's)."""
    views: list[int] | None = None
    """Input view ids for every scene (default: the pipeline's choice per scene)."""
    view_sets: list[list[int]] | None = None
    """Several input view sets for every scene, one job (and table row) each; replaces
    ``views``."""
    scene_views: list[list[int] | None] | None = None
    """Input views of particular scenes, one per scene of ``scenes`` (None: that scene takes
    ``views`` / ``view_sets``): a dataset whose scans each have their own inputs (BlendedMVS)."""
    size: tuple[int, int] | None = None
    """Working image size (W, H) (default: the pipeline's)."""
    device: str | None = None
    """auto, cpu or cuda (default: the preset's)."""
    dtu_gt: Path | None = None
    """DTU ground-truth root (ObsMask/, Points/stl/) for scenes with a DTU scan number."""
    scan: int | None = None
    """DTU scan number for scenes whose name does not contain one (scanNN)."""
    lpips_net: str = "vgg"
    """LPIPS backbone for image metrics."""
    lpips_weights: Path | None = None
    """LPIPS weights file or folder (default: shared/weights/lpips)."""
    report: bool = False
    """Also write each run's report.html."""
    render: bool = True
    """Render the held-out (test) views of runs with a field, by volume rendering and IBR,
    before scoring, so that the table has PSNR / SSIM / LPIPS (docs/method.md 7, 8.2)."""
    render_size: tuple[int, int] | None = None
    """(W, H) of those renders; None: the working size. Ground-truth images are resized to it."""
    executor: ExecutorConfig = field(default_factory=ExecutorConfig)
    """Where the jobs run: in this process (local) or as Ray tasks (`ExecutorConfig`)."""
    sets: list[str] = field(default_factory=list)
    """``--set section.option=value`` items applied to every run (after the options above)."""
    config: Path | None = None
    """``--config FILE``: every run starts from this config instead of ``preset``."""
    variants: list[Variant] | None = None
    """An experiment's configurations: each one runs on every scene and view set and is a
    column of the table (its mode from its config); replaces ``modes``, ``preset``, ``sets``
    and ``config``."""
    experiment: dict | None = None
    """What the experiment's record says beside its rows (`svolsdf.commands.experiment`):
    name, file, command, plot; None: no experiment record."""
    threads: int | None = None
    """torch intra-op threads of every job, under either executor; None: the executor's
    (`svolsdf.commands.executors.job_threads`). A job's floating-point sums, hence the last
    digits of its numbers, depend on it: the same count gives the same rows locally and on Ray."""


def scan_number(scene: str | Path) -> int | None:
    """The DTU scan number in a scene's folder name (``dtu_scan65`` -> 65), or None."""
    m = re.search(r"scan_?(\d+)", Path(scene).name, flags=re.IGNORECASE)
    return int(m.group(1)) if m else None


def _labels(scenes: list[Path]) -> list[str]:
    """Unique row labels: the folder names, with a suffix for repeats."""
    out: list[str] = []
    for s in scenes:
        name = Path(s).resolve().name or str(s)
        label, k = name, 2
        while label in out:
            label, k = f"{name}-{k}", k + 1
        out.append(label)
    return out


# --------------------------------------------------------------------------- driver
def run_metrics(metrics: dict, scene: str, mode: str, time_s: float | None,
                status: str = "ok") -> dict:
    """One benchmark row from an evaluate_run metrics dict (METRIC_KEYS, scene, mode, status,
    protocol); `run_job` adds ``views``, ``field`` (the field kind, for `method_label`) and
    ``threads`` (torch's threads the job ran with)."""
    c = metrics.get("chamfer") or {}
    cm = metrics.get("chamfer_mesh") or {}

    def image(block: str, key: str):
        return ((metrics.get(block) or {}).get(key) or {}).get("mean")

    return {"scene": scene, "mode": mode, "status": status,
            "accuracy": c.get("accuracy"), "completeness": c.get("completeness"),
            "overall": c.get("overall"), "overall_dtu_rule": c.get("overall_dtu_rule"),
            "protocol": c.get("protocol"), "fscore": metrics.get("fscore"),
            **{k + sfx: image(block, k) for block, sfx in (("images", ""),
                                                           ("images_ibr", "_ibr"))
               for k in ("psnr", "ssim", "lpips")},
            "mesh_accuracy": cm.get("accuracy"), "mesh_completeness": cm.get("completeness"),
            "mesh_overall": cm.get("overall"),
            "mesh_overall_dtu_rule": cm.get("overall_dtu_rule"),
            # which surface mesh.ply is (a table must not mix kinds in a column unsaid)
            "mesh_source": (metrics.get("mesh_source") or cm.get("mesh_source")
                            if cm.get("overall") is not None else None),
            # how it was scored: "surface" (sampled every mesh_density world units); None with
            # a mesh score: metrics.json of a time when meshes were scored by their vertices
            "mesh_sampled": cm.get("sampled") if cm.get("overall") is not None else None,
            "mesh_density": cm.get("density") if cm.get("overall") is not None else None,
            "time_s": time_s}


def _stage_seconds(run_dir: Path) -> float | None:
    t = RunFolder(run_dir).timing()
    if not t:
        return None
    secs = [v.get("seconds") for k, v in t.items() if k != "total" and isinstance(v, dict)]
    secs = [float(s) for s in secs if isinstance(s, (int, float))]
    return sum(secs) if secs else None


def _has_ground_truth(cfg: BenchmarkConfig, scene: Path) -> bool:
    """Whether a scene's runs get geometry scores: DTU's (`_ground_truth`), its gt_points.ply,
    or a synthetic scene's own."""
    from svolsdf.evaluate.synthetic import is_synthetic_scene

    return bool(_ground_truth(cfg, scene)) or is_synthetic_scene(scene)


def _ground_truth(cfg: BenchmarkConfig, scene: Path) -> dict:
    """EvaluateConfig geometry options for one scene."""
    if cfg.dtu_gt is not None:
        scan = scan_number(scene) or cfg.scan
        if scan is not None:
            return {"dtu_gt": Path(cfg.dtu_gt).absolute(), "scan": int(scan)}
    from svolsdf.evaluate.synthetic import is_synthetic_scene

    if is_synthetic_scene(scene):  # as `svolsdf evaluate`: what the input views observe
        return {}
    gt = scene / "gt_points.ply"
    if gt.is_file():
        return {"gt_points": gt}
    return {}


# --------------------------------------------------------------------------- jobs
@dataclass
class BenchmarkJob:
    """One run of the benchmark: a scene in one mode from one set of input views, and how to
    score it. Plain data (paths, numbers, strings), so it travels to a Ray worker as is."""

    scene: Path
    """Scene folder."""
    label: str
    """The run's row in the table (the scene's label, with the views when there are several
    view sets)."""
    mode: str
    """Pipeline mode (`MODES`)."""
    views: list[int] | None
    """Input view ids (None: the pipeline's choice)."""
    out: Path
    """The run folder."""
    preset: str = "fast"
    """Config preset."""
    overrides: dict = field(default_factory=dict)
    """Config overrides (`svolsdf.config.apply_overrides`: dotted key -> value, None = keep)."""
    evaluate: dict = field(default_factory=dict)
    """`EvaluateConfig` options: ground truth (gt_points or dtu_gt + scan), lpips_net,
    lpips_weights, report."""
    render: dict | None = None
    """Held-out views to render before scoring: ``{"size": [W, H] or None}`` (volume
    rendering and IBR of the run's test views); None: none."""
    variant: str | None = None
    """The experiment variant the job runs (its table column); None: the column is ``mode``."""
    sets: list[str] = field(default_factory=list)
    """``--set`` items applied last (`svolsdf.config.parse_set`)."""
    config: Path | None = None
    """Config file the run starts from instead of ``preset``."""

    @property
    def column(self) -> str:
        """The job's column in the table: its variant, else its mode."""
        return self.variant or self.mode

    def key(self) -> str:
        """What decides the job's row (not where, on what device or with how many threads it
        runs): a finished run with the same key is not run again."""
        over = {k: v for k, v in self.overrides.items() if k not in ("device", "threads")}
        # variants, --set and --config enter only when given: earlier benchmarks keep their rows
        extra = {k: v for k, v in (("variant", self.variant), ("sets", self.sets),
                                   ("config", self._config_text())) if v}
        text = json.dumps({"scene": str(Path(self.scene).resolve()), "mode": self.mode,
                           "views": self.views, "preset": self.preset, "overrides": over,
                           "evaluate": self.evaluate, "label": self.label,
                           # rows before the held-out renders and the synthetic protocol
                           "render": self.render, "rows": ROW_VERSION, **extra},
                          sort_keys=True, default=str)
        return hashlib.sha1(text.encode()).hexdigest()[:16]

    def _config_text(self) -> str | None:
        """The config file's contents (a changed file is another job), None without one."""
        if self.config is None:
            return None
        try:
            return Path(self.config).read_text()
        except OSError:
            return str(self.config)


ROW_VERSION = 3
"""Bumped when a row's contents change (2: held-out renders, the synthetic protocol, DTU-rule
and IBR columns; 3: meshes scored by their surface, ``mesh_sampled``): finished runs are scored
again, their stages reused."""

ROW_FILE = "benchmark_row.json"
"""A finished job's row in its run folder, with the job's `BenchmarkJob.key`."""


def _view_sets(cfg: BenchmarkConfig, scene: int | None = None) -> list[list[int] | None]:
    """The input view sets of every scene, or with ``scene`` (an index into ``cfg.scenes``)
    of that one (its own, ``scene_views``, when it has them)."""
    if scene is not None and cfg.scene_views and cfg.scene_views[scene] is not None:
        return [list(cfg.scene_views[scene])]
    if cfg.view_sets:
        return [list(v) for v in cfg.view_sets]
    return [list(cfg.views) if cfg.views else None]


def _columns(cfg: BenchmarkConfig) -> list[tuple[str, str | None, Variant | None]]:
    """(mode, variant name, variant) of each column: the modes, or an experiment's variants
    with the mode each one's config names."""
    if cfg.variants:
        return [(variant_mode(v), v.name, v) for v in cfg.variants]
    return [(m, None, None) for m in cfg.modes]


def variant_mode(v: Variant) -> str:
    """The ``train.mode`` a variant's config names (its ``--set`` items included)."""
    from svolsdf.config import parse_set

    mode = parse_set(v.sets).get("train.mode")
    if mode is None:
        mode = _base_config(v.preset, v.config).train.mode
    return mode


def _base_config(preset_name: str, config: Path | None):
    from svolsdf.config import load_config, preset

    return load_config(config) if config is not None else preset(preset_name)


def benchmark_jobs(cfg: BenchmarkConfig) -> list[BenchmarkJob]:
    """The jobs of a benchmark, scene-major, then view set, then mode (or variant).

    Run folders: ``OUT/<scene>/<mode>/``, or with several view sets
    ``OUT/<scene>/views-<a>-<b>-<c>/<mode>/`` (row label ``<scene> [a,b,c]``); an experiment's
    ``OUT/<scene>/<variant>/``.
    """
    threads = cfg.threads if cfg.threads is not None else job_threads(cfg.executor)
    jobs = []
    # absolute paths: a Ray worker on another node does not share this process's directory
    out = Path(cfg.out).absolute()
    for i, (scene, label) in enumerate(zip(cfg.scenes, _labels(cfg.scenes), strict=True)):
        scene = Path(scene).absolute()
        sets = _view_sets(cfg, i)
        ev = {**_ground_truth(cfg, scene), "lpips_net": cfg.lpips_net,
              "lpips_weights": None if cfg.lpips_weights is None
              else Path(cfg.lpips_weights).absolute(), "report": cfg.report}
        for views in sets:
            base, row = out / label, label
            if len(sets) > 1:
                base = base / ("views-" + "-".join(map(str, views)))
                row = f"{label} [{','.join(map(str, views))}]"
            for mode, name, v in _columns(cfg):
                config = v.config if v is not None else cfg.config
                jobs.append(BenchmarkJob(
                    scene=scene, label=row, mode=mode, views=views, out=base / (name or mode),
                    preset=v.preset if v is not None else cfg.preset, evaluate=ev,
                    render={"size": list(cfg.render_size) if cfg.render_size else None}
                    if cfg.render and mode != "mvs-only" else None,
                    overrides={"train.steps": cfg.steps, "scene.views": views,
                               "scene.image_size": list(cfg.size) if cfg.size else None,
                               "device": cfg.device, "threads": threads},
                    variant=name, sets=list(v.sets if v is not None else cfg.sets),
                    config=None if config is None else Path(config).absolute()))
    return jobs


#: the command-line option behind each override, for the messages of `validate_config`
_OPTION_LABELS = {"train.steps": "--steps", "scene.views": "--views",
                  "scene.image_size": "--size", "device": "--device", "threads": "--threads"}


def job_config(job: BenchmarkJob):
    """The pipeline `Config` of a job: its preset (or config file), the benchmark's options,
    then its ``--set`` items."""
    from svolsdf.config import apply_overrides, parse_set

    c = _base_config(job.preset, job.config)
    c.scene.path = str(job.scene)
    c.train.mode = job.mode
    if job.mode == "mvs-only" and c.mesh.method == "field":
        # mvs-only fits no field and makes points only; the preset's field mesh (paper) is
        # refused there (validate_config), and no mesh option changes an mvs-only run
        c.mesh.method = "poisson"
    c = apply_overrides(c, dict(job.overrides), labels=_OPTION_LABELS)
    given = parse_set(job.sets)
    if job.config is None:  # the released preset's per-scan constants (not over given values)
        from svolsdf.config.presets import scene_overrides

        scene_overrides(c, {k for k, v in job.overrides.items() if v is not None} | set(given))
    if given:
        where = f"variant {job.variant}: set" if job.variant else "--set"
        c = apply_overrides(c, given, labels={k: f"{where} {k}" for k in given},
                            skip_none=False)
    return c


def _field_kind(job: BenchmarkJob) -> str | None:
    """The job's ``field.kind`` (what its method is: `method_label`), None if its config is
    invalid."""
    try:
        return job_config(job).field.kind
    except InputError:
        return None


def failed_row(job: BenchmarkJob, error: BaseException) -> dict:
    """The row of a job that raised ``error``: no metrics, status "failed: <type>: <message>"."""
    msg = f"failed: {type(error).__name__}: {error}".strip().splitlines()[0]
    return {**run_metrics({}, job.label, job.column, None, status=msg), "views": job.views,
            "field": _field_kind(job), "threads": None, **_variant_keys(job)}


def _variant_keys(job: BenchmarkJob) -> dict:
    """What an experiment's row adds: the pipeline mode its variant ran (``run_mode``)."""
    return {"run_mode": job.mode} if job.variant else {}


def finished_row(job: BenchmarkJob) -> dict | None:
    """The row a previous run of this job left (`ROW_FILE`), if it finished ("ok") with the same
    `BenchmarkJob.key`; else None (the job runs, resuming the pipeline's finished stages)."""
    p = Path(job.out) / ROW_FILE
    try:
        saved = json.loads(p.read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(saved, dict) or saved.get("key") != job.key():
        return None
    row = saved.get("row")
    if not isinstance(row, dict) or row.get("status") != "ok":
        return None
    return row if "field" in row else {**row, "field": _field_kind(job)}  # an older row


def run_job(job: BenchmarkJob) -> dict:
    """Run one job: the pipeline into ``job.out`` (resuming its finished stages), then
    `evaluate_run`; returns its row (`run_metrics` plus ``views``) and writes it to
    ``job.out/benchmark_row.json``. Never raises: an error becomes a row with ``status``
    "failed: ..." (`failed_row`). The one job function of both executors."""
    from svolsdf import pipeline as pipeline_module
    from svolsdf.evaluate.scoring import EvaluateConfig, evaluate_run

    out = Path(job.out)
    t0 = time.perf_counter()
    try:
        pipeline_module.Pipeline(job_config(job), out, progress=False).run()
        elapsed = time.perf_counter() - t0
        run_views = RunFolder(out).views()  # views.json, read once
        test = run_views.test if run_views is not None else []
        if job.render is not None and test:
            from svolsdf.commands.render import render_outputs

            render_outputs(out, views=test, ibr=True, size=job.render.get("size"),
                           progress=False)
        metrics = evaluate_run(EvaluateConfig(
            out=out, scene=Path(job.scene), views=test,
            extra={"benchmark": {"scene": job.label, "mode": job.mode,
                                 **({"variant": job.variant} if job.variant else {})}},
            **job.evaluate))
        t = _stage_seconds(out)
        import torch

        row = {**run_metrics(metrics, job.label, job.column, t if t is not None else elapsed),
               "views": job.views, "field": _field_kind(job),
               "threads": torch.get_num_threads(),  # what the job's sums ran on
               **_variant_keys(job)}
    except Exception as e:  # one failed run must not lose the others
        raise_if_interrupted()  # but a Ctrl-C that a library made an error stops them all
        log.error("%s / %s failed: %s", job.label, job.column, e,
                  exc_info=not isinstance(e, InputError))
        row = failed_row(job, e)
    try:
        out.mkdir(parents=True, exist_ok=True)
        tmp = out / (ROW_FILE + ".tmp")
        tmp.write_text(json.dumps({"key": job.key(), "row": row}, indent=1))
        tmp.replace(out / ROW_FILE)
    except OSError as e:
        log.warning("%s: could not write %s: %s", out, ROW_FILE, e)
    return row


# --------------------------------------------------------------------------- driver
def _write_tables(cfg: BenchmarkConfig, rows: list[dict]) -> None:
    out = Path(cfg.out)
    cols = [name or mode for mode, name, _ in _columns(cfg)]
    views = (f", input views {cfg.views}" if cfg.views and not cfg.view_sets else
             f", input view sets {cfg.view_sets}" if cfg.view_sets else "")
    what = ("Variants " + "; ".join(f"{v.name} = {_variant_text(v)}" for v in cfg.variants)
            if cfg.variants else _variant_text(Variant("", cfg.preset, cfg.sets, cfg.config)))
    notes = [what + (f", {cfg.steps} steps" if cfg.steps else "") + views
             + (f", size {cfg.size[0]}x{cfg.size[1]}" if cfg.size else "") + "."]
    for path, text in ((out / "benchmark.md", benchmark_markdown(
            rows, cols, title=f"svolsdf benchmark ({len({r['scene'] for r in rows})} "
                              f"scenes)", notes=notes)),
                       (out / "benchmark.csv", benchmark_csv(rows, cols)),
                       (out / "benchmark.json", json.dumps(rows, indent=1, allow_nan=False))):
        tmp = path.with_name(path.name + ".tmp")
        tmp.write_text(text)
        tmp.replace(path)
    try:
        benchmark_plot(rows, out / "benchmark.png", cols)
    except Exception as e:  # the tables matter; the picture is a convenience
        log.warning("benchmark plot failed: %s", e)
    if cfg.experiment is not None:
        from svolsdf.commands.experiment import write_experiment

        write_experiment(cfg, rows)


def _variant_text(v: Variant) -> str:
    """``preset fast, --set a=1 b=2`` (or ``config FILE``) for the table's notes."""
    base = f"config {Path(v.config).name}" if v.config is not None else f"preset {v.preset}"
    return base + (", --set " + " ".join(v.sets) if v.sets else "")


def run_benchmark(cfg: BenchmarkConfig, progress: bool = True) -> list[dict]:
    """Run and evaluate every job (scene x view set x mode); write OUT/benchmark.{md,csv,json}
    and OUT/benchmark.png.

    Jobs run on ``cfg.executor`` (`svolsdf.commands.executors`: in this process, or as Ray
    tasks), each with `run_job` into its own run folder. A job that finished before with the
    same settings is not run again (its row is read back, `finished_row`); an interrupted one
    resumes its pipeline's finished stages. The tables are rewritten as each job finishes, with
    the finished rows in job order, so the executors write the same tables.

    Args:
        cfg: `BenchmarkConfig`.
        progress: show a progress bar over the jobs.

    Returns:
        The per-run rows (see `run_metrics`, plus the input ``views``), in job order
        (`benchmark_jobs`).

    Raises:
        InputError: a missing scene or ground-truth folder, an unknown mode or executor, a DTU
            scene without a scan number or its scan's files, --scan without --dtu-gt, a view
            set that a scene does not have, or Ray options without Ray; raised before any job
            starts.
    """
    from svolsdf.commands.benchmark_checks import validate_benchmark
    from svolsdf.commands.executors import check_executor, run_jobs

    cfg.scenes = [Path(s) for s in cfg.scenes]
    cfg.out = Path(cfg.out)
    validate_benchmark(cfg)
    check_executor(cfg.executor)
    if cfg.executor.name == "ray" and cfg.device == "cuda" and cfg.executor.gpus_per_job <= 0:
        # Ray hides the GPUs from tasks that reserve none
        raise InputError("--device cuda with --executor ray needs --gpus-per-job > 0 (e.g. 1): "
                         "Ray gives each job only the GPUs it reserves")
    output_dir(cfg.out)
    for scene in cfg.scenes:
        if not _has_ground_truth(cfg, scene):
            log.warning("%s: no ground-truth geometry (a synthetic scene's, gt_points.ply, or "
                        "--dtu-gt with a scan number): Chamfer columns stay empty", scene)
    jobs = benchmark_jobs(cfg)
    rows: list[dict | None] = [finished_row(j) for j in jobs]
    todo = [i for i, r in enumerate(rows) if r is None]
    if len(todo) < len(jobs):
        log.info("%d of %d job(s) finished before (%s): not run again",
                 len(jobs) - len(todo), len(jobs), ROW_FILE)
    for i in todo:
        log.info("job %s / %s -> %s", jobs[i].label, jobs[i].column, jobs[i].out)

    def on_row(k: int, row: dict) -> None:
        i = todo[k]
        rows[i] = row
        log.info("finished %s / %s: %s", jobs[i].label, jobs[i].column, row["status"])
        _write_tables(cfg, [r for r in rows if r is not None])

    if len(todo) < len(jobs):
        _write_tables(cfg, [r for r in rows if r is not None])
    run_jobs(run_job, [jobs[i] for i in todo], on_row, cfg.executor, failed_row,
             progress=progress, done=len(jobs) - len(todo))
    return [r for r in rows if r is not None]
