"""benchmarks/results/input_views_dtu.md is what benchmarks/input_views_dtu.py makes of the JSON
beside it, byte for byte: no number in it is written by hand."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results"


def test_input_views_md_is_made_from_its_json(tmp_path):
    out = tmp_path / "input_views_dtu.json"
    subprocess.run([sys.executable, str(REPO / "benchmarks" / "input_views_dtu.py"),
                    "--from-json", str(RESULTS / "input_views_dtu.json"), "--results", str(out)],
                   check=True, capture_output=True, cwd=tmp_path)
    assert out.with_suffix(".md").read_bytes() == (RESULTS / "input_views_dtu.md").read_bytes()


def test_input_views_json_says_where_it_came_from():
    doc = json.loads((RESULTS / "input_views_dtu.json").read_text())
    assert {"commit", "date", "machine", "commands", "threshold", "rows"} <= set(doc)
    scans = {r["scan"] for r in doc["rows"]}
    assert {"dtu_scan65", "dtu_scan37"} <= scans  # chosen on one, confirmed on the other
    for r in doc["rows"]:
        assert {"object", "table", "background"} <= set(r["mean"])
    text = (RESULTS / "input_views_dtu.json").read_text()
    assert not [root for root in ("tmp", "work", "home", "root") if f"/{root}/" in text]
