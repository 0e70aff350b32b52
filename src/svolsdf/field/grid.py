"""The `fast` preset's surface: an explicit dense SDF grid plus a multi-level feature grid.

Design (measured by ``benchmarks/field_speed.py``; ``benchmarks/results/history/field_speed.md``):

- Geometry is an explicit dense SDF grid over an axis-aligned box of the unit frame, interpolated
  trilinearly (``grid_sample`` semantics, align_corners=True) and initialised to a sphere SDF
  |x - c| - r, like VolSDF's geometric init (docs/method.md 5.2). Its spatial gradient is computed
  in closed form from the 8 gathered corners (`grid_ops.trilinear_with_grad`): on 50k points with an
  eikonal term this measured ~3.5x faster than autograd through ``grid_sample`` with
  create_graph and ~13x faster than central finite differences at half a cell, and it is exact.
- Appearance comes from a multi-level dense feature grid (levels at fixed fractions of the SDF
  resolution) feeding a small MLP with the view-direction encoding and the normal, like IDR's
  rendering network (docs/method.md 5.3) but 2x64 wide. The levels are read by `trilinear_sample`
  (a corner gather; ~2x faster than the single-threaded ``grid_sample`` 3-D CPU kernel with its
  backward, benchmarks/results/history/train_step_speed.md).
- Optionally (``sdf_residual``) the same features feed a second small MLP whose output is added to
  the grid SDF; its x-gradient then goes through autograd (slower, see the benchmark).
- Outside the box the SDF continues as f(p) + |x - p| with p the closest box point, so rays
  outside the box see a positive SDF that grows with the distance (if f > 0 on the box faces).
- Coarse-to-fine: `upsample` resamples every grid; the caller rebuilds its optimizer from
  `param_groups`. `smoothness_loss` (a Laplacian on the SDF grid) is the regulariser sparse views
  need, `feature_tv_loss` smooths the colour features.
- Density: VolSDF's Laplace density (docs/method.md 5.4, `svolsdf.field.density`), with a learnable
  beta and a settable floor `beta_min` that `beta_schedule` can anneal.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor, nn
from torch.profiler import record_function

from svolsdf.field.base import SurfaceModel
from svolsdf.field.density import LaplaceDensity
from svolsdf.field.embedding import positional_encoding
from svolsdf.field.grid_ops import (
    GradBuffers,
    device_vector,
    laplacian_loss,
    resample_grid,
    total_variation_loss,
    trilinear_sample,
    trilinear_with_grad,
)

__all__ = ["GridFieldConfig", "GridSDFField", "beta_schedule"]


@dataclass
class GridFieldConfig:
    """Configuration of `GridSDFField`."""

    resolution: int = 64
    """Initial SDF grid nodes along the longest box side (other sides in proportion, so cells are
    about cubic); `GridSDFField.upsample` grows it (e.g. 64 -> 96 -> 128 -> 160)."""

    feature_channels: int = 8
    """Channels per feature level."""

    feature_level_scales: tuple[float, ...] = (0.25, 0.5, 1.0)
    """Resolution of each feature level as a fraction of the SDF grid resolution (coarse to fine);
    the levels follow the SDF grid when it is upsampled."""

    min_feature_resolution: int = 8
    """Lower bound on a feature level's nodes along the longest side."""

    feature_init_std: float = 1e-2
    """Std of the normal initialisation of the feature grids (small: colour starts near grey)."""

    hidden_width: int = 64
    """Width of the hidden layers of the colour (and residual) MLP."""

    hidden_layers: int = 2
    """Number of hidden layers of the colour (and residual) MLP."""

    view_multires: int = 1
    """Positional-encoding frequencies of the view direction (docs/method.md 5.3 uses 1)."""

    sdf_residual: bool = False
    """Add a feature-MLP residual to the grid SDF (more expressive, ~2-3x slower per step)."""

    init_radius: float = 0.6
    """Radius r of the initial sphere SDF |x - c| - r, unit-frame units (VolSDF's bias 0.6)."""

    init_centre: tuple[float, float, float] | None = None
    """Centre c of the initial sphere; None = the box centre."""

    beta_init: float = 0.1
    """Initial value of the learnable Laplace beta parameter (docs/method.md 5.4)."""

    beta_min: float = 1e-4
    """Floor added to |beta_param| (docs/method.md 5.4); settable later for annealing."""

    sphere_clamp_scale: float | None = 20.0
    """sdf <- min(sdf, scale (radius - |x|)) as in docs/method.md 5.2 (DTU: 20); None disables
    it."""

    radius: float = 3.0
    """Bounding-sphere radius R of the unit frame for the clamp (docs/method.md 5.2)."""


