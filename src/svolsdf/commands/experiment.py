"""``svolsdf benchmark --experiment FILE``: an experiment file names scenes, view sets and
variants (a preset or config file plus ``--set`` items each); the benchmark runs scenes x view
sets x variants (`svolsdf.commands.benchmark`, with its executors and resume) and writes one
results record, ``OUT/experiment.json``, with the Markdown table and the plot rendered from it.

The file (YAML)::

    name: ablation                  # optional, default: the file's name
    description: ...                # optional, one paragraph for the table's heading
    scenes: [dtu_scan65, ...]       # folders, relative to --data (default: the current folder)
    views: [[25, 22, 28], ...]      # optional input view sets, one table row each
    scene_views: {bmvs_scan1: [9, 10, 55], ...}   # optional: a scene's own inputs (not views)
    size: 768x576                   # optional working size
    steps: 300                      # optional optimization steps of every variant
    dtu_gt: dtu_gt                  # optional DTU ground truth, relative to --data
    plot: {kind: sweep, x: train.gce_q}   # optional: bars (default) | sweep | accuracy-completeness
    variants:
      full: {preset: fast}
      ce: {preset: fast, set: [train.ablation=ce], tuned_on: "..."}

A variant's ``config`` (a config.yaml) is relative to the experiment file. Everything is
checked when the file is read, before any job: an unknown key, a malformed value or a variant
whose config `svolsdf.config.validate_config` refuses is one line naming the file and the key.

The record holds the rows (`svolsdf.commands.benchmark.run_metrics`), the variants with the
scenes each one's choices were tuned on (`PRESET_TUNED_ON` unless the file says), the commit,
the machine and the command line (paths outside the current folder shortened to their names);
`experiment_markdown` and `experiment_plot` render it and nothing else.
"""

from __future__ import annotations

import json
import logging
import os
import platform
import sys
import time
from pathlib import Path

from svolsdf.commands.benchmark import BenchmarkConfig, Variant, variant_mode
from svolsdf.errors import InputError
from svolsdf.evaluate.benchmark_tables import benchmark_markdown, benchmark_plot

__all__ = ["EXPERIMENT_FILE", "PLOT_KINDS", "PRESET_TUNED_ON", "experiment_markdown",
           "experiment_plot", "git_commit", "load_experiment", "machine", "public_command",
           "write_experiment"]

log = logging.getLogger(__name__)

EXPERIMENT_FILE = "experiment.json"
"""The results record in the benchmark's output folder."""

PLOT_KINDS = ("bars", "sweep", "accuracy-completeness")
"""bars: Chamfer (and PSNR) per scene and variant; sweep: a metric against a ``--set`` value
of the variants (``plot.x``); accuracy-completeness: one point per variant and scene."""

PRESET_TUNED_ON = {
    "fast": "synthetic scenes (seeds 0, 3, 11, blobs 7; 401, 402; 501, 502) and DTU scan 65 "
            "against its 49-view pseudo ground truth (docs/presets.md)",
    "draft": "the fast preset's scenes, then synthetic seeds 411 and 412 (docs/presets.md)",
    "paper": "none: the paper's constants (docs/method.md)",
    "released": "none: the released code's constants (docs/method.md 9)",
}
"""The scenes each preset's choices were tuned on, for the record of an experiment whose
variant does not say (`docs/presets.md` has the evidence)."""

_TOP_KEYS = ("name", "description", "scenes", "views", "scene_views", "size", "steps", "dtu_gt",
             "variants", "plot", "paper")
_VARIANT_KEYS = ("preset", "set", "config", "tuned_on")


