"""benchmarks/experiment_results.py finds each benchmark row's run folder and scene, with one
view set or several (the 3/6/9-view table's rows carry their views in the scene label)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def _module():
    spec = importlib.util.spec_from_file_location(
        "experiment_results", REPO / "benchmarks" / "experiment_results.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_row_paths_with_one_and_several_view_sets(tmp_path):
    row_paths = _module().row_paths
    run, data = tmp_path / "OUT", tmp_path / "DATA"
    assert row_paths({"scene": "dtu_scan65", "mode": "full"}, run, data) == (
        "dtu_scan65", run / "dtu_scan65" / "full", data / "dtu_scan65")
    assert row_paths({"scene": "dtu_scan65 [25,22,28,40,44,48]", "mode": "svolsdf"}, run,
                     data) == ("dtu_scan65", run / "dtu_scan65" / "views-25-22-28-40-44-48" /
                               "svolsdf", data / "dtu_scan65")