def beta_schedule(step: int, total_steps: int, start: float, end: float) -> float:
    """Log-linear anneal of beta: ``start`` at step 0, ``end`` at ``total_steps`` and after.

    beta(step) = start * (end / start) ** min(step / total_steps, 1). Two ways to use it: pass it
    explicitly, ``field.density(sdf, beta=torch.tensor(beta_schedule(...)))`` (the learned beta is
    then unused), or set ``field.beta_min`` to it so the learned beta cannot fall below the
    schedule early in training.
    """
    if start <= 0 or end <= 0 or total_steps <= 0:
        raise ValueError(
            f"beta_schedule needs start, end, total_steps > 0, got {start}, {end}, {total_steps}"
        )
    t = min(max(step, 0) / total_steps, 1.0)
    return float(start * (end / start) ** t)


def _mlp(d_in: int, width: int, layers: int, d_out: int) -> nn.Sequential:
    mods: list[nn.Module] = []
    d = d_in
    for _ in range(layers):
        mods += [nn.Linear(d, width), nn.ReLU(inplace=True)]
        d = width
    mods.append(nn.Linear(d, d_out))
    return nn.Sequential(*mods)


def _grid_shape(extent: Tensor, resolution: int) -> tuple[int, int, int]:
    """(Z, Y, X) node counts for a box of size ``extent`` (3,) (x, y, z) at ``resolution`` nodes
    along its longest side; with a box from `_snap_bounds` the cells are exactly cubic."""
    n = [max(2, int(round((resolution - 1) * float(e) / float(extent.max()))) + 1) for e in extent]
    return (n[2], n[1], n[0])


def _snap_bounds(bounds: Tensor, resolution: int) -> Tensor:
    """Grow the shorter sides of a (2, 3) box symmetrically (by less than one cell) so that a
    grid with ``resolution`` nodes along the longest side has cubic cells. Then every
    ``upsample`` to k (resolution - 1) + 1 nodes refines every axis exactly."""
    extent = bounds[1] - bounds[0]
    h = float(extent.max()) / (resolution - 1)
    cells = torch.clamp(torch.ceil(extent / h - 1e-4), min=1)
    centre = bounds.mean(0)
    half = cells * h / 2
    return torch.stack([centre - half, centre + half])