# --------------------------------------------------------------------------- reading
def load_experiment(path: str | Path, data: str | Path | None = None,
                    check_scenes: bool = True) -> dict:
    """Read and check an experiment file.

    Args:
        path: the YAML file.
        data: the folder the file's scenes and ``dtu_gt`` are relative to (default: the current
            folder).
        check_scenes: check that the scene folders exist (False: only the file and the
            variants' configs, as the tests of the shipped files do without the data).

    Returns:
        ``{"name", "description", "paper", "scenes": [Path], "view_sets": [[int]] | None,
        "scene_views": [[int] | None] (one per scene) | None,
        "size": (W, H) | None, "steps": int | None, "dtu_gt": Path | None, "variants":
        [Variant], "plot": dict}``.

    Raises:
        InputError: ``<file>: <key>: <problem>``, one line.
    """
    import yaml

    path = Path(path)
    if not path.is_file():
        raise InputError(f"--experiment {path}: no such file")
    try:
        spec = yaml.safe_load(path.read_text())
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as e:
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise InputError(f"{path}: not a readable YAML file ({first})") from None

    def bad(key: str, problem: str) -> InputError:
        return InputError(f"{path}: {key}: {problem}")

    if not isinstance(spec, dict):
        raise InputError(f"{path}: expected a mapping with scenes and variants")
    unknown = [k for k in spec if k not in _TOP_KEYS]
    if unknown:
        raise bad(str(unknown[0]), f"unknown key (known: {', '.join(_TOP_KEYS)})")
    root = Path(data) if data is not None else Path.cwd()
    scenes = spec.get("scenes")
    if not isinstance(scenes, list) or not scenes or \
            not all(isinstance(s, str) and s for s in scenes):
        raise bad("scenes", "expected a list of scene folders, e.g. [dtu_scan65]")
    scene_dirs = [root / s for s in scenes]
    if check_scenes:
        for s, d in zip(scenes, scene_dirs, strict=True):
            if not d.is_dir():
                raise bad("scenes", f"{s} is no folder under {root} (give the data folder "
                                    "with --data)")
    def view_list(v) -> bool:
        return (isinstance(v, list) and len(v) >= 2 and len(set(v)) == len(v)
                and all(isinstance(i, int) and not isinstance(i, bool) for i in v))

    view_sets = spec.get("views")
    if view_sets is not None:
        if not isinstance(view_sets, list) or not view_sets or not all(
                view_list(v) for v in view_sets):
            raise bad("views", "expected a list of view id lists, each of at least two "
                               "different ids, e.g. [[25, 22, 28]]")
    scene_views = spec.get("scene_views")
    if scene_views is not None:
        if not isinstance(scene_views, dict) or not scene_views:
            raise bad("scene_views", "expected a mapping SCENE: [view ids], e.g. "
                                     "{bmvs_scan1: [9, 10, 55]}")
        for s, v in scene_views.items():
            if s not in scenes:
                raise bad(f"scene_views.{s}", "not one of the file's scenes")
            if not view_list(v):
                raise bad(f"scene_views.{s}", "expected a list of at least two different "
                                              "view ids, e.g. [9, 10, 55]")
        scene_views = [scene_views.get(s) for s in scenes]
    size = spec.get("size")
    if size is not None:
        from svolsdf.scene.size import parse_size

        try:
            size = parse_size(str(size))
        except InputError as e:
            raise bad("size", str(e)) from None
    steps = spec.get("steps")
    if steps is not None and (not isinstance(steps, int) or isinstance(steps, bool)
                              or steps < 0):
        raise bad("steps", f"expected a whole number >= 0, got {steps!r}")
    dtu_gt = spec.get("dtu_gt")
    if dtu_gt is not None:
        if not isinstance(dtu_gt, str):
            raise bad("dtu_gt", "expected a folder")
        dtu_gt = root / dtu_gt
        if check_scenes and not dtu_gt.is_dir():
            raise bad("dtu_gt", f"{spec['dtu_gt']} is no folder under {root}")
    variants = _variants(spec.get("variants"), path, bad)
    plot = _plot(spec.get("plot"), variants, bad)
    for v in variants:  # every variant's config is valid, before any job
        try:
            cfg = _variant_config(v)
            if steps is not None:
                cfg.train.steps = steps
        except InputError as e:
            raise bad(f"variants.{v.name}", str(e)) from None
    for key in ("name", "description", "paper"):
        if spec.get(key) is not None and not isinstance(spec[key], str):
            raise bad(key, "expected text")
    return {"name": spec.get("name") or path.stem, "description": spec.get("description"),
            "paper": spec.get("paper"), "scenes": scene_dirs,
            "view_sets": [list(v) for v in view_sets] if view_sets else None,
            "scene_views": scene_views, "size": size,
            "steps": steps, "dtu_gt": dtu_gt, "variants": variants, "plot": plot}


