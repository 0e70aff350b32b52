"""Where the seconds of a fast-preset run go: per stage, and within the field per part of a step.

On a finished fast-preset `svolsdf reconstruct` folder (read only):

(a) the stages' seconds, shares and peak memory from OUT/timing.json;
(b) the field, profiled with ``torch.profiler`` (CPU): the field stage's trainer is rebuilt from
    the run's config and stage-1 volumes as the pipeline builds it
    (``train_step_speed.build_trainer``). The run's steps fall into phases (the RGB warm-up,
    then one phase per grid resolution of the coarse-to-fine schedule); in each phase the trainer
    jumps to the phase's first step (growing the grid there as the run did), runs ``--warm``
    steps, times ``--steps`` steps without the profiler, then profiles ``--steps`` more. The
    ``svolsdf.*`` labels of `Trainer.train_step` and of the code it calls (the grid field's
    lookups, the compositing, the MVS prior) give each part's milliseconds per step, and the
    run's own seconds per phase (OUT/field/losses.csv) turn the parts' shares into seconds of the
    run. Also the ten ATen ops with the most self CPU time and the largest backward nodes.
(c) with ``--stages``, other stages under cProfile: each in a copy of the run folder (its field
    checkpoint left out) where only that stage's record is removed, so that the pipeline
    computes that stage again and reuses the others.

Run (from the repo root):

    python benchmarks/profile_fast.py --run OUT [--steps 30] [--warm 3]
        [--stages mvs23 fusion mesh] [--scene TEXT] [--results benchmarks/results/profile_fast.md]

The absolute milliseconds depend on the machine's load (the load average is recorded); the
shares are what the profile is for.
"""

from __future__ import annotations

import os

# before torch loads its OpenMP runtime (as svolsdf/__init__.py does): threads that spin while
# waiting make every step several times slower when another process shares the cores
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import argparse  # noqa: E402
import cProfile  # noqa: E402
import csv  # noqa: E402
import datetime  # noqa: E402
import json  # noqa: E402
import logging  # noqa: E402
import platform  # noqa: E402
import pstats  # noqa: E402
import shutil  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from collections import defaultdict  # noqa: E402
from pathlib import Path  # noqa: E402

import torch  # noqa: E402
from torch.profiler import ProfilerActivity, profile  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import cpu_name, write_results  # noqa: E402
from train_step_speed import build_trainer  # noqa: E402

from svolsdf.config import load_config  # noqa: E402
from svolsdf.pipeline import STAGES, Pipeline, set_threads  # noqa: E402
from svolsdf.pipeline.builders import grid_schedule  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
PREFIX = "svolsdf."
ROOT = "svolsdf.train_step"
#: the labels of the field, the compositing and the prior, wherever they are called
COMPONENTS = ("sdf_lookup", "feature_lookup", "colour_mlp", "composite", "prior_lookup")
BACKWARD_NODE = "autograd::engine::evaluate_function: "


# ---------------------------------------------------------------------- profile parsing
def label_times(events) -> dict[tuple[str, ...], float]:
    """Inclusive microseconds of every ``svolsdf.*`` label of a ``torch.profiler`` event list,
    keyed by its path of enclosing labels, e.g. ``("train_step", "render", "sdf_lookup")``
    (the prefix dropped; repeated scopes of one path summed)."""
    out: dict[tuple[str, ...], float] = defaultdict(float)
    for e in events:
        if not e.name.startswith(PREFIX):
            continue
        path = [e.name[len(PREFIX):]]
        p = e.cpu_parent
        while p is not None:
            if p.name.startswith(PREFIX):
                path.append(p.name[len(PREFIX):])
            p = p.cpu_parent
        out[tuple(reversed(path))] += e.cpu_time_total
    return dict(out)


def part_rows(times: dict[tuple[str, ...], float]) -> list[tuple[str, ...]]:
    """The label paths under the step, each parent followed by its children (largest first), and
    a ``(..., "(unlabelled)")`` row after each parent that has labelled children."""
    rows: list[tuple[str, ...]] = []

    def walk(parent: tuple[str, ...]) -> None:
        kids = sorted((k for k in times if len(k) == len(parent) + 1 and k[:-1] == parent),
                      key=lambda k: -times[k])
        for k in kids:
            rows.append(k)
            walk(k)
        if kids:
            rows.append(parent + ("(unlabelled)",))

    walk(("train_step",))
    return rows


