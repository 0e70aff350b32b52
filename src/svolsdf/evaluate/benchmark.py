"""``svolsdf benchmark``: the pipeline over scenes x modes, evaluated, as a table like Table 1.

For every scene and mode (``svolsdf``, ``mvs-only``, ``volsdf``) the reconstruction pipeline runs
into ``OUT/<scene>/<mode>/`` (a rerun resumes finished stages), then `evaluate_run` scores it:

- geometry: the DTU protocol (METHOD.md 8.1) when ``dtu_gt`` is given and the scan number is known
  (from the scene's name, e.g. ``scan65``, or ``scan``); otherwise the generic two-way Chamfer
  against the scene's ``gt_points.ply`` (synthetic scenes, `make_synthetic_scene`); otherwise
  none. The fused point cloud (``points.ply``) is scored for every mode, as in the paper.
- images: PSNR / SSIM / LPIPS (METHOD.md 8.3) of the held-out views named in the run's
  ``views.json`` (``"test"``) that have a render in ``renders/``; none when there are none.

Results go to ``OUT/benchmark.md`` and ``OUT/benchmark.csv`` (rows: scenes, then the mean; per
mode: accuracy, completeness, overall Chamfer, PSNR when any run has it, time), and every run's
numbers to ``OUT/benchmark.json``. The files are rewritten after each run, so an interrupted
benchmark keeps the finished rows. A run that fails is recorded (``status``) and the benchmark
goes on.

Time is the sum of the pipeline's stage times from the run's ``timing.json`` (so a resumed run
still reports the compute its stages took), or this invocation's elapsed time without one.
"""

from __future__ import annotations

import csv
import io
import json
import logging
import math
import re
import time
from dataclasses import dataclass, field
from pathlib import Path

from svolsdf.errors import InputError

__all__ = [
    "MODES",
    "METRIC_KEYS",
    "BenchmarkConfig",
    "benchmark_csv",
    "benchmark_markdown",
    "run_benchmark",
    "run_metrics",
    "scan_number",
]

log = logging.getLogger(__name__)

MODES = ("svolsdf", "mvs-only", "volsdf")
"""The pipeline's modes (``cfg.train.mode``)."""

METRIC_KEYS = ("accuracy", "completeness", "overall", "fscore", "psnr", "ssim", "lpips",
               "mesh_overall", "time_s")
"""Numeric keys of a per-run metrics dict (None when not computed)."""


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


# --------------------------------------------------------------------------- tables
def _fmt(x, digits: int) -> str:
    return "-" if x is None or not math.isfinite(x) else f"{x:.{digits}f}"


def _mean(values: list) -> float | None:
    vs = [float(v) for v in values if v is not None and math.isfinite(float(v))]
    return sum(vs) / len(vs) if vs else None


def _grid(rows: list[dict], modes: list[str] | None) -> tuple[list[str], list[str], dict]:
    """Scenes (first-seen order), modes and {(scene, mode): row}."""
    scenes: list[str] = []
    seen_modes: list[str] = []
    cell = {}
    for r in rows:
        if r["scene"] not in scenes:
            scenes.append(r["scene"])
        if r["mode"] not in seen_modes:
            seen_modes.append(r["mode"])
        cell[(r["scene"], r["mode"])] = r
    return scenes, list(modes) if modes else seen_modes, cell


def _columns(rows: list[dict]) -> list[tuple[str, str, int]]:
    """(key, header, digits) per mode; PSNR only when some run has it."""
    cols = [("accuracy", "Acc.", 2), ("completeness", "Comp.", 2), ("overall", "Chamfer", 2)]
    if any(r.get("psnr") is not None for r in rows):
        cols.append(("psnr", "PSNR", 2))
    cols.append(("time_s", "time (s)", 0))
    return cols


def _table(rows: list[dict], modes: list[str] | None):
    scenes, modes, cell = _grid(rows, modes)
    cols = _columns(rows)
    body = []
    for s in scenes:
        body.append((s, [[cell.get((s, m), {}).get(k) for k, _, _ in cols] for m in modes]))
    means, partial = [], []
    for j in range(len(modes)):
        vals, part = [], []
        for c in range(len(cols)):
            col = [b[1][j][c] for b in body]
            vals.append(_mean(col))
            n = sum(v is not None and math.isfinite(float(v)) for v in col)
            part.append(0 < n < len(col))
        means.append(vals)
        partial.append(part)
    return scenes, modes, cols, body, means, partial