def _variants(spec, path: Path, bad) -> list[Variant]:
    from svolsdf.config import PRESETS

    if not isinstance(spec, dict) or not spec:
        raise bad("variants", "expected a mapping NAME: {preset: fast, set: [...]}")
    out = []
    for name, v in spec.items():
        key = f"variants.{name}"
        if not isinstance(name, str) or not name or "/" in name or name.startswith("."):
            raise bad(key, "a variant's name is its run folder: a plain name")
        v = {} if v is None else v
        if not isinstance(v, dict):
            raise bad(key, "expected a mapping {preset: ..., set: [...]}")
        unknown = [k for k in v if k not in _VARIANT_KEYS]
        if unknown:
            raise bad(f"{key}.{unknown[0]}", f"unknown key (known: {', '.join(_VARIANT_KEYS)})")
        preset = v.get("preset", "fast")
        if preset not in PRESETS:
            raise bad(f"{key}.preset", f"unknown preset {preset!r} (choose from "
                                       f"{', '.join(PRESETS)})")
        sets = v.get("set") or []
        if not isinstance(sets, list) or not all(isinstance(s, str) and "=" in s for s in sets):
            raise bad(f"{key}.set", "expected a list of section.option=value items")
        config = v.get("config")
        if config is not None:
            config = path.parent / str(config)
            if not config.is_file():
                raise bad(f"{key}.config", f"{v['config']}: no such file beside {path.name}")
        tuned = v.get("tuned_on")
        if tuned is not None and not isinstance(tuned, str):
            raise bad(f"{key}.tuned_on", "expected text naming the scenes")
        out.append(Variant(name, preset, list(sets), config, tuned))
    return out


def _plot(spec, variants: list[Variant], bad) -> dict:
    from svolsdf.config import parse_set

    spec = {"kind": "bars"} if spec is None else spec
    if not isinstance(spec, dict) or spec.get("kind", "bars") not in PLOT_KINDS:
        raise bad("plot", f"expected {{kind: {' | '.join(PLOT_KINDS)}}}")
    unknown = [k for k in spec if k not in ("kind", "x", "metric")]
    if unknown:
        raise bad(f"plot.{unknown[0]}", "unknown key (known: kind, x, metric)")
    plot = {"kind": spec.get("kind", "bars"), "metric": spec.get("metric", "overall")}
    from svolsdf.commands.benchmark import METRIC_KEYS

    if plot["metric"] not in METRIC_KEYS:
        raise bad("plot.metric", f"unknown metric {plot['metric']!r} (choose from "
                                 f"{', '.join(METRIC_KEYS)})")
    if plot["kind"] == "sweep":
        x = spec.get("x")
        if not isinstance(x, str):
            raise bad("plot.x", "a sweep plots against a --set option, e.g. x: train.gce_q")
        values = {}
        for v in variants:
            given = parse_set(v.sets)
            if x not in given or isinstance(given[x], bool) or \
                    not isinstance(given[x], (int, float)):
                raise bad("plot.x", f"variant {v.name} sets no number for {x}")
            values[v.name] = float(given[x])
        plot.update(x=x, values=values)
    return plot


def _variant_config(v: Variant):
    """A variant's `Config` (validated; no scene)."""
    from svolsdf.config import apply_overrides, load_config, parse_set, preset

    cfg = load_config(v.config) if v.config is not None else preset(v.preset)
    given = parse_set(v.sets)
    return apply_overrides(cfg, given, labels={k: f"set {k}" for k in given}, skip_none=False)


def experiment_config(path: str | Path, out: Path, data: str | Path | None = None,
                      command: str | None = None, check_scenes: bool = True,
                      **options) -> BenchmarkConfig:
    """The `BenchmarkConfig` of an experiment file (`load_experiment`); ``options`` are further
    `BenchmarkConfig` fields from the command line (device, executor, lpips_net, dtu_gt, ...),
    and the file's ``steps``, ``size`` and ``dtu_gt`` give way to given ones."""
    spec = load_experiment(path, data, check_scenes=check_scenes)
    steps = options.pop("steps", None)
    size = options.pop("size", None)
    dtu_gt = options.pop("dtu_gt", None)
    return BenchmarkConfig(
        scenes=spec["scenes"], out=out, variants=spec["variants"],
        views=None, view_sets=spec["view_sets"], scene_views=spec["scene_views"],
        size=size or spec["size"],
        steps=steps if steps is not None else spec["steps"], dtu_gt=dtu_gt or spec["dtu_gt"],
        # the commit the jobs run from: taken now, since the checkout may move while they run
        experiment={"name": spec["name"], "description": spec["description"],
                    "commit": git_commit(),
                    "paper": spec["paper"], "file": Path(path).name, "plot": spec["plot"],
                    "command": command}, **options)


# --------------------------------------------------------------------------- the record
def git_commit() -> str:
    """The short HEAD commit of the checkout svolsdf runs from, "unknown" outside one."""
    import subprocess

    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"],
                              cwd=Path(__file__).resolve().parent, check=True,
                              capture_output=True, text=True, timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def machine() -> dict:
    """The CPU model, its cores, and the Python and torch versions."""
    import torch

    cpu = platform.processor() or "unknown"
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return {"cpu": cpu, "cores": os.cpu_count(), "python": platform.python_version(),
            "torch": torch.__version__,
            "gpu": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None}


