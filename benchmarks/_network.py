"""Shared by the benchmarks that use the DTU-trained PatchmatchNet of ../shared/weights:
its arguments, and the dtu_scan65 pseudo-ground-truth scoring of benchmarks/dtu_pseudo_gt.py."""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
WEIGHTS = SHARED / "weights/patchmatchnet/patchmatchnet_dtu_module.pt"

__all__ = ["REPO", "SHARED", "network_args", "score_dtu65"]


def network_args(ap: argparse.ArgumentParser, out: str, results: str) -> argparse.Namespace:
    """Add --weights, --out, --pgt and --results to ``ap``, parse, check the weights and make
    OUT (``out`` and ``results``: their defaults, the latter under benchmarks/results/)."""
    ap.add_argument("--weights", type=Path, default=WEIGHTS)
    ap.add_argument("--out", type=Path, default=Path(out))
    ap.add_argument("--pgt", type=Path, default=Path("/tmp/dtu_pseudo_gt"),
                    help="cache folder of benchmarks/dtu_pseudo_gt.py (its --out)")
    ap.add_argument("--results", type=Path, default=REPO / "benchmarks/results" / results)
    args = ap.parse_args()
    if not args.weights.is_file():
        sys.exit(f"{args.weights}: PatchmatchNet weights not found (--weights)")
    args.out.mkdir(parents=True, exist_ok=True)
    return args


def score_dtu65(runs: dict[str, Path], pgt: Path, out: Path) -> list[str]:
    """Score run folders of dtu_scan65 (views 25 22 28) with benchmarks/dtu_pseudo_gt.py
    (reference cached in ``pgt``); returns a Markdown section with its output."""
    res = out / "dtu_pseudo_gt_scan65.md"
    cmd = [sys.executable, str(REPO / "benchmarks/dtu_pseudo_gt.py"),
           "--scene", str(SHARED / "data/dtu_scan65"), "--out", str(pgt), "--results", str(res),
           "--runs", *(f"{k}={v}" for k, v in runs.items())]
    print("$", " ".join(cmd), flush=True)
    subprocess.run(cmd, check=True)
    return ["## dtu_scan65 (views 25 22 28) against the 49-view pseudo ground truth", "",
            "(benchmarks/dtu_pseudo_gt.py's output follows)", "",
            *res.read_text().splitlines()[1:], ""]
