"""The saved field (`svolsdf.field.saved`): one function writes the dict (the field stage's
model.pt, the refined and the point-fitted fields, the trainer's checkpoints: the same keys,
``bounds`` included) and one reads it back into a model."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest
import torch

import svolsdf
from svolsdf.field.grid import GridFieldConfig, GridSDFField
from svolsdf.field.saved import field_state, load_field, read_field, save_field
from svolsdf.field.volsdf import VolSDFField, VolSDFFieldConfig


def _grid(resolution=8):
    return GridSDFField(torch.tensor([[-0.5, -0.4, -0.3], [0.5, 0.4, 0.3]]),
                        GridFieldConfig(resolution=resolution))


def test_a_grid_field_round_trips_with_its_box_and_resolution(tmp_path):
    torch.manual_seed(0)
    model = _grid(12)
    with torch.no_grad():
        model.sdf_grid.add_(torch.rand_like(model.sdf_grid))
    save_field(tmp_path / "f" / "model.pt", model)
    state = read_field(tmp_path / "f" / "model.pt")
    assert set(state) == {"model_state_dict", "grid_resolution", "bounds"}
    assert state["grid_resolution"] == 12
    torch.testing.assert_close(state["bounds"], model.bounds)
    other = _grid(8)  # takes the saved grid's shapes
    load_field(other, state)
    torch.testing.assert_close(other.sdf_grid, model.sdf_grid)


def test_a_field_without_a_grid_saves_no_box():
    state = field_state(VolSDFField(VolSDFFieldConfig(mlp_depth=2, skip_in=(), mlp_width=8)))
    assert state["grid_resolution"] is None and state["bounds"] is None


def test_a_file_of_another_kind_is_no_saved_field(tmp_path):
    torch.save({"weights": 1}, tmp_path / "x.pt")
    with pytest.raises(KeyError, match="not a saved field"):
        read_field(tmp_path / "x.pt")


def test_the_checkpoint_holds_the_saved_field(tmp_path):
    from svolsdf.config import TrainConfig
    from svolsdf.optimize.trainer import TrainData, Trainer
    from svolsdf.scene.cameras import Cameras

    cams = Cameras(torch.tensor([[[8.0, 0, 4], [0, 8.0, 4], [0, 0, 1]]]),
                   torch.eye(4)[None], 8, 8)
    t = Trainer(_grid(), TrainData(torch.rand(1, 3, 8, 8), cams, None),
                TrainConfig(mode="volsdf", steps=1), out_dir=tmp_path)
    state = read_field(t.save_checkpoint())
    assert {"model_state_dict", "grid_resolution", "bounds"} <= set(state)
    torch.testing.assert_close(state["bounds"], t.model.bounds)


def test_only_the_saved_field_module_writes_the_dict():
    root = Path(svolsdf.__file__).parent
    writers = sorted(str(p.relative_to(root)) for p in root.rglob("*.py")
                     if any(isinstance(n, ast.Constant) and n.value == "model_state_dict"
                            for n in ast.walk(ast.parse(p.read_text()))))
    assert writers == ["field/saved.py"]
