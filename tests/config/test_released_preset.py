"""The released preset (the released code's settings and per-scan constants) and the record of
which MVS backbone a paper or released run used."""

from __future__ import annotations

import json

import pytest

from svolsdf.config import load_config, preset, save_config
from svolsdf.config.presets import (
    RELEASED_SCAN_OVERRIDES,
    backbone_provenance,
    scene_overrides,
)
from svolsdf.mvs.hypotheses import interval_ratio


def test_released_preset_is_the_released_codes_settings():
    c = preset("released")
    assert c.preset == "released" and c.field.kind == "mlp" and c.train.steps == 100_000
    assert (c.train.gce_form, c.train.sparse_norm, c.train.sparse_decay,
            c.train.warmup_mask_supervised) == ("released", "all", True, True)
    assert [interval_ratio(k, c.mvs.width) for k in (1, 2, 3)] == [1.0, 0.5, 0.5]


@pytest.mark.parametrize("folder, expected", [
    ("dtu_scan24", {"train.sparse_weight": 0.0}),
    ("scan37", {"train.sparse_weight": 0.1}),
    ("bmvs_scan2", {"train.sparse_weight": 0.0, "mvs.inverse_depth": True}),
    ("BlendedMVS_scan5", {"mvs.inverse_depth": True}),
    ("dtu_scan65", {}),
    ("my_photos", {}),
])
def test_released_per_scan_constants(folder, expected):
    c = preset("released")
    c.scene.path = f"data/{folder}"
    assert scene_overrides(c) == expected
    for k, v in expected.items():
        s, o = k.split(".")
        assert getattr(getattr(c, s), o) == v
    f = preset("fast")  # other presets have no per-scan constants
    f.scene.path = f"data/{folder}"
    assert scene_overrides(f) == {}


def test_given_options_win_over_per_scan_constants():
    c = preset("released")
    c.scene.path = "dtu_scan24"
    assert scene_overrides(c, {"train.sparse_weight"}) == {}
    assert c.train.sparse_weight == 1.0
    assert RELEASED_SCAN_OVERRIDES["dtu"][24] == {"train.sparse_weight": 0.0}


def test_cli_config_of_released_preset_on_scan_24(tmp_path, capsys):
    from svolsdf.cli.app import build_config

    scene = tmp_path / "dtu_scan24"
    scene.mkdir()
    cfg = build_config(scene, None, "released", {})
    assert cfg.train.sparse_weight == 0.0
    cfg = build_config(scene, None, "released", {}, sets=["train.sparse_weight=0.5"])
    assert cfg.train.sparse_weight == 0.5


def test_paper_preset_says_which_backbone_ran(tmp_path):
    c = preset("paper")
    p = backbone_provenance(c)
    assert p["backbone"] == "planesweep" and not p["papers"]
    assert "not the paper's DTU-trained CasMVSNet" in p["note"] and "plane sweep" in p["note"]
    save_config(c, tmp_path / "config.yaml")
    head = (tmp_path / "config.yaml").read_text().splitlines()[0]
    assert head.startswith("# paper preset: mvs.backbone planesweep, not the paper's")
    assert load_config(tmp_path / "config.yaml").mvs.backbone == "planesweep"  # still loads
    c.mvs.backbone, c.mvs.weights = "casmvsnet", "/x/casmvsnet.ckpt"
    p = backbone_provenance(c)
    assert p["papers"] and p["weights"] == "casmvsnet.ckpt"
    save_config(preset("fast"), tmp_path / "fast.yaml")  # other presets: no comment
    assert not (tmp_path / "fast.yaml").read_text().startswith("#")


def test_metrics_json_records_the_backbone(tmp_path):
    from svolsdf.evaluate.scoring import EvaluateConfig, evaluate_run
    from svolsdf.io.ply import write_points_ply

    out = tmp_path / "run"
    out.mkdir()
    save_config(preset("paper"), out / "config.yaml")
    import numpy as np

    write_points_ply(out / "points.ply", np.random.default_rng(0).random((50, 3)))
    m = evaluate_run(EvaluateConfig(out=out))
    rec = json.loads((out / "metrics.json").read_text())["settings"]["mvs_backbone"]
    assert rec["backbone"] == "planesweep" and rec["papers"] is False
    assert rec["preset"] == "paper" and m["settings"]["mvs_backbone"] == rec
