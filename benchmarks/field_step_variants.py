"""The field's training step under config variants, side by side (issue 48: each change alone).

On a finished fast-preset `svolsdf reconstruct` folder, one trainer per variant is built as the
pipeline builds the field stage's (`train_step_speed.make_trainer`: the run's config and stage-1
volumes, the MVS initialisation, the prior and sampler), with the variant's ``--set``-style
overrides on the run's config; each gets ``--warm`` steps, then blocks of ``--block`` steps are
timed round-robin (the machine may be shared: the ratios in one run are what counts). "run"
(the run's config unchanged) is always the first variant and the reference.

    python benchmarks/field_step_variants.py --run OUT [--phase 128]
        --variant colour=train.colour_min_weight=1e-4 [--variant NAME=KEY=VALUE[,KEY=VALUE] ...]
        --results benchmarks/results/field_step_variants.md

The measurements go to the JSON beside the Markdown (``--results X.md`` writes ``X.json``); the
Markdown is rendered from the JSON alone: ``--from-json X.json --results X.md`` writes it again.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch loads OpenMP (as svolsdf)

import argparse  # noqa: E402
import datetime  # noqa: E402
import json  # noqa: E402
import logging  # noqa: E402
import platform  # noqa: E402
import statistics  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import cpu_name  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


def parse_variant(text: str) -> tuple[str, dict]:
    """``NAME=KEY=VALUE[,KEY=VALUE]`` -> (NAME, {KEY: VALUE as YAML})."""
    import yaml

    name, _, rest = text.partition("=")
    if not name or not rest:
        raise SystemExit(f"field_step_variants: --variant {text!r}: expected NAME=KEY=VALUE")
    out = {}
    for item in rest.split(","):
        key, _, value = item.partition("=")
        if not key or not value:
            raise SystemExit(f"field_step_variants: --variant {text!r}: {item!r} is not KEY=VALUE")
        out[key] = yaml.safe_load(value)
    return name, out


def measure(run: Path, variants: dict[str, dict], warm: int, block: int, repeats: int,
            phase: int | None) -> dict:
    """The timings of every variant (wall and CPU seconds per step, per block)."""
    import torch
    from train_step_speed import make_trainer

    logging.disable(logging.INFO)
    trainers = {k: make_trainer(run, set(), warm, phase, overrides=v) for k, v in variants.items()}
    wall = {k: [] for k in trainers}
    cpu = {k: [] for k in trainers}
    for _ in range(repeats):
        for k, t in trainers.items():
            t0, c0 = time.perf_counter(), time.process_time()
            for _ in range(block):
                t.train_step()
            wall[k].append((time.perf_counter() - t0) / block)
            cpu[k].append((time.process_time() - c0) / block)
    ref = next(iter(trainers.values()))
    m = ref.model
    keys = sorted({k for v in variants.values() for k in v})
    # each variant's value of every overridden option (the reference: the run's config as
    # loaded, options newer than the run's config.yaml taking its preset's values)
    effective = {name: {k: getattr(t.cfg, k.split(".", 1)[1]) if k.startswith("train.") else None
                        for k in keys} for name, t in trainers.items()}
    return {"wall_s_per_step": wall, "cpu_s_per_step": cpu, "effective": effective,
            "grid": list(getattr(m, "grid_shape", ())),
            "parameters_m": sum(p.numel() for p in m.parameters()) / 1e6,
            "rays": ref.cfg.rays, "volumes": len(ref.prior) if ref.prior is not None else 0,
            "threads": torch.get_num_threads(), "torch": torch.__version__}


def render(d: dict) -> str:
    """The Markdown of a measurement (everything from the JSON ``d``)."""
    names = list(d["variants"])
    med = {k: statistics.median(v) for k, v in d["wall_s_per_step"].items()}
    medc = {k: statistics.median(v) for k, v in d["cpu_s_per_step"].items()}
    ref = names[0]
    lines = [
        "# The field's training step under config variants, side by side",
        "",
        f"- command: `{d['command']}`",
        f"- commit {d['commit']}, {d['date']}; machine: {d['machine']}; torch {d['torch']}, "
        f"{d['threads']} threads; load average at the start {d['load'][0]}, at the end "
        f"{d['load'][1]} (a shared machine: compare the ratios)",
        f"- field: grid {tuple(d['grid'])} SDF nodes, {d['parameters_m']:.1f} M parameters; "
        f"{d['rays']} rays per step; {d['volumes']} stage-1 volumes"
        + (f"; steps at the run's grid resolution {d['phase']}" if d["phase"] else
           "; a run of the warm-up steps, full grid"),
        f"- each variant: its own trainer, {d['warm']} warm-up steps, then {d['repeats']} "
        f"blocks of {d['block']} steps, round-robin; median per step",
        f"- {ref}: the run's config.yaml as loaded (an option newer than the file takes the "
        "value of the file's preset); the others: it with their options",
        "",
        "| variant | options | wall ms / step | CPU ms / step | wall, "
        f"{ref} = 1 | CPU, {ref} = 1 | fastest block's wall ms / step |",
        "|---|---|---:|---:|---:|---:|---:|",
    ]
    for k in names:
        eff = d.get("effective", {}).get(k) or d["variants"][k]
        ov = ", ".join(f"`{a}={b}`" for a, b in eff.items()) or "-"
        lines.append(f"| {k} | {ov} | {med[k] * 1000:.0f} | {medc[k] * 1000:.0f} | "
                     f"{med[k] / med[ref]:.2f} | {medc[k] / medc[ref]:.2f} | "
                     f"{min(d['wall_s_per_step'][k]) * 1000:.0f} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--run", type=Path, help="a finished fast-preset `svolsdf reconstruct` folder")
    ap.add_argument("--variant", action="append", default=[], metavar="NAME=KEY=VALUE[,KEY=VALUE]")
    ap.add_argument("--warm", type=int, default=24)
    ap.add_argument("--block", type=int, default=10)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--phase", type=int, default=None,
                    help="steps at this grid resolution of the run's schedule (default: a run "
                         "of --warm steps, full grid)")
    ap.add_argument("--results", type=Path,
                    default=REPO / "benchmarks/results/field_step_variants.md")
    ap.add_argument("--from-json", type=Path, help="only render --results from this JSON")
    args = ap.parse_args()
    if args.from_json:
        args.results.write_text(render(json.loads(args.from_json.read_text())))
        return
    if args.run is None or not (args.run / "config.yaml").is_file():
        raise SystemExit(f"field_step_variants: --run {args.run} is not a run folder")
    variants = {"run": {}} | dict(parse_variant(v) for v in args.variant)
    load0 = os.getloadavg()[0]
    d = measure(args.run, variants, args.warm, args.block, args.repeats, args.phase)
    commit = subprocess.run(["git", "rev-parse", "--short=9", "HEAD"], cwd=REPO,
                            capture_output=True, text=True).stdout.strip()
    dirty = subprocess.run(["git", "status", "--porcelain", "src"], cwd=REPO,
                           capture_output=True, text=True).stdout.strip()
    cmd = ("python benchmarks/field_step_variants.py --run OUT"
           + "".join(f" --variant {v}" for v in args.variant)
           + (f" --phase {args.phase}" if args.phase else "")
           + f" --warm {args.warm} --block {args.block} --repeats {args.repeats}")
    d |= {"variants": variants, "command": cmd,
          "commit": commit + (" with uncommitted changes under src/" if dirty else ""),
          "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
          "machine": f"{os.cpu_count()} logical cores, {cpu_name()}, Python "
                     f"{platform.python_version()}",
          "load": [round(load0, 2), round(os.getloadavg()[0], 2)],
          "phase": args.phase, "warm": args.warm, "block": args.block, "repeats": args.repeats}
    args.results.parent.mkdir(parents=True, exist_ok=True)
    args.results.with_suffix(".json").write_text(json.dumps(d, indent=1) + "\n")
    text = render(d)
    args.results.write_text(text)
    print(text)


if __name__ == "__main__":
    main()