def row_time(times: dict[tuple[str, ...], float], row: tuple[str, ...]) -> float:
    """A row of `part_rows`: its label's time, or for "(unlabelled)" the parent's time less its
    labelled children's."""
    if row[-1] != "(unlabelled)":
        return times.get(row, 0.0)
    parent = row[:-1]
    kids = [k for k in times if len(k) == len(parent) + 1 and k[:-1] == parent]
    return times.get(parent, 0.0) - sum(times[k] for k in kids)


def component_times(times: dict[tuple[str, ...], float]) -> dict[str, float]:
    """Each `COMPONENTS` label summed over every place it is called from (forward only)."""
    out = {c: 0.0 for c in COMPONENTS}
    for path, us in times.items():
        if path[-1] in out and path.count(path[-1]) == 1:
            out[path[-1]] += us
    return out


def aten_self_times(prof) -> dict[str, float]:
    """Self CPU microseconds of every ATen op (all calls summed)."""
    return {e.key: e.self_cpu_time_total for e in prof.key_averages()
            if e.key.startswith("aten::")}


def backward_node_times(events) -> dict[str, float]:
    """Inclusive microseconds of each autograd node type run by the backward pass."""
    out: dict[str, float] = defaultdict(float)
    for e in events:
        if e.name.startswith(BACKWARD_NODE):
            out[e.name[len(BACKWARD_NODE):]] += e.cpu_time_total
    return dict(out)


# ---------------------------------------------------------------------- the field's phases
def phases(cfg) -> list[tuple[int, int, bool]]:
    """The run's steps cut where a step's work changes: the RGB warm-up's end and each grid
    growth. [(first step, end step, in the RGB warm-up)]."""
    t = cfg.train
    cuts = {0, t.steps} | {s for s, _ in grid_schedule(cfg) if 0 < s < t.steps}
    warm = t.mode == "svolsdf" and t.sparse_weight > 0 and 0 < t.anneal_rgb < t.steps
    if warm:
        cuts.add(t.anneal_rgb)
    cuts = sorted(cuts)
    return [(a, b, warm and a < t.anneal_rgb) for a, b in zip(cuts, cuts[1:], strict=False)]


def run_phase_seconds(losses_csv: Path, cuts: list[tuple[int, int]]) -> list[float] | None:
    """The run's own seconds in each phase, from the cumulative steps/s of its loss log (one row
    every few steps); None when the log does not have a row at every cut or was resumed."""
    if not losses_csv.is_file():
        return None
    elapsed = {0: 0.0}
    with open(losses_csv, newline="") as f:
        for row in csv.DictReader(f):
            try:
                step, rate = int(float(row["step"])), float(row["steps_per_s"])
            except (KeyError, ValueError):
                return None
            if rate > 0:
                elapsed[step] = step / rate
    steps = sorted(elapsed)
    if any(elapsed[b] < elapsed[a] for a, b in zip(steps, steps[1:], strict=False)):
        return None  # a resumed run: its rates restart at the resume
    if any(a not in elapsed or b not in elapsed for a, b in cuts):
        return None
    return [elapsed[b] - elapsed[a] for a, b in cuts]


def profile_field(run: Path, steps: int, warm: int) -> dict:
    """Each phase of the field: ms per step without and with the profiler, the label times,
    the ATen ops' self times and the backward nodes (all per step, microseconds)."""
    cfg = load_config(run / "config.yaml")
    set_threads(cfg.threads)
    t = build_trainer(run)
    out = {"phases": [], "grid_shape": None}
    for a, b, rgb_warm_up in phases(cfg):
        t.step = a  # the grid grows at its scheduled step, as in the run
        for _ in range(warm):
            t.train_step()
        what = f"steps {a}-{b - 1}, grid {getattr(t.model, 'resolution', '?')}" + (
            ", RGB warm-up" if rgb_warm_up else "")
        s0 = t.step
        t0 = time.perf_counter()
        for _ in range(steps):
            t.train_step()
        plain = (time.perf_counter() - t0) / steps
        t.step = s0  # the profiled steps are the same steps of the schedule
        with profile(activities=[ProfilerActivity.CPU]) as prof:
            t0 = time.perf_counter()
            for _ in range(steps):
                t.train_step()
            profiled = (time.perf_counter() - t0) / steps
        events = prof.events()
        per = 1.0 / steps
        out["phases"].append({
            "first": a, "end": b, "what": what, "profiled_steps": (s0, s0 + steps),
            "plain_s": plain, "profiled_s": profiled,
            "labels": {k: v * per for k, v in label_times(events).items()},
            "aten": {k: v * per for k, v in aten_self_times(prof).items()},
            "backward": {k: v * per for k, v in backward_node_times(events).items()},
            "grid_shape": tuple(getattr(t.model, "grid_shape", ())),
        })
        print(f"profile_fast: {what}: {plain * 1000:.0f} ms/step, {profiled * 1000:.0f} "
              "with the profiler", flush=True)
    out["rays"] = t.cfg.rays
    out["params_m"] = sum(p.numel() for p in t.model.parameters()) / 1e6
    return out


