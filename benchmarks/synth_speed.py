"""Synthetic-scene generation time (issue 2: a 3-view 96x72 scene in seconds, 768x576 in minutes).

Usage:
    python benchmarks/synth_speed.py [--results benchmarks/results/synth_speed.md]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--results", type=Path, default=REPO / "benchmarks/results/synth_speed.md")
    args = ap.parse_args()

    from svolsdf.runtime import set_cpu_env

    set_cpu_env()  # before torch loads
    from svolsdf.scene.synthetic import SynthConfig, make_synthetic_scene

    cpu = next((ln.split(":", 1)[1].strip() for ln in open("/proc/cpuinfo")
                if ln.startswith("model name")), "unknown")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for views, w, h in ((3, 96, 72), (3, 768, 576), (9, 768, 576)):
            t0 = time.perf_counter()
            make_synthetic_scene(Path(tmp) / f"s{views}_{w}", SynthConfig(views=views, width=w,
                                                                          height=h, seed=0))
            rows.append((views, w, h, time.perf_counter() - t0))
    lines = ["# Synthetic scene generation time", "",
             f"- machine: nproc = {os.cpu_count()}, CPU: {cpu}; shared machine",
             f"- command: `python benchmarks/synth_speed.py {' '.join(sys.argv[1:])}`",
             "- default SynthConfig (seed 0, object random, supersample 2, 200k gt points)", "",
             "| views | size | seconds |", "|---|---|---|"]
    lines += [f"| {v} | {w}x{h} | {t:.1f} |" for v, w, h, t in rows]
    args.results.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
