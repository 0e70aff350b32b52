"""`SurfaceModel`: the interface every surface representation implements (docs/architecture.md).

Beside the queries a renderer needs, a model declares what its training needs, each with a
default that fits a plain network (the pattern of nerfstudio's ``get_param_groups`` and
``get_training_callbacks``): its optimizer parameter groups, the parameters of its colour alone,
its per-step hooks (``before_step``, ``grow``), its extra losses, the box its eikonal samples are
drawn in, its background and its Laplace density. The trainer (`svolsdf.optimize.trainer`) and
the builders (`svolsdf.pipeline.builders`) call these and probe no attribute.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import torch
from torch import Tensor, nn

__all__ = ["SurfaceModel"]


class SurfaceModel(nn.Module):
    """An SDF field (SDF > 0 outside), a Laplace density and a colour network, in the unit frame.

    Subclasses: the paper's VolSDF MLP (`svolsdf.field.volsdf`) and the fast grid field.
    """

    #: bounding-sphere radius of the unit frame (docs/method.md 5.2)
    radius: float = 3.0
    #: nodes along the longest side of a field on a grid (saved with the field); None: no grid
    resolution: int | None = None
    #: the field was started from the stage-1 MVS surface (`svolsdf.field.initial` sets it)
    mvs_initialised: bool = False

    def sdf(self, x: Tensor) -> Tensor:
        """x: (N, 3) unit-frame points -> (N,) signed distances (clamped to the sphere)."""
        raise NotImplementedError

    def sdf_and_grad(
        self, x: Tensor, create_graph: bool = True, clamp: bool = True
    ) -> tuple[Tensor, Tensor, Tensor]:
        """x: (N, 3) -> sdf (N,), gradient (N, 3), feature (N, F).

        ``clamp=False`` asks for the raw field without the bounding-sphere clamp (the eikonal
        loss uses it, docs/method.md 4.5); models without a clamp ignore it. The gradient must be
        returned even when called under ``torch.no_grad()`` (render/ relies on it).
        """
        raise NotImplementedError

    def colour(self, x: Tensor, view_dir: Tensor, normal: Tensor, feature: Tensor) -> Tensor:
        """x, view_dir, normal: (N, 3), feature: (N, F) -> rgb (N, 3) in [0, 1]."""
        raise NotImplementedError

    def density(self, sdf: Tensor, beta: Tensor | None = None) -> Tensor:
        """sdf: (...) -> sigma (...) >= 0 (Laplace density, docs/method.md 5.4)."""
        raise NotImplementedError

    @property
    def beta(self) -> Tensor:
        """() current Laplace scale beta."""
        raise NotImplementedError

    # ---------------------------------------------------------------- training
    def get_param_groups(self, train: Any) -> list[dict]:
        """The optimizer's parameter groups (`torch.optim.Adam`'s dicts with "params" and
        "lr"), at the rates of ``train`` (a `svolsdf.config.TrainConfig`); the default: every
        parameter at ``train.lr`` (docs/method.md 4.6)."""
        return [{"params": list(self.parameters()), "lr": train.lr}]

    def colour_parameters(self) -> list[nn.Parameter] | None:
        """The parameters of the colour alone, which ``train.colour_steps`` train with the
        surface frozen; None (the default): colour and surface share their parameters."""
        return None

    def before_step(self) -> None:
        """Called before every optimization step, before the gradients are cleared (the grid
        field recycles its gradients' memory); the default does nothing."""

    def grow(self, resolution: int) -> bool:
        """Refine the field to ``resolution`` (a step of its kind's coarse-to-fine schedule,
        `svolsdf.field.kinds.FieldKind.schedule`).

        Returns:
            Whether the parameters were replaced (the optimizer is then rebuilt); the default:
            False (nothing to refine).
        """
        return False

    def extra_losses(self, train: Any) -> Iterator[tuple[str, float, Tensor]]:
        """The field's own regularisers under ``train`` (a `TrainConfig`): (name, weight, () loss)
        for each that applies, computed as it is yielded (the trainer adds weight x loss to the
        total); the default: none."""
        return iter(())

    def sdf_grad(self, x: Tensor, create_graph: bool = True, clamp: bool = True
                 ) -> tuple[Tensor, Tensor]:
        """x: (N, 3) -> sdf (N,), gradient (N, 3), without the colour feature (the eikonal
        samples need none); the default drops `sdf_and_grad`'s."""
        sdf, grad, _ = self.sdf_and_grad(x, create_graph=create_graph, clamp=clamp)
        return sdf, grad

    def box(self) -> Tensor | None:
        """(2, 3) unit-frame box [lo, hi] of a field that lives in one (a grid's), saved with
        the field; None (the default): the field fills the bounding sphere."""
        return None

    def sample_box(self, device: torch.device | str | None = None) -> Tensor:
        """(2, 3) unit-frame box [lo, hi] the eikonal term's uniform points are drawn in
        (docs/method.md 4.5): `box`, else the bounding sphere's cube (made on ``device``: no
        copy from the host inside a step)."""
        b = self.box()
        if b is not None:
            return b
        r = float(self.radius)
        return torch.stack([torch.full((3,), -r, device=device),
                            torch.full((3,), r, device=device)])

    def get_background(self) -> nn.Module | None:
        """The background model rendered beyond the bounding sphere (``model.background``,
        docs/method.md 5.5), or None."""
        return self._modules.get("background")

    def laplace_density(self) -> nn.Module | None:
        """The `svolsdf.field.density.LaplaceDensity` whose beta the trainer anneals and the
        config floors (``model.laplace``), or None (a fixed density)."""
        return self._modules.get("laplace")