class GridSDFField(SurfaceModel):
    """Dense SDF grid + multi-level feature grid + small colour MLP (the `fast` preset's field).

    Args:
        bounds: (2, 3) [[x0, y0, z0], [x1, y1, z1]] the grid's box in the unit frame; the shorter
            sides grow by less than one cell so that cells are cubic (see ``field.bounds``).
        config: `GridFieldConfig`; defaults if None.

    Example:
        >>> field = GridSDFField(torch.tensor([[-1.2] * 3, [1.2] * 3]))
        >>> s, g, feat = field.sdf_and_grad(torch.zeros(5, 3))
        >>> s.shape, g.shape, feat.shape
        (torch.Size([5]), torch.Size([5, 3]), torch.Size([5, 24]))
    """

    def __init__(self, bounds: Tensor, config: GridFieldConfig | None = None):
        super().__init__()
        cfg = config or GridFieldConfig()
        self.config = cfg
        bounds = torch.as_tensor(bounds, dtype=torch.float32)
        if bounds.shape != (2, 3) or not torch.isfinite(bounds).all():
            raise ValueError(f"GridSDFField: bounds must be a finite (2, 3) tensor, got {bounds}")
        if not (bounds[1] > bounds[0]).all():
            raise ValueError(f"GridSDFField: bounds must have lo < hi on every axis, got {bounds}")
        if cfg.resolution < 3:
            raise ValueError(f"GridSDFField: resolution must be >= 3, got {cfg.resolution}")
        self.radius = float(cfg.radius)
        # The box grows by < 1 cell on its shorter sides so that cells are cubic.
        self.register_buffer("bounds", _snap_bounds(bounds, cfg.resolution))
        self.resolution = int(cfg.resolution)

        shape = _grid_shape(self.bounds[1] - self.bounds[0], self.resolution)
        self.sdf_grid = nn.Parameter(self._sphere_grid(shape))
        self.feature_grids = nn.ParameterList(
            [
                nn.Parameter(
                    torch.randn(cfg.feature_channels, *self._feature_shape(s))
                    * cfg.feature_init_std
                )
                for s in cfg.feature_level_scales
            ]
        )
        self.feature_dim = cfg.feature_channels * len(cfg.feature_level_scales)
        view_dim = 3 * (1 + 2 * cfg.view_multires)
        self.colour_net = _mlp(
            self.feature_dim + view_dim + 3, cfg.hidden_width, cfg.hidden_layers, 3
        )
        self.residual_net: nn.Sequential | None = None
        if cfg.sdf_residual:
            self.residual_net = _mlp(self.feature_dim, cfg.hidden_width, cfg.hidden_layers, 1)
            nn.init.zeros_(self.residual_net[-1].weight)  # residual starts at 0
            nn.init.zeros_(self.residual_net[-1].bias)
        self.laplace = LaplaceDensity(cfg.beta_init, cfg.beta_min)
        self._grad_buffers = GradBuffers()  # the feature grids' gradients, reused

    # ------------------------------------------------------------------ grids
    def _node_coords(self, shape: tuple[int, int, int]) -> Tensor:
        """(Z, Y, X, 3) unit-frame positions (x, y, z) of the nodes of a grid of ``shape``."""
        lo, hi = self.bounds
        axes = [torch.linspace(float(lo[i]), float(hi[i]), shape[2 - i]) for i in range(3)]
        zz, yy, xx = torch.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
        return torch.stack([xx, yy, zz], dim=-1)

    def _sphere_grid(self, shape: tuple[int, int, int]) -> Tensor:
        """(1, Z, Y, X) sphere SDF |x - c| - r at the nodes (docs/method.md 5.2's geometric
        init)."""
        cfg = self.config
        c = (
            self.bounds.mean(0)
            if cfg.init_centre is None
            else torch.tensor(cfg.init_centre, dtype=torch.float32)
        )
        return ((self._node_coords(shape) - c).norm(dim=-1) - cfg.init_radius)[None]

    def _feature_shape(self, scale: float) -> tuple[int, int, int]:
        res = max(self.config.min_feature_resolution, int(round(self.resolution * scale)))
        return _grid_shape(self.bounds[1] - self.bounds[0], res)

    @property
    def grid_shape(self) -> tuple[int, int, int]:
        """(Z, Y, X) node counts of the SDF grid."""
        return tuple(self.sdf_grid.shape[1:])

    @property
    def cell_size(self) -> Tensor:
        """(3,) SDF grid spacing (x, y, z) in unit-frame units."""
        Z, Y, X = self.grid_shape
        n = device_vector([X, Y, Z], self.bounds.device, self.bounds.dtype)
        return (self.bounds[1] - self.bounds[0]) / (n - 1)

    @torch.no_grad()
    def upsample(self, new_resolution: int) -> None:
        """Resample the SDF grid (and the feature levels, in proportion) to ``new_resolution``.

        The represented SDF is preserved up to trilinear re-interpolation error (exactly when the
        new node count per axis is k (old - 1) + 1). The grids become new ``nn.Parameter``
        objects: rebuild the optimizer from `param_groups` afterwards.
        """
        if new_resolution < 3:
            raise ValueError(f"upsample: resolution must be >= 3, got {new_resolution}")
        self._grad_buffers.clear()
        self.resolution = int(new_resolution)
        shape = _grid_shape(self.bounds[1] - self.bounds[0], self.resolution)
        self.sdf_grid = nn.Parameter(resample_grid(self.sdf_grid.data, shape))
        for i, s in enumerate(self.config.feature_level_scales):
            fs = self._feature_shape(s)
            self.feature_grids[i] = nn.Parameter(resample_grid(self.feature_grids[i].data, fs))

    def _load_from_state_dict(self, state_dict, prefix, local_metadata, strict, missing_keys,
                              unexpected_keys, error_msgs) -> None:
        """A checkpoint is self-describing: take its box and grid shapes before copying.

        The box comes from stage-1 MVS and a random subset of its points (``field_bounds`` in
        the pipeline), so a field rebuilt later (another process, the stage-1 volumes deleted,
        another seed) may have a slightly different box; the stored one is the truth.
        """
        b = state_dict.get(prefix + "bounds")
        g = state_dict.get(prefix + "sdf_grid")
        if b is not None and g is not None and b.shape == (2, 3) and g.ndim == 4:
            with torch.no_grad():
                self.bounds = b.detach().to(self.bounds.device, self.bounds.dtype).clone()
                self.resolution = int(max(g.shape[1:]))
                if tuple(g.shape) != tuple(self.sdf_grid.shape):
                    self.sdf_grid = nn.Parameter(self.sdf_grid.new_zeros(g.shape))
                for i in range(len(self.feature_grids)):
                    f = state_dict.get(f"{prefix}feature_grids.{i}")
                    if f is not None and tuple(f.shape) != tuple(self.feature_grids[i].shape):
                        self.feature_grids[i] = nn.Parameter(
                            self.feature_grids[i].new_zeros(f.shape))
        super()._load_from_state_dict(state_dict, prefix, local_metadata, strict, missing_keys,
                                      unexpected_keys, error_msgs)

    def param_groups(self, lr_grid: float, lr_mlp: float) -> list[dict]:
        """Optimizer parameter groups: the grids at ``lr_grid``; the MLPs and beta at ``lr_mlp``.

        Returns a list of dicts usable as ``torch.optim.Adam(field.param_groups(...))``; each has
        a "name" key ("grid" or "mlp").
        """
        grid = [self.sdf_grid, *self.feature_grids]
        bg = self.get_background()  # a background's maps train as grids
        if bg is not None and hasattr(bg, "grid_parameters"):
            grid += bg.grid_parameters()
        grid_ids = {id(p) for p in grid}
        rest = [p for p in self.parameters() if id(p) not in grid_ids]
        return [
            {"params": grid, "lr": lr_grid, "name": "grid"},
            {"params": rest, "lr": lr_mlp, "name": "mlp"},
        ]

    def get_param_groups(self, train) -> list[dict]:
        """`param_groups` at ``train.lr_grid`` and ``train.lr``, the SDF grid apart at its own
        (small) rate: ``train.lr_sdf`` started from the MVS surface, else
        ``train.lr_sdf_sphere``."""
        groups = self.param_groups(train.lr_grid, train.lr)
        sdf = self.sdf_grid
        for g in groups:
            g["params"] = [p for p in g["params"] if p is not sdf]
        lr = train.lr_sdf if self.mvs_initialised else train.lr_sdf_sphere
        groups.append({"params": [sdf], "lr": lr, "name": "sdf"})
        return groups

    def colour_parameters(self) -> list[nn.Parameter]:
        """The parameters of the colour alone: the feature grids, the colour network and the
        background's (`svolsdf.optimize.trainer.Trainer`'s colour steps train only these)."""
        bg = self.get_background()
        return [*self.feature_grids, *self.colour_net.parameters(),
                *(bg.parameters() if bg is not None else [])]

    def before_step(self) -> None:
        """`recycle_grads`: the dense gradients' memory is reused every step."""
        self.recycle_grads()

    def grow(self, resolution: int) -> bool:
        """`upsample` to ``resolution`` when it is finer than the grid's."""
        if resolution <= self.resolution:
            return False
        self.upsample(resolution)
        return True

    def extra_losses(self, train):
        """The grid's eikonal term on every node (``train.grid_eikonal_weight``, from the
        sphere only: a start from the MVS surface is not a distance field yet) and its
        Laplacian smoothness (``train.smooth_weight``)."""
        if train.grid_eikonal_weight > 0 and not self.mvs_initialised:
            yield "grid_eikonal", train.grid_eikonal_weight, self.grid_eikonal_loss()
        if train.smooth_weight > 0:
            yield "smooth", train.smooth_weight, self.smoothness_loss()

    def box(self) -> Tensor:
        """(2, 3) the grid's box (``bounds``)."""
        return self.bounds

    def recycle_grads(self) -> None:
        """Clear the feature grids' gradients (``.grad = None``), keeping their memory for the
        next backward (`grid_ops.GradBuffers`). For an optimizer loop that clears the gradients
        after each step and keeps no reference to them (`svolsdf.optimize.trainer.Trainer`): a
        kept reference would see the next step's gradient."""
        for fg in self.feature_grids:
            if fg.grad is not None:
                self._grad_buffers.give(fg.grad.view(fg.shape[0], -1))
                fg.grad = None

    def smoothness_loss(self, n_samples: int | None = 65536) -> Tensor:
        """() Laplacian regulariser of the SDF grid, in unit-frame units (see grid_ops).

        L = mean over nodes and axes of (second difference / h_axis^2)^2, with h the cell size,
        so its scale does not change with `upsample`; zero for planar SDFs, hence compatible with
        the eikonal term. ``n_samples`` random interior nodes (None = all).
        """
        # Cells are cubic (_snap_bounds) up to rounding after a non-integer upsample factor.
        # (the cell size stays a device tensor: float() here would stall a GPU every step)
        return laplacian_loss(self.sdf_grid, n_samples) / self.cell_size.mean() ** 4

    def grid_eikonal_loss(self) -> Tensor:
        """() mean over all cells of (|grad f| - 1)^2, grad f by forward differences of the SDF
        grid (the eikonal constraint of docs/method.md 4.5 on every node, not only at samples)."""
        g = self.sdf_grid[0]
        cs = self.cell_size  # (x, y, z)
        base = g[:-1, :-1, :-1]
        gz = (g[1:, :-1, :-1] - base) / cs[2]
        gy = (g[:-1, 1:, :-1] - base) / cs[1]
        gx = (g[:-1, :-1, 1:] - base) / cs[0]
        return ((torch.sqrt(gx.square() + gy.square() + gz.square() + 1e-12) - 1) ** 2).mean()

    def feature_tv_loss(self) -> Tensor:
        """() mean over levels of the total variation (squared differences) of each feature grid."""
        return torch.stack([total_variation_loss(g) for g in self.feature_grids]).mean()

    # ---------------------------------------------------------------- queries
    def _check_points(self, x: Tensor, name: str = "x") -> None:
        if x.dim() != 2 or x.shape[-1] != 3:
            raise ValueError(f"GridSDFField: {name} must be (N, 3), got shape {tuple(x.shape)}")

    def _to_box(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """x (N, 3) -> p (N, 3) closest box point, x - p (N, 3), inside-per-axis mask (N, 3)."""
        lo, hi = self.bounds
        p = torch.maximum(torch.minimum(x, hi), lo)
        inside = (x >= lo) & (x <= hi)
        return p, x - p, inside

    def _features(self, p: Tensor) -> Tensor:
        """p: (N, 3) box points -> (N, feature_dim) multi-level trilinear features."""
        with record_function("svolsdf.feature_lookup"):
            lo, hi = self.bounds
            t = (p - lo) / (hi - lo)  # (N, 3) in [0, 1] over the box
            feats = []
            for fg in self.feature_grids:
                Z, Y, X = fg.shape[1:]
                feats.append(trilinear_sample(fg, t * device_vector([X - 1, Y - 1, Z - 1],
                                                                    t.device, t.dtype),
                                              self._grad_buffers))
            return torch.cat(feats, dim=1)

    def _grid_sdf(self, x: Tensor, with_grad: bool) -> tuple[Tensor, Tensor | None, Tensor]:
        """Box-extended grid SDF: f(p) + |x - p|; returns sdf (N,), grad (N, 3) or None, p."""
        p, d, inside = self._to_box(x)
        lo, hi = self.bounds
        Z, Y, X = self.grid_shape
        n = device_vector([X, Y, Z], x.device, x.dtype)
        to_index = (n - 1) / (hi - lo)  # (3,) index units per unit-frame unit
        value, gu = trilinear_with_grad(self.sdf_grid, (p - lo) * to_index, with_grad)
        dist = d.norm(dim=-1)
        sdf = value[:, 0] + dist
        if not with_grad:
            return sdf, None, p
        grad = gu[:, 0] * to_index * inside + d / dist.clamp_min(1e-12)[:, None]
        return sdf, grad, p

    def _clamp(self, x: Tensor, sdf: Tensor, grad: Tensor | None) -> tuple[Tensor, Tensor | None]:
        """sdf <- min(sdf, s (R - |x|)) (docs/method.md 5.2) and the matching gradient."""
        s = self.config.sphere_clamp_scale
        if s is None:
            return sdf, grad
        r = x.norm(dim=-1)
        bound = s * (self.radius - r)
        use_bound = bound < sdf
        sdf = torch.where(use_bound, bound, sdf)
        if grad is not None:
            gb = -s * x / r.clamp_min(1e-12)[:, None]
            grad = torch.where(use_bound[:, None], gb, grad)
        return sdf, grad

    def sdf(self, x: Tensor, clamp: bool = True) -> Tensor:
        """x: (N, 3) unit-frame points -> (N,) signed distances (> 0 outside).

        ``clamp`` applies the bounding-sphere clamp (docs/method.md 5.2); the eikonal term uses the
        raw field (clamp=False, docs/method.md 4.5).
        """
        self._check_points(x)
        with record_function("svolsdf.sdf_lookup"):
            sdf, _, p = self._grid_sdf(x, with_grad=False)
        if self.residual_net is not None:
            sdf = sdf + self.residual_net(self._features(p))[:, 0]
        return self._clamp(x, sdf, None)[0] if clamp else sdf

    def sdf_and_grad(
        self, x: Tensor, create_graph: bool = True, clamp: bool = True
    ) -> tuple[Tensor, Tensor, Tensor]:
        """x: (N, 3) -> sdf (N,), gradient d sdf / d x (N, 3), feature (N, feature_dim).

        The grid part's gradient is analytic (closed form of trilinear interpolation) and is
        differentiable w.r.t. the grid, so an eikonal loss on it trains the grid. With
        ``create_graph=False`` the gradient is returned detached (normals for rendering).
        ``clamp`` as in `sdf`.
        """
        self._check_points(x)
        with record_function("svolsdf.sdf_lookup"):
            sdf, grad, p = self._grid_sdf(x, with_grad=True)
        feat = self._features(p)
        if self.residual_net is not None:
            with torch.enable_grad():
                xr = x if x.requires_grad else x.detach().requires_grad_(True)
                pr, _, _ = self._to_box(xr)
                fr = self._features(pr)
                res = self.residual_net(fr)[:, 0]
                (gres,) = torch.autograd.grad(res.sum(), xr, create_graph=create_graph)
            sdf = sdf + res
            grad = grad + gres
            feat = fr
        if clamp:
            sdf, grad = self._clamp(x, sdf, grad)
        if not create_graph:
            grad = grad.detach()
        return sdf, grad, feat

    def sdf_grad(
        self, x: Tensor, create_graph: bool = True, clamp: bool = True
    ) -> tuple[Tensor, Tensor]:
        """x: (N, 3) -> sdf (N,), gradient d sdf / d x (N, 3): `sdf_and_grad` without the
        colour features (the eikonal term, docs/method.md 4.5, needs only the gradient; with
        ``sdf_residual`` the features are part of the SDF and are computed)."""
        if self.residual_net is not None:
            sdf, grad, _ = self.sdf_and_grad(x, create_graph=create_graph, clamp=clamp)
            return sdf, grad
        self._check_points(x)
        with record_function("svolsdf.sdf_lookup"):
            sdf, grad, _ = self._grid_sdf(x, with_grad=True)
        if clamp:
            sdf, grad = self._clamp(x, sdf, grad)
        if not create_graph:
            grad = grad.detach()
        return sdf, grad

    def colour_features(self, x: Tensor) -> Tensor:
        """x: (N, 3) -> (N, feature_dim) the colour network's features at x, the third output
        of `sdf_and_grad` without its SDF (training renders the colour only where a sample's
        weight counts, `svolsdf.render.volume.render_rays`)."""
        self._check_points(x)
        p, _, _ = self._to_box(x)
        return self._features(p)

    def colour(self, x: Tensor, view_dir: Tensor, normal: Tensor, feature: Tensor) -> Tensor:
        """x, view_dir, normal: (N, 3), feature: (N, feature_dim) -> rgb (N, 3) in [0, 1].

        MLP([feature, gamma_1(view_dir), normal / |normal|]) with a sigmoid output, an IDR-style
        rendering network (docs/method.md 5.3) narrowed to `hidden_width`. ``x`` is not an input
        (the features already encode position); it is checked for shape only.
        """
        self._check_points(x)
        n = x.shape[0]
        if view_dir.shape != (n, 3) or normal.shape != (n, 3):
            raise ValueError(
                f"GridSDFField.colour: view_dir and normal must be ({n}, 3), got "
                f"{tuple(view_dir.shape)} and {tuple(normal.shape)}"
            )
        if feature.shape != (n, self.feature_dim):
            raise ValueError(
                f"GridSDFField.colour: feature must be ({n}, {self.feature_dim}), "
                f"got {tuple(feature.shape)}"
            )
        with record_function("svolsdf.colour_mlp"):
            nrm = normal / normal.norm(dim=-1, keepdim=True).clamp_min(1e-6)
            h = torch.cat(
                [feature, positional_encoding(view_dir, self.config.view_multires), nrm], dim=-1
            )
            return torch.sigmoid(self.colour_net(h))

    def density(self, sdf: Tensor, beta: Tensor | None = None) -> Tensor:
        """sdf: (...) -> sigma (...) >= 0, VolSDF's Laplace density (docs/method.md 5.4).

        ``beta`` (scalar or broadcastable) overrides the learned one.
        """
        return self.laplace(sdf, beta)

    @property
    def beta(self) -> Tensor:
        """() current Laplace scale beta = |beta_param| + beta_min (docs/method.md 5.4)."""
        return self.laplace.get_beta()

    @property
    def beta_min(self) -> float:
        """Floor of beta; set it each step from `beta_schedule` to anneal."""
        return self.laplace.beta_min

    @beta_min.setter
    def beta_min(self, value: float) -> None:
        if not (value > 0 and math.isfinite(value)):
            raise ValueError(f"beta_min must be a positive finite number, got {value}")
        self.laplace.beta_min = float(value)
