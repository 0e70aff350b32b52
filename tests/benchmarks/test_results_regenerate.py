"""Every results file in benchmarks/results/ is written by its script from the JSON beside it
(issue 50): each one is rendered again from its committed JSON into a temporary folder and must
equal the committed Markdown byte for byte. Nothing is reconstructed or scored; the scripts'
``--from-json`` path only reads the JSON.

Files whose runs are gone and that no JSON can render are kept, unchanged, in
benchmarks/results/history/ with a README naming each one."""

from __future__ import annotations

import difflib
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
RESULTS = REPO / "benchmarks" / "results"
HISTORY = RESULTS / "history"

# results file -> the script that renders it from results file's .json
REGENERABLE = {
    "fast_preset_side_by_side.md": "benchmarks/fast_preset.py",
    "draft_preset_side_by_side.md": "benchmarks/fast_preset.py",
    "mesh_study.md": "benchmarks/mesh_study.py",
    "mesh_study_tune.md": "benchmarks/mesh_study.py",
    "field_step_variants.md": "benchmarks/field_step_variants.py",
    "table1.md": "benchmarks/table1.py",
    "fast_preset_against_854eaed.md": "benchmarks/fast_preset.py",
    "fast_preset_against_c184b53.md": "benchmarks/fast_preset.py",
    "input_views_dtu.md": "benchmarks/input_views_dtu.py",
    "novel_views_dtu.md": "benchmarks/novel_views_dtu.py",
    "novel_views_ibr_holes.md": "benchmarks/novel_views_dtu.py",
    "colour_ceiling.md": "benchmarks/colour_ceiling.py",
    "ablation_synthetic.md": "benchmarks/experiment_results.py",
    "ablation_dtu.md": "benchmarks/experiment_results.py",
    "ablation_synthetic_long.md": "benchmarks/experiment_results.py",
    "fusion_thresholds.md": "benchmarks/experiment_results.py",
    "stages.md": "benchmarks/experiment_results.py",
    "gce_q.md": "benchmarks/experiment_results.py",
    "views_cpu.md": "benchmarks/experiment_results.py",
    "views_accuracy.md": "benchmarks/views_accuracy.py",
    "ablation_fusion.md": "benchmarks/ablation_fusion.py",
    "resolution_cpu.md": "benchmarks/experiment_results.py",
    "views_cpu_scan37.md": "benchmarks/experiment_results.py",
    "ablation_synthetic_specular.md": "benchmarks/experiment_results.py",
    "ablation_synthetic_specular_long.md": "benchmarks/experiment_results.py",
}
TABLE_BRANCH: set[str] = set()  # (table1.md is rendered by benchmarks/table1.py since issue 50)


def _render(script: str, src: Path, out: Path) -> str:
    p = subprocess.run([sys.executable, script, "--from-json", str(src), "--results", str(out)],
                       cwd=REPO, capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    return out.read_text()


@pytest.mark.parametrize("name", sorted(REGENERABLE))
def test_results_file_is_rendered_from_its_json(name, tmp_path):
    md = RESULTS / name
    src = md.with_suffix(".json")
    assert src.is_file(), f"{name}: no JSON beside it"
    text = _render(REGENERABLE[name], src, tmp_path / name)
    committed = md.read_text()
    diff = "".join(difflib.unified_diff(committed.splitlines(True), text.splitlines(True),
                                        f"committed {name}", "rendered from its JSON", n=1))
    assert text == committed, diff[:4000]


def test_every_results_file_is_regenerable_or_history():
    """A Markdown file in benchmarks/results/ has its JSON and its renderer; anything else lives
    in history/ (listed in its README)."""
    top = {p.name for p in RESULTS.glob("*.md")}
    assert top - set(REGENERABLE) - TABLE_BRANCH == set(), \
        "results files no script renders from JSON: render them or move them to history/"
    listed = (HISTORY / "README.md").read_text()
    kept = sorted(p.relative_to(HISTORY).as_posix() for p in HISTORY.glob("*.md")
                  if p.name != "README.md")
    assert kept, "history/ holds no results file"
    missing = [k for k in kept if f"`{k}`" not in listed]
    assert not missing, f"history/README.md does not list {missing}"


def test_no_results_file_keeps_hand_written_notes():
    """Notes in a regenerable results file are computed; reasoning belongs in docs/."""
    for name in REGENERABLE:
        text = (RESULTS / name).read_text()
        assert "hand-written" not in text.lower(), name


def test_a_changed_json_changes_the_rendering(tmp_path):
    """The check has teeth: a number edited in the JSON shows in the rendered Markdown."""
    import json

    data = json.loads((RESULTS / "mesh_study_tune.json").read_text())
    data["points"]["s501"]["overall"] = 9.876
    src = tmp_path / "edited.json"
    src.write_text(json.dumps(data, indent=1))
    text = _render(REGENERABLE["mesh_study_tune.md"], src, tmp_path / "edited.md")
    assert "9.88" in text and text != (RESULTS / "mesh_study_tune.md").read_text()