def public_command(argv: list[str]) -> str:
    """A command line as a results record keeps it: absolute paths become DATA/<name> (also
    after NAME=), so no machine's folders are written."""
    def one(a: str) -> str:
        name, eq, rest = a.partition("=")
        if eq and rest.startswith("/"):
            return f"{name}=DATA/{Path(rest).name}"
        return f"DATA/{Path(a).name}" if a.startswith("/") else a

    return " ".join(one(a) for a in argv)


def write_experiment(cfg: BenchmarkConfig, rows: list[dict]) -> Path:
    """Write ``OUT/experiment.json`` (the rows with the experiment's variants, commit, machine
    and command), then ``OUT/experiment.md`` and ``OUT/experiment.png`` rendered from it."""
    from svolsdf import __version__

    exp = dict(cfg.experiment or {})
    record = {
        "experiment": exp.get("name"), "description": exp.get("description"),
        "paper": exp.get("paper"), "file": exp.get("file"),
        "command": exp.get("command") or public_command(["svolsdf", *sys.argv[1:]]),
        "commit": exp.get("commit") or git_commit(), "version": __version__,
        "machine": machine(),
        "date": time.strftime("%Y-%m-%d", time.gmtime()),
        "scenes": list(dict.fromkeys(r["scene"] for r in rows)),
        "view_sets": cfg.view_sets or ([cfg.views] if cfg.views else None),
        "scene_views": {Path(s).name: v for s, v in zip(cfg.scenes, cfg.scene_views or [],
                                                         strict=False) if v is not None} or None,
        "size": list(cfg.size) if cfg.size else None, "steps": cfg.steps,
        "variants": [{"name": v.name, "preset": None if v.config else v.preset, "set": v.sets,
                      "config": Path(v.config).name if v.config else None,
                      "mode": variant_mode(v),
                      "tuned_on": v.tuned_on or PRESET_TUNED_ON.get(
                          v.preset if v.config is None else "", "not recorded")}
                     for v in cfg.variants or []],
        "plot": exp.get("plot") or {"kind": "bars", "metric": "overall"},
        "rows": rows,
    }
    out = Path(cfg.out)
    path = out / EXPERIMENT_FILE
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(record, indent=1, allow_nan=False))
    tmp.replace(path)
    record = json.loads(path.read_text())  # the renderings read the record, nothing else
    md = out / "experiment.md"
    md.with_name(md.name + ".tmp").write_text(experiment_markdown(record))
    md.with_name(md.name + ".tmp").replace(md)
    try:
        experiment_plot(record, out / "experiment.png")
    except Exception as e:  # the record and the table matter; the picture is a convenience
        log.warning("experiment plot failed: %s", e)
    return path


# --------------------------------------------------------------------------- renderings
def experiment_markdown(record: dict) -> str:
    """The Markdown of an experiment record: its table (`benchmark_markdown`, one column
    group per variant), then what ran: variants with the scenes their choices were tuned on,
    the commit, the machine, the command."""
    names = [v["name"] for v in record["variants"]]
    m = record.get("machine") or {}
    notes = ["## What ran", ""]
    if record.get("paper"):
        notes += [f"Paper: {record['paper']}.", ""]
    notes += ["| variant | preset / config | set | mode | choices tuned on |",
              "|---|---|---|---|---|"]
    for v in record["variants"]:
        notes.append(f"| {v['name']} | {v['preset'] or v['config']} | "
                     f"{' '.join(f'`{s}`' for s in v['set']) or '-'} | {v['mode']} | "
                     f"{v['tuned_on']} |")
    views = record.get("view_sets")
    own = record.get("scene_views") or {}
    notes += ["", f"Scenes: {', '.join(record['scenes'])}"
              + (f"; input view sets {views}" if views else
                 "" if own else "; the pipeline's input views")
              + "".join(f"; {s}: input views {v}" for s, v in own.items())
              + (f"; size {record['size'][0]}x{record['size'][1]}" if record.get("size") else "")
              + (f"; {record['steps']} steps" if record.get("steps") is not None else "") + ".",
              "", f"Commit {record['commit']} (svolsdf {record['version']}), {record['date']}; "
              f"{m.get('cpu', 'unknown CPU')}, {m.get('cores', '?')} cores"
              + (f", {m['gpu']}" if m.get("gpu") else "") + f", torch {m.get('torch', '?')}.",
              "", f"Command: `{record['command']}`"
              + (f" (experiment file `{record['file']}`)." if record.get("file") else ".")]
    pgt = record.get("pseudo_gt")
    if pgt:  # DTU scans without their STL: scored against a many-view reference
        f = lambda x: "-" if x is None else f"{x:.2f}"  # noqa: E731
        notes += ["", "## Against the pseudo ground truth", "", pgt["what"], "",
                  "| scene | variant | points acc. | points comp. | points Chamfer | DTU rule "
                  "| F | mesh Chamfer | mesh DTU rule |",
                  "|---|---|" + "---:|" * 7]
        for r in pgt["rows"]:
            notes.append(f"| {r['scene']} | {r['variant']} | {f(r.get('points_accuracy'))} | "
                         f"{f(r.get('points_completeness'))} | {f(r.get('points_overall'))} | "
                         f"{f(r.get('points_overall_dtu_rule'))} | "
                         f"{f(r.get('points_fscore'))} | {f(r.get('mesh_overall'))} | "
                         f"{f(r.get('mesh_overall_dtu_rule'))} |")
    field = record.get("field_alone")
    if field:  # the guide depth against the ground truth, before stages 2-3 and fusion
        notes += ["", "## The field alone", "", field["what"], "",
                  "| scene | " + " | ".join(names) + " |", "|---|" + "---:|" * len(names)]
        for scene in dict.fromkeys(r["scene"] for r in field["rows"]):
            cell = {r["variant"]: r for r in field["rows"] if r["scene"] == scene}
            notes.append(f"| {scene} | " + " | ".join(
                f"{cell[n]['median_mm']:.2f} ({100 * cell[n]['within_2mm']:.0f} %)"
                if n in cell else "-" for n in names) + " |")
    title = f"Experiment {record['experiment']}"
    text = benchmark_markdown(record["rows"], names, title=title, notes=notes)
    if record.get("description"):
        head, _, rest = text.partition("\n\n")
        text = f"{head}\n\n{record['description'].strip()}\n\n{rest}"
    return text