# ---------------------------------------------------------------------- other stages
def _short(path: str) -> str:
    """A source path without the machine's folders (package-relative, else the file name)."""
    for mark in ("/site-packages/", "/src/", "/lib/python"):
        i = path.rfind(mark)
        if i >= 0:
            return path[i + len(mark):]
    return Path(path).name if path.startswith("/") else path


def profile_stage(run: Path, stage: str, work: Path) -> dict:
    """``stage`` computed again under cProfile in a copy of ``run`` (the others reused)."""
    dst = work / stage
    shutil.copytree(run, dst, ignore=shutil.ignore_patterns("checkpoint.pt", ".svolsdf.lock"))
    try:
        p = Pipeline(load_config(dst / "config.yaml"), dst, progress=False)
        p.dir.unmark([stage])
        fn = getattr(p, f"stage_{stage}")
        prof = cProfile.Profile()
        spent = [0.0]

        def profiled(*a, **k):
            t0 = time.perf_counter()
            prof.enable()
            try:
                return fn(*a, **k)
            finally:
                prof.disable()
                spent[0] += time.perf_counter() - t0

        setattr(p, f"stage_{stage}", profiled)
        p.run()
        st = pstats.Stats(prof)
        rows = []
        for (file, line, func), (_, ncalls, tt, ct, _) in st.stats.items():
            where = func if file == "~" else f"{_short(file)}:{line} {func}"
            rows.append((where, ncalls, tt, ct))
        return {"seconds": spent[0], "rows": rows}
    finally:
        shutil.rmtree(dst, ignore_errors=True)