def benchmark_markdown(rows: list[dict], modes: list[str] | None = None,
                       title: str = "Benchmark", notes: list[str] | None = None) -> str:
    """A Markdown table like the paper's Table 1 from per-run metrics dicts.

    Args:
        rows: one dict per run with ``scene``, ``mode`` and any of `METRIC_KEYS` (None or
            missing: not computed), optionally ``status`` (anything but "ok" is listed below
            the table) and ``protocol`` (how the Chamfer was computed).
        modes: column order (default: modes in order of appearance).
        title: the heading.
        notes: extra lines under the table.

    Returns:
        The Markdown text: a table with one row per scene and a mean row (mean over the scenes
        that have the value; marked * when some do not), per mode the accuracy, completeness and
        overall Chamfer, PSNR when any run has it, and time; the lowest Chamfer of each row in
        bold.
    """
    if not rows:
        raise InputError("benchmark table: no runs to tabulate")
    scenes, modes, cols, body, means, partial = _table(rows, modes)
    head = ["scene"] + [f"{m} {h}" for m in modes for _, h, _ in cols]
    out = [f"# {title}", "", "| " + " | ".join(head) + " |",
           "|---|" + "---:|" * (len(head) - 1)]
    ci = [k for k, _, _ in cols].index("overall")

    def line(label, per_mode, marks=None):
        best = [v[ci] for v in per_mode if v[ci] is not None and math.isfinite(v[ci])]
        best = min(best) if len(best) > 1 else None
        cells = []
        for j, vals in enumerate(per_mode):
            for c, (_, _, digits) in enumerate(cols):
                t = _fmt(vals[c], digits)
                if marks and marks[j][c] and t != "-":
                    t += "*"
                if c == ci and best is not None and vals[c] == best:
                    t = f"**{t}**"
                cells.append(t)
        return "| " + " | ".join([label] + cells) + " |"

    for s, per_mode in body:
        out.append(line(s, per_mode))
    out.append(line("**mean**", means, partial))
    out.append("")
    protocols = sorted({r.get("protocol") for r in rows if r.get("protocol")})
    out.append("Chamfer: accuracy (prediction -> ground truth), completeness (ground truth -> "
               "prediction) and their mean, of the fused point cloud, in the scene's world units "
               f"(DTU: mm); protocol: {', '.join(protocols) if protocols else 'none'}. "
               + ("PSNR on held-out views. " if "psnr" in [k for k, _, _ in cols] else "")
               + "Time: the pipeline's stage times. "
               "'-': not computed; '*': mean over fewer scenes than the table has.")
    failed = [r for r in rows if r.get("status", "ok") != "ok"]
    if failed:
        out += ["", "Runs without results:", ""]
        out += [f"- {r['scene']} / {r['mode']}: {r['status']}" for r in failed]
    if notes:
        out += [""] + list(notes)
    return "\n".join(out) + "\n"


def benchmark_csv(rows: list[dict], modes: list[str] | None = None) -> str:
    """The same table as `benchmark_markdown` as CSV: a ``scene`` column, then
    ``<mode>_<metric>`` columns, one line per scene and a last line ``mean``; empty cells for
    values not computed; full precision."""
    if not rows:
        raise InputError("benchmark table: no runs to tabulate")
    scenes, modes, cols, body, means, _ = _table(rows, modes)
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["scene"] + [f"{m}_{k}" for m in modes for k, _, _ in cols])
    for label, per_mode in [*body, ("mean", means)]:
        w.writerow([label] + ["" if v is None or not math.isfinite(v) else repr(float(v))
                              for vals in per_mode for v in vals])
    return buf.getvalue()


# --------------------------------------------------------------------------- driver
def run_metrics(metrics: dict, scene: str, mode: str, time_s: float | None,
                status: str = "ok") -> dict:
    """One benchmark row from an evaluate_run metrics dict (METRIC_KEYS, scene, mode, status,
    protocol)."""
    c = metrics.get("chamfer") or {}
    cm = metrics.get("chamfer_mesh") or {}
    im = metrics.get("images") or {}
    return {"scene": scene, "mode": mode, "status": status,
            "accuracy": c.get("accuracy"), "completeness": c.get("completeness"),
            "overall": c.get("overall"), "protocol": c.get("protocol"),
            "fscore": metrics.get("fscore"),
            "psnr": (im.get("psnr") or {}).get("mean"), "ssim": (im.get("ssim") or {}).get("mean"),
            "lpips": (im.get("lpips") or {}).get("mean"),
            "mesh_overall": cm.get("overall"), "time_s": time_s}


def _stage_seconds(run_dir: Path) -> float | None:
    p = run_dir / "timing.json"
    if not p.is_file():
        return None
    try:
        t = json.loads(p.read_text())
    except ValueError:
        return None
    secs = [v.get("seconds") for k, v in t.items() if k != "total" and isinstance(v, dict)]
    secs = [float(s) for s in secs if isinstance(s, (int, float))]
    return sum(secs) if secs else None


def _ground_truth(cfg: BenchmarkConfig, scene: Path) -> dict:
    """EvaluateConfig geometry options for one scene."""
    if cfg.dtu_gt is not None:
        scan = scan_number(scene) or cfg.scan
        if scan is not None:
            return {"dtu_gt": Path(cfg.dtu_gt), "scan": int(scan)}
    gt = scene / "gt_points.ply"
    if gt.is_file():
        return {"gt_points": gt}
    return {}


