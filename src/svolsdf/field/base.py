"""`SurfaceModel`: the interface every surface representation implements (docs/architecture.md)."""

from __future__ import annotations

from torch import Tensor, nn

__all__ = ["SurfaceModel"]


class SurfaceModel(nn.Module):
    """An SDF field (SDF > 0 outside), a Laplace density and a colour network, in the unit frame.

    Subclasses: the paper's VolSDF MLP (`svolsdf.field.volsdf`) and the fast grid field.
    """

    #: bounding-sphere radius of the unit frame (docs/method.md 5.2)
    radius: float = 3.0

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
