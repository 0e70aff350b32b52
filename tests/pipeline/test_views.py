"""The held-out test views a run records (svolsdf.pipeline.views.test_views): the BlendedMVS
protocol's test views on a scan run from its input views, every other view elsewhere."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

from svolsdf.evaluate.blendedmvs import protocol
from svolsdf.pipeline import views as run_views


def _scene(name: str, n: int) -> SimpleNamespace:
    """What test_views reads of a scene: its folder, view ids and format facts."""
    return SimpleNamespace(path=Path("data") / name, view_ids=list(range(n)), extras={})


def test_a_blendedmvs_scan_from_its_inputs_holds_out_the_protocols_test_views():
    p = protocol(7)
    assert run_views.test_views(_scene("bmvs_scan7", 31), p["inputs"]) == p["test"]
    assert len(p["test"]) == 12
    # other inputs, another dataset's name, or a scene without every test view: every other view
    for scene, inputs in ((_scene("bmvs_scan7", 31), [0, 1, 2]),
                          (_scene("scan7", 31), p["inputs"]),
                          (_scene("bmvs_scan7", 26), p["inputs"])):
        assert run_views.test_views(scene, inputs) == [v for v in scene.view_ids if v not in inputs]