# ---------------------------------------------------------------------- report
def _git(*args: str) -> str:
    try:
        return subprocess.run(["git", *args], cwd=REPO, capture_output=True, text=True,
                              check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return ""


def _pct(x: float, total: float) -> str:
    return f"{100 * x / total:.1f} %" if total > 0 else "-"


def stage_section(timing: dict) -> tuple[list[str], dict[str, float]]:
    stages = {k: v for k, v in timing.items() if k != "total" and isinstance(v, dict)
              and "seconds" in v}
    total = sum(v["seconds"] for v in stages.values())
    lines = ["## Stages (OUT/timing.json)", "",
             "| stage | seconds | share of the stages | peak memory (GB, process so far) | notes |",
             "|---|---|---|---|---|"]
    for k in [s for s in STAGES if s in stages] + [s for s in stages if s not in STAGES]:
        v = stages[k]
        note = ""
        if k == "field" and v.get("steps_per_s"):
            note = f"{v.get('steps', '?')} steps, {v['steps_per_s']:.2f} steps/s"
        elif "faces" in v:
            note = f"{v.get('vertices', '?')} vertices, {v['faces']} faces"
        elif "points" in v:
            note = f"{v['points']} points"
        mem = v.get("peak_memory_gb")
        lines.append(f"| {k} | {v['seconds']:.1f} | {_pct(v['seconds'], total)} | "
                     f"{mem if mem is not None else '-'} | {note} |")
    tot = timing.get("total", {})
    lines.append(f"| all stages | {total:.1f} | 100 % | {tot.get('peak_memory_gb', '-')} | "
                 f"wall of the whole run {tot.get('seconds', float('nan')):.1f} s |")
    return lines, {k: v["seconds"] for k, v in stages.items()}


def field_section(field: dict, run_secs: list[float] | None, field_s: float | None
                  ) -> tuple[list[str], dict]:
    ph = field["phases"]
    n_steps = [b - a for a, b, *_ in ((p["first"], p["end"]) for p in ph)]
    # seconds of the run in each phase: the run's own (loss log), else ms/step x steps
    if run_secs is None:
        run_secs = [p["plain_s"] * n for p, n in zip(ph, n_steps, strict=True)]
        source = "the unprofiled ms/step measured here x the phase's steps (no usable loss log)"
    else:
        source = "the run's own seconds per phase (OUT/field/losses.csv)"
    steps_s = sum(run_secs)

    def run_seconds(get) -> float:
        """Seconds of the run's steps spent in a part: its share of each phase's profiled step
        times the run's seconds in that phase."""
        return sum(get(p) / p["labels"][("train_step",)] * s
                   for p, s in zip(ph, run_secs, strict=True) if p["labels"].get(("train_step",)))

    lines = ["## The field, per part of a training step (torch.profiler)", "",
             f"- trainer rebuilt from the run's config and stage-1 volumes; {field['rays']} rays "
             f"per step, {field['params_m']:.1f} M parameters at the final grid "
             f"{field['phases'][-1]['grid_shape']}",
             f"- seconds of the run per part: each phase's profiled shares x {source}; the "
             f"steps took {steps_s:.1f} s of the field stage's "
             + (f"{field_s:.1f} s (the rest: the trainer's set-up with the field's MVS "
                "initialisation, and the model's save)" if field_s else "time"),
             "- `prior_lookup` directly under the step: the labels P' at the rendered samples "
             "(GCE and sparsity losses); under `sampling`: P' at the probes that place the "
             "samples",
             "", "| phase | run's ms/step | ms/step here | with the profiler | steps profiled |",
             "|---|---|---|---|---|"]
    for p, n, s in zip(ph, n_steps, run_secs, strict=True):
        a, b = p["profiled_steps"]
        lines.append(f"| {p['what']} | {1000 * s / n:.0f} | {1000 * p['plain_s']:.0f} | "
                     f"{1000 * p['profiled_s']:.0f} | {a}-{b - 1} |")
    # parts, ordered by their seconds of the run
    paths = set().union(*(p["labels"] for p in ph))
    rows = part_rows({k: run_seconds(lambda p, k=k: p["labels"].get(k, 0.0)) for k in paths})
    head = " | ".join(f"ms/step, {p['what'].split(',')[0]}" for p in ph)
    lines += ["", "Parts (a label's time includes the labels under it; \"(unlabelled)\": the "
              "parent's time outside its labelled parts). Shares are of the steps' time.", "",
              f"| part | {head} | seconds of the run | share |",
              "|---|" + "---|" * len(ph) + "---|---|"]
    parts = {}
    for row in [("train_step",), *rows]:
        ms = [row_time(p["labels"], row) / 1000 for p in ph]
        secs = run_seconds(lambda p, row=row: row_time(p["labels"], row))
        parts[" / ".join(row[1:]) or "step"] = secs
        name = " / ".join(row[1:]) if len(row) > 1 else "**the whole step**"
        lines.append(f"| {name} | " + " | ".join(f"{m:.1f}" for m in ms)
                     + f" | {secs:.1f} | {_pct(secs, steps_s)} |")
    comps = {c: run_seconds(lambda p, c=c: component_times(p["labels"])[c]) for c in COMPONENTS}
    lines += ["", "The field's, the compositing's and the prior's labels summed over every place "
              "they are called from (forward only; their gradients are in backward):", "",
              "| label | seconds of the run | share |", "|---|---|---|"]
    for c, secs in sorted(comps.items(), key=lambda kv: -kv[1]):
        lines.append(f"| {c} | {secs:.1f} | {_pct(secs, steps_s)} |")
    def top(what: str, n: int, title: str, column: str) -> list[tuple[str, float]]:
        """The ``n`` largest entries of each phase's ``what`` profile, in seconds of the run,
        written as a table under ``title``."""
        secs: dict[str, float] = defaultdict(float)
        for p, s in zip(ph, run_secs, strict=True):
            for k, v in p[what].items():
                secs[k] += v / p["labels"][("train_step",)] * s
        lines.extend(["", title, "", f"| {column} | seconds of the run | share |",
                      "|---|---|---|"])
        best = sorted(secs.items(), key=lambda kv: -kv[1])[:n]
        lines.extend(f"| `{k}` | {t:.1f} | {_pct(t, steps_s)} |" for k, t in best)
        return best

    top_ops = top("aten", 10, "Top 10 ATen ops by self CPU time (all phases, in seconds of the "
                  "run):", "op")
    top_nodes = top("backward", 8, "Largest backward nodes (inclusive):", "autograd node")
    summary = {"steps_s": steps_s, "parts": parts, "components": comps, "ops": top_ops,
               "nodes": top_nodes, "run_ms": [1000 * s / n for s, n in
                                              zip(run_secs, n_steps, strict=True)],
               "plain_ms": [1000 * p["plain_s"] for p in ph],
               "profiled_ms": [1000 * p["profiled_s"] for p in ph]}
    return lines, summary


def stages_cprofile_section(results: dict[str, dict], timing: dict) -> list[str]:
    lines = ["## Other stages (cProfile, each computed again in a copy of the run folder)", ""]
    for stage, r in results.items():
        rec = timing.get(stage, {}).get("seconds")
        lines += [f"### {stage}: {r['seconds']:.1f} s under cProfile"
                  + (f" ({rec:.1f} s in the run)" if rec else ""), "",
                  "| function | calls | self s | cumulative s |", "|---|---|---|---|"]
        for where, n, tt, ct in sorted(r["rows"], key=lambda x: -x[2])[:12]:
            lines.append(f"| `{where}` | {n} | {tt:.2f} | {ct:.2f} |")
        lines.append("")
    return lines


def says_section(stage_s: dict[str, float], summary: dict | None,
                 cprof: dict[str, dict]) -> list[str]:
    """The largest items, in numbers only."""
    lines = ["## What the profile says", ""]
    total = sum(stage_s.values())
    top = sorted(stage_s.items(), key=lambda kv: -kv[1])
    lines.append("- Stages, largest first: " + ", ".join(
        f"{k} {v:.0f} s ({_pct(v, total)})" for k, v in top[:4]) + f" of {total:.0f} s.")
    if summary:
        s = summary["steps_s"]
        first = {k: v for k, v in summary["parts"].items() if k != "step" and " / " not in k}
        big = sorted(first.items(), key=lambda kv: -kv[1])
        lines.append("- The field's steps, largest parts: " + ", ".join(
            f"{k} {_pct(v, s)}" for k, v in big[:4]) + f" of {s:.0f} s of steps.")
        for k, _ in big[:2]:
            subs = {n: v for n, v in summary["parts"].items() if n.startswith(k + " / ")
                    and n.count(" / ") == 1}
            if subs:
                lines.append(f"  - inside {k}: " + ", ".join(
                    f"{n.split(' / ')[1]} {_pct(v, s)}"
                    for n, v in sorted(subs.items(), key=lambda kv: -kv[1])[:3]) + ".")
        comps = sorted(summary["components"].items(), key=lambda kv: -kv[1])
        lines.append("- Wherever called (forward): " + ", ".join(
            f"{k} {_pct(v, s)}" for k, v in comps) + ".")
        if summary["ops"]:
            lines.append("- Largest ATen ops by self time: " + ", ".join(
                f"`{k}` {_pct(v, s)}" for k, v in summary["ops"][:3]) + ".")
        if summary["nodes"]:
            lines.append("- Largest backward nodes: " + ", ".join(
                f"`{k}` {_pct(v, s)}" for k, v in summary["nodes"][:3]) + ".")
        over = [p / q for p, q in zip(summary["profiled_ms"], summary["plain_ms"], strict=True)]
        here = [p / r for p, r in zip(summary["plain_ms"], summary["run_ms"], strict=True)]
        lines.append(f"- The profiler's cost: {min(over):.2f}-{max(over):.2f} x the unprofiled "
                     f"step; the unprofiled steps here took {min(here):.2f}-{max(here):.2f} x "
                     "the run's own.")
    for stage, r in cprof.items():
        top = sorted(r["rows"], key=lambda x: -x[2])[:3]
        lines.append(f"- {stage} (cProfile, {r['seconds']:.0f} s), largest self times: "
                     + ", ".join(f"`{where}` {_pct(tt, r['seconds'])}"
                                 for where, _, tt, _ in top) + ".")
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--run", type=Path, required=True,
                    help="a finished fast-preset `svolsdf reconstruct` folder (read only)")
    ap.add_argument("--steps", type=int, default=30, help="steps timed and profiled per phase")
    ap.add_argument("--warm", type=int, default=3, help="warm-up steps per phase")
    ap.add_argument("--stages", nargs="*", default=[],
                    choices=[s for s in STAGES if s != "field"],
                    help="other stages to profile with cProfile (each in a copy of the run)")
    ap.add_argument("--workdir", type=Path, default=None,
                    help="where the copies for --stages go (default: a temporary folder)")
    ap.add_argument("--scene", default=None, help="how the results name the run's scene")
    ap.add_argument("--results", type=Path, default=REPO / "benchmarks/results/profile_fast.md")
    args = ap.parse_args()
    run = args.run
    if not (run / "config.yaml").is_file() or not (run / "timing.json").is_file():
        sys.exit(f"profile_fast: {run} has no config.yaml and timing.json (not a run folder)")
    timing = json.loads((run / "timing.json").read_text())
    if "total" not in timing:
        sys.exit(f"profile_fast: {run} is not finished (timing.json has no total)")
    cfg = load_config(run / "config.yaml")
    if cfg.field.kind != "grid" or cfg.train.sampler != "mvs" or cfg.train.mode != "svolsdf":
        sys.exit(f"profile_fast: {run} is not a fast-preset run (grid field, MVS-guided sampler, "
                 "mode svolsdf)")
    logging.disable(logging.INFO)
    load0 = os.getloadavg()[0]
    started = datetime.datetime.now().strftime("%Y-%m-%d %H:%M")

    stage_lines, stage_s = stage_section(timing)
    field = profile_field(run, args.steps, args.warm)
    run_secs = run_phase_seconds(run / "field" / "losses.csv",
                                 [(p["first"], p["end"]) for p in field["phases"]])
    field_lines, summary = field_section(field, run_secs, stage_s.get("field"))
    cprof: dict[str, dict] = {}
    if args.stages:
        work = args.workdir or Path(tempfile.mkdtemp(prefix="profile_fast_"))
        work.mkdir(parents=True, exist_ok=True)
        try:
            for stage in args.stages:
                print(f"profile_fast: stage {stage} under cProfile", flush=True)
                cprof[stage] = profile_stage(run, stage, work)
        finally:
            if args.workdir is None:
                shutil.rmtree(work, ignore_errors=True)
    load1 = os.getloadavg()[0]

    cmd = f"python benchmarks/profile_fast.py --run OUT --steps {args.steps} --warm {args.warm}"
    if args.stages:
        cmd += " --stages " + " ".join(args.stages)
    dirty = [ln[3:] for ln in _git("status", "--porcelain", "--", "src", "benchmarks")
             .splitlines() if ln.strip()]
    commit = _git("rev-parse", "--short", "HEAD") or "unknown"
    if dirty:
        commit += f" (with uncommitted changes to {len(dirty)} files under src/ and benchmarks/)"
    scene = args.scene or (f"scene folder `{Path(cfg.scene.path).name}`, views "
                           f"{' '.join(map(str, cfg.scene.views or []))}, preset {cfg.preset}")
    lines = [
        "# Where a fast-preset run spends its time (profile)", "",
        f"- command: `{cmd}` (OUT: a finished `svolsdf reconstruct SCENE -o OUT`)",
        f"- run: {scene}; {timing.get('total', {}).get('seconds', float('nan')):.0f} s in all",
        f"- machine: {os.cpu_count()} logical cores, {cpu_name()}; torch {torch.__version__}, "
        f"{torch.get_num_threads()} threads; Python {platform.python_version()}; 1-minute load "
        f"average {load0:.1f} at the start, {load1:.1f} at the end",
        f"- date: {started}; commit {commit}",
        "",
        *says_section(stage_s, summary, cprof), "",
        *stage_lines, "",
        *field_lines, "",
    ]
    if cprof:
        lines += stages_cprofile_section(cprof, timing)
    text = "\n".join(lines).rstrip() + "\n"
    print(text)
    write_results(args.results, text)


if __name__ == "__main__":
    main()