def _write_tables(cfg: BenchmarkConfig, rows: list[dict]) -> None:
    out = Path(cfg.out)
    notes = [f"Preset {cfg.preset}" + (f", {cfg.steps} steps" if cfg.steps else "")
             + (f", input views {cfg.views}" if cfg.views else "")
             + (f", size {cfg.size[0]}x{cfg.size[1]}" if cfg.size else "") + "."]
    for path, text in ((out / "benchmark.md", benchmark_markdown(
            rows, cfg.modes, title=f"svolsdf benchmark ({len({r['scene'] for r in rows})} "
                                   f"scenes)", notes=notes)),
                       (out / "benchmark.csv", benchmark_csv(rows, cfg.modes)),
                       (out / "benchmark.json", json.dumps(rows, indent=1, allow_nan=False))):
        tmp = path.with_name(path.name + ".tmp")
        tmp.write_text(text)
        tmp.replace(path)


def _validate(cfg: BenchmarkConfig) -> None:
    if not cfg.scenes:
        raise InputError("benchmark: give at least one scene (--scenes A B ...)")
    if not cfg.modes:
        raise InputError("benchmark: give at least one mode (--modes svolsdf mvs-only volsdf)")
    bad = [m for m in cfg.modes if m not in MODES]
    if bad:
        raise InputError(f"benchmark: unknown mode(s) {bad} (choose from {', '.join(MODES)})")
    for s in cfg.scenes:
        if not Path(s).is_dir():
            raise InputError(f"{s}: scene folder does not exist")
    if cfg.dtu_gt is not None:
        if not Path(cfg.dtu_gt).is_dir():
            raise InputError(f"{cfg.dtu_gt}: DTU ground-truth folder does not exist")
        if cfg.scan is None:
            missing = [str(s) for s in cfg.scenes
                       if scan_number(s) is None and not (Path(s) / "gt_points.ply").is_file()]
            if missing:
                raise InputError(f"--dtu-gt: no DTU scan number in the name of {missing[0]} "
                                 "(name it like scan65 or pass --scan N)")
    if cfg.out.exists() and not cfg.out.is_dir():
        raise InputError(f"{cfg.out}: output path exists and is not a folder")
    for mode in cfg.modes:  # the run configs (--steps, --size, --device ...) are valid
        _config(cfg, cfg.scenes[0], mode)


def _config(cfg: BenchmarkConfig, scene: Path, mode: str):
    from svolsdf.config import apply_overrides, preset

    c = preset(cfg.preset)
    c.scene.path = str(scene)
    c.train.mode = mode
    return apply_overrides(c, {
        "train.steps": cfg.steps,
        "scene.views": list(cfg.views) if cfg.views else None,
        "scene.image_size": list(cfg.size) if cfg.size else None,
        "device": cfg.device,
    }, labels={"train.steps": "--steps", "scene.views": "--views", "scene.image_size": "--size",
               "device": "--device"})


def run_benchmark(cfg: BenchmarkConfig) -> list[dict]:
    """Run and evaluate every scene x mode; write OUT/benchmark.{md,csv,json}.

    Args:
        cfg: `BenchmarkConfig`.

    Returns:
        The per-run rows (see `run_metrics`), in scene-major order.

    Raises:
        InputError: a missing scene or ground-truth folder, an unknown mode, or a DTU scene
            without a scan number; raised before any run starts.
    """
    from svolsdf import pipeline as pipeline_module
    from svolsdf.evaluate.run import EvaluateConfig, evaluate_run, run_views
    from svolsdf.io.folders import ensure_writable_folder

    cfg.scenes = [Path(s) for s in cfg.scenes]
    cfg.out = Path(cfg.out)
    _validate(cfg)
    ensure_writable_folder(cfg.out)
    rows: list[dict] = []
    labels = _labels(cfg.scenes)
    n = len(cfg.scenes) * len(cfg.modes)
    k = 0
    for scene, label in zip(cfg.scenes, labels, strict=True):
        gt = _ground_truth(cfg, scene)
        if not gt:
            log.warning("%s: no ground-truth geometry (gt_points.ply or --dtu-gt with a scan "
                        "number): Chamfer columns stay empty", scene)
        for mode in cfg.modes:
            k += 1
            run_dir = cfg.out / label / mode
            log.info("[%d/%d] %s / %s -> %s", k, n, label, mode, run_dir)
            t0 = time.perf_counter()
            try:
                pipeline_module.Pipeline(_config(cfg, scene, mode), run_dir,
                                         progress=False).run()
                elapsed = time.perf_counter() - t0
                metrics = evaluate_run(EvaluateConfig(
                    out=run_dir, scene=scene, views=run_views(run_dir, "test"),
                    lpips_net=cfg.lpips_net, lpips_weights=cfg.lpips_weights,
                    report=cfg.report, extra={"benchmark": {"scene": label, "mode": mode}},
                    **gt))
                t = _stage_seconds(run_dir)
                row = run_metrics(metrics, label, mode, t if t is not None else elapsed)
            except Exception as e:  # one failed run must not lose the others
                log.error("%s / %s failed: %s", label, mode, e, exc_info=not isinstance(
                    e, InputError))
                row = run_metrics({}, label, mode, None,
                                  status=f"failed: {type(e).__name__}: {e}".splitlines()[0])
            rows.append(row)
            _write_tables(cfg, rows)
    return rows
