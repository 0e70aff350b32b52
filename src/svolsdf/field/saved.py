"""The saved field: the one layout of the dict a fitted `SurfaceModel` is saved as (OUT/field/
model.pt, the refined and the point-fitted fields, the trainer's checkpoints), written by
`field_state` and read back by `load_field`.

The dict: ``model_state_dict`` (the model's state_dict; a grid field takes its grid shapes and
box from it, `svolsdf.field.grid.GridSDFField`), ``grid_resolution`` (`SurfaceModel.resolution`,
None without a grid) and ``bounds`` (`SurfaceModel.box`, the (2, 3) unit-frame box of a field
on a grid, None otherwise); a checkpoint adds the optimizer's state beside them.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from svolsdf.field.base import SurfaceModel
from svolsdf.io.runfolder import atomic_write

__all__ = ["field_state", "load_field", "read_field", "save_field"]


def field_state(model: SurfaceModel) -> dict[str, Any]:
    """The dict ``model`` is saved as (see the module's docstring)."""
    return {"model_state_dict": model.state_dict(), "grid_resolution": model.resolution,
            "bounds": model.box()}


def save_field(path: str | Path, model: SurfaceModel) -> None:
    """Write `field_state` (``model``) to ``path`` atomically (`svolsdf.io.runfolder.atomic_write`:
    a killed run leaves no half file), creating its folder."""
    state = field_state(model)
    atomic_write(Path(path), lambda tmp: torch.save(state, tmp))


def read_field(path: str | Path, map_location: Any = "cpu") -> dict[str, Any]:
    """The dict `save_field` wrote to ``path`` (or a checkpoint), its tensors on
    ``map_location``.

    Raises:
        KeyError: the file holds no saved field; torch.load's errors (RuntimeError,
            UnpicklingError, EOFError, OSError) for a truncated or unreadable one.
    """
    state = torch.load(path, map_location=map_location, weights_only=False)
    if not isinstance(state, dict) or "model_state_dict" not in state:
        raise KeyError("no model_state_dict: not a saved field")
    return state


def load_field(model: SurfaceModel, state: dict[str, Any]) -> None:
    """Load a dict `field_state` wrote (read with ``torch.load``) into ``model``.

    Raises:
        KeyError: ``state`` is not a saved field.
        RuntimeError: it holds another field than ``model`` (torch's message).
    """
    model.load_state_dict(state["model_state_dict"])
