"""benchmarks/results/table1.md is what benchmarks/table1.py makes of table1.json beside it, byte
for byte (issue 50): no number in it is written by hand, and every number it shows is in the
JSON with the commands, commit, date and machine that made it."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results"


def test_table1_md_is_made_from_its_json(tmp_path):
    out = tmp_path / "table1.md"
    subprocess.run([sys.executable, str(REPO / "benchmarks" / "table1.py"), "--from-json",
                    str(RESULTS / "table1.json"), "--results", str(out)],
                   check=True, capture_output=True, cwd=tmp_path)
    assert out.read_bytes() == (RESULTS / "table1.md").read_bytes()


def test_table1_json_says_where_it_came_from():
    doc = json.loads((RESULTS / "table1.json").read_text())
    assert {"commands", "commit", "date", "machine", "rows", "checks", "fusion_rules",
            "fusion_effects", "tuning"} <= set(doc)
    assert doc["commands"]["table"].startswith("python benchmarks/table1.py --bench WORK/")
    # the scenes' share in the choices they were (or were not) used for is data
    assert {t["these_scenes"] for t in doc["tuning"]} <= {"used", "held out"}
    # no machine's folders in a committed result
    text = (RESULTS / "table1.json").read_text() + (RESULTS / "table1.md").read_text()
    assert not [root for root in ("tmp", "work", "home", "root") if f"/{root}/" in text]
