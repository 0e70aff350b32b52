"""What the stage helpers may use of the running pipeline: the `StageContext` protocol.

`pipeline/fusion_stage.py`, `pipeline/mesh.py` and `pipeline/finer.py` gather a stage's inputs and
call the component that does the work. They take a `StageContext`, not the `Pipeline`: the
config, the run folder, the loaded scene, the backbones and the guide depth the earlier
stages wrote, and nothing else. `svolsdf.pipeline.runner.Pipeline` provides it; the helpers do not
import the pipeline, so the only arrow between them runs from the pipeline down to its helpers.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import torch

from svolsdf.config import Config
from svolsdf.pipeline.rundir import RunDir
from svolsdf.scene.scene import Scene

__all__ = ["GuideRender", "StageContext"]


@dataclass
class GuideRender:
    """The field's rendering of the input views for the guide (`StageContext.render_guide`).

    Attributes:
        depth: {view: (H, W) world z-depth} with docs/method.md 6.1's low-weight rule.
        field_psnr: PSNR of the rendered colours on the input views
            (`svolsdf.pipeline.previews.field_psnr`), when previews were asked for.
    """

    depth: dict[int, torch.Tensor]
    field_psnr: float | None = None


class StageContext(Protocol):
    """The running pipeline as the stage helpers see it.

    Attributes:
        cfg: the run's validated `Config`.
        dir: the run folder (`RunDir`); ``out`` its path.
        views: the input view ids, in the run's order (after `load`).
        device: where the stages compute.
        progress: show progress bars.
    """

    cfg: Config
    dir: RunDir
    out: Path
    views: list[int]
    device: torch.device
    progress: bool

    def load(self) -> Scene:
        """The input views at the working size (loaded once)."""
        ...

    def field_bounds(self) -> torch.Tensor:
        """(2, 3) unit-frame box of the field."""
        ...

    def backbone(self) -> Any:
        """The configured MVS backbone (`svolsdf.mvs.backbone.MVSBackbone`)."""
        ...

    def network_backbone(self) -> Any:
        """The ``fusion.network`` backbone (its weights loaded once)."""
        ...

    def train_data(self) -> Any:
        """The field stage's `svolsdf.optimize.trainer.TrainData`."""
        ...

    def guide_depth(self) -> dict[int, torch.Tensor] | None:
        """The guide stage's depth maps as it wrote them ({view: (H, W) world z-depth}), or
        None when the run has no guide."""
        ...

    def render_guide(self, model, previews: bool = False) -> GuideRender:
        """``model``'s guide depth of the input views (docs/method.md 6.1)."""
        ...