def experiment_plot(record: dict, path: str | Path) -> Path:
    """The plot of an experiment record (``record["plot"]["kind"]``, `PLOT_KINDS`): bars as
    `benchmark_plot`; a sweep of the metric against each variant's ``plot.x`` value, one line
    per scene; or accuracy against completeness, one point per variant and scene (the fusion
    thresholds' trade-off). Written as a PNG (matplotlib)."""
    rows, plot = record["rows"], record.get("plot") or {"kind": "bars"}
    names = [v["name"] for v in record["variants"]]
    path = Path(path)
    pgt = {(r["scene"], r["variant"]): r for r in (record.get("pseudo_gt") or {}).get("rows", [])}
    if pgt and not any(r.get("overall") is not None for r in rows):
        # DTU scans without their STL: the bars show the Chamfer against the pseudo ground truth
        rows = [{**r, **{k: pgt[(r["scene"], r["mode"])].get(f"points_{k}")
                         for k in ("accuracy", "completeness", "overall")}}
                if (r["scene"], r["mode"]) in pgt else r for r in rows]
    if plot["kind"] == "bars":
        return benchmark_plot(rows, path, names)
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.5, 4.0))
    ok = [r for r in rows if r.get("status", "ok") == "ok"]
    for scene in dict.fromkeys(r["scene"] for r in ok):
        mine = {r["mode"]: r for r in ok if r["scene"] == scene}
        if plot["kind"] == "sweep":
            pts = sorted((plot["values"][n], mine[n].get(plot["metric"])) for n in names
                         if n in mine and mine[n].get(plot["metric"]) is not None)
            ax.plot([p[0] for p in pts], [p[1] for p in pts], "o-", label=scene)
        else:
            pts = [(mine[n]["completeness"], mine[n]["accuracy"], n) for n in names
                   if n in mine and mine[n].get("accuracy") is not None
                   and mine[n].get("completeness") is not None]
            ax.plot([p[0] for p in pts], [p[1] for p in pts], "o-", label=scene)
            for x, y, n in pts:
                ax.annotate(n, (x, y), fontsize=7, xytext=(3, 3), textcoords="offset points")
    if plot["kind"] == "sweep":
        ax.set_xlabel(plot["x"])
        ax.set_ylabel(f"{plot['metric']} (lower is better)"
                      if plot["metric"] not in ("psnr", "ssim", "psnr_ibr", "ssim_ibr", "fscore")
                      else plot["metric"])
    else:
        ax.set_xlabel("completeness (lower is better)")
        ax.set_ylabel("accuracy (lower is better)")
    ax.set_title(f"{record['experiment']}", fontsize=10)
    ax.grid(alpha=0.3)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=8)
    fig.tight_layout()
    from svolsdf.io.images import save_figure

    return save_figure(fig, path)
