"""The paper's surface model: VolSDF's SDF MLP, Laplace density and IDR colour network.

docs/method.md 5.1-5.4 (``ImplicitNetwork``, ``RenderingNetwork`` mode "idr", ``LaplaceDensity``).
The SDF is > 0 outside; see :mod:`svolsdf.field.density` for the density's sign convention.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch
from torch import Tensor, nn
from torch.nn.utils.parametrizations import weight_norm

from svolsdf.field.base import SurfaceModel
from svolsdf.field.density import LaplaceDensity
from svolsdf.field.embedding import PositionalEncoding

__all__ = ["VolSDFFieldConfig", "SDFNetwork", "IDRRenderingNetwork", "VolSDFField"]


@dataclass
class VolSDFFieldConfig:
    """Constants of the paper preset's field (docs/method.md 5.2-5.4)."""

    mlp_depth: int = 8
    """Number of hidden layers of width ``mlp_width`` in the SDF MLP (paper: 8;
    ``field.mlp_depth``)."""
    mlp_width: int = 256
    """Hidden width of the SDF MLP, and of the colour network unless ``render_hidden`` says
    otherwise (paper: 256; ``field.mlp_width``)."""
    multires: int = 6
    """Positional-encoding frequencies of the SDF input (paper: 6, giving 39 channels)."""
    skip_in: tuple[int, ...] = (4,)
    """Layers whose input is concat(h, gamma(x)) / sqrt(2) (paper: layer 4)."""
    feature_dim: int = 256
    """Size of the geometry feature passed to the colour network (paper: 256)."""
    geometric_init: bool = True
    """IDR geometric initialisation so that the SDF starts as ~ |x| - bias (docs/method.md 5.2)."""
    bias: float = 0.6
    """Radius of the initial sphere of the geometric init (paper: 0.6)."""
    softplus_beta: float = 100.0
    """Sharpness of the Softplus activations (paper: 100)."""
    use_weight_norm: bool = True
    """Weight normalisation on every linear layer of both networks (paper: on)."""
    sphere_clamp: bool = True
    """Clamp sdf <- min(sdf, sphere_scale (radius - |x|)) (paper: on for DTU, off when a
    background model is used)."""
    sphere_scale: float = 20.0
    """Slope of the sphere clamp (paper: 20)."""
    radius: float = 3.0
    """Bounding-sphere radius of the unit frame (paper: 3)."""
    multires_view: int = 1
    """Positional-encoding frequencies of the view direction (S-VolSDF: 1; VolSDF: 4)."""
    render_layers: int = 4
    """Hidden layers of the IDR colour network (paper: 4)."""
    render_hidden: int | None = None
    """Hidden width of the IDR colour network; None: ``mlp_width`` (paper: 256 both)."""
    beta_init: float = 0.1
    """Initial Laplace beta_param (paper: 0.1)."""
    beta_min: float = 1e-4
    """beta = |beta_param| + beta_min (paper: 1e-4)."""
    extra: dict = field(default_factory=dict)
    """Unused; reserved so that configs written by later versions still load."""

    @classmethod
    def from_config(cls, field) -> VolSDFFieldConfig:
        """The paper's field for a run's field section ``field`` (a
        `svolsdf.config.FieldConfig`): ``mlp_depth`` x ``mlp_width``, the sphere clamp off
        under a ``background`` model (docs/method.md 5.5), the paper's constants otherwise."""
        return cls(mlp_depth=field.mlp_depth, mlp_width=field.mlp_width,
                   sphere_clamp=not field.background)


def _maybe_wn(lin: nn.Linear, on: bool) -> nn.Module:
    return weight_norm(lin) if on else lin


class SDFNetwork(nn.Module):
    """IDR/VolSDF ``ImplicitNetwork`` (docs/method.md 5.2): gamma(x) -> [sdf, feature].

    Layer widths [d_emb, H x n_layers, 1 + F]; a layer in ``skip_in`` takes
    concat(h, gamma(x)) / sqrt(2), so the layer before it outputs H - d_emb channels.
    Softplus(beta) after every layer but the last.
    """

    def __init__(
        self,
        d_in: int = 3,
        d_out: int = 1,
        feature_dim: int = 256,
        d_hidden: int = 256,
        n_layers: int = 8,
        skip_in: tuple[int, ...] = (4,),
        multires: int = 6,
        geometric_init: bool = True,
        bias: float = 0.6,
        softplus_beta: float = 100.0,
        use_weight_norm: bool = True,
        abs_first: bool = False,
    ):
        super().__init__()
        self.embed = PositionalEncoding(d_in, multires)
        d_emb = self.embed.out_dim
        dims = [d_emb] + [d_hidden] * n_layers + [d_out + feature_dim]
        self.d_in, self.d_out, self.feature_dim = d_in, d_out, feature_dim
        self.skip_in = tuple(skip_in)
        self.num_linear = len(dims) - 1
        for s in self.skip_in:
            # a hidden layer: the geometric init's last layer sums hidden units into ~|x|, and
            # gamma(x) entering there would add its sin/cos (an MLP of 4 hidden layers with the
            # skip at 4 started with |grad| ~ 9, not VolSDF's sphere)
            if not 1 <= s < self.num_linear - 1 or d_hidden <= d_emb:
                raise ValueError(
                    f"SDFNetwork: skip layer {s} needs 1 <= skip < {self.num_linear - 1} (a "
                    f"hidden layer) and d_hidden ({d_hidden}) > embedding size ({d_emb})"
                )
        layers = []
        for i in range(self.num_linear):
            out_dim = dims[i + 1] - d_emb if (i + 1) in self.skip_in else dims[i + 1]
            lin = nn.Linear(dims[i], out_dim)
            if geometric_init:
                self._geometric_init(lin, i, dims, out_dim, d_emb, d_in, multires, bias)
            layers.append(_maybe_wn(lin, use_weight_norm))
        self.layers = nn.ModuleList(layers)
        self.act = nn.Softplus(beta=softplus_beta)

    def _geometric_init(self, lin, i, dims, out_dim, d_emb, d_in, multires, bias):
        """docs/method.md 5.2 (IDR, Atzmon & Lipman SAL): the network starts as ~ |x| - bias."""
        with torch.no_grad():
            std = math.sqrt(2.0) / math.sqrt(out_dim)
            if i == self.num_linear - 1:
                nn.init.normal_(lin.weight, mean=math.sqrt(math.pi) / math.sqrt(dims[i]), std=1e-4)
                nn.init.constant_(lin.bias, -bias)
            elif multires > 0 and i == 0:
                nn.init.constant_(lin.bias, 0.0)
                nn.init.constant_(lin.weight[:, d_in:], 0.0)  # sin/cos columns
                nn.init.normal_(lin.weight[:, :d_in], 0.0, std)
            elif multires > 0 and i in self.skip_in:
                nn.init.constant_(lin.bias, 0.0)
                nn.init.normal_(lin.weight, 0.0, std)
                nn.init.constant_(lin.weight[:, -(d_emb - d_in):], 0.0)  # gamma(x)'s sin/cos
            else:
                nn.init.constant_(lin.bias, 0.0)
                nn.init.normal_(lin.weight, 0.0, std)

    def forward(self, x: Tensor) -> Tensor:
        """x: (N, d_in) -> (N, d_out + feature_dim); column 0 is the raw (unclamped) SDF."""
        inp = self.embed(x)
        h = inp
        for i, lin in enumerate(self.layers):
            if i in self.skip_in:
                h = torch.cat([h, inp], dim=-1) / math.sqrt(2.0)
            h = lin(h)
            if i < self.num_linear - 1:
                h = self.act(h)
        return h


class IDRRenderingNetwork(nn.Module):
    """IDR colour network, mode "idr" (docs/method.md 5.3).

    Input [x (3), gamma_L(view_dir) (3 + 6L), grad sdf (3, unnormalised), feature (F)]
    (271 channels for L = 1, F = 256) -> ReLU MLP -> sigmoid rgb.
    """

    def __init__(
        self,
        feature_dim: int = 256,
        d_hidden: int = 256,
        n_layers: int = 4,
        multires_view: int = 1,
        use_weight_norm: bool = True,
    ):
        super().__init__()
        self.embed_view = PositionalEncoding(3, multires_view)
        d_in = 3 + self.embed_view.out_dim + 3 + feature_dim
        dims = [d_in] + [d_hidden] * n_layers + [3]
        self.d_in = d_in
        self.layers = nn.ModuleList(
            _maybe_wn(nn.Linear(dims[i], dims[i + 1]), use_weight_norm)
            for i in range(len(dims) - 1)
        )

    def forward(self, x: Tensor, view_dir: Tensor, normal: Tensor, feature: Tensor) -> Tensor:
        """x, view_dir, normal: (N, 3), feature: (N, F) -> rgb (N, 3) in (0, 1)."""
        h = torch.cat([x, self.embed_view(view_dir), normal, feature], dim=-1)
        for i, lin in enumerate(self.layers):
            h = lin(h)
            if i < len(self.layers) - 1:
                h = torch.relu(h)
        return torch.sigmoid(h)


class VolSDFField(SurfaceModel):
    """The paper preset's :class:`SurfaceModel` (docs/method.md 5.2-5.4).

    Example:
        >>> m = VolSDFField(VolSDFFieldConfig(mlp_depth=2, mlp_width=64, skip_in=()))
        >>> sdf, grad, feat = m.sdf_and_grad(torch.zeros(5, 3), create_graph=False)
        >>> sdf.shape, grad.shape, feat.shape
        (torch.Size([5]), torch.Size([5, 3]), torch.Size([5, 256]))
    """

    def __init__(self, config: VolSDFFieldConfig | None = None):
        super().__init__()
        c = config or VolSDFFieldConfig()
        self.config = c
        self.radius = float(c.radius)
        self.feature_dim = c.feature_dim
        self.sdf_net = SDFNetwork(
            d_in=3, d_out=1, feature_dim=c.feature_dim, d_hidden=c.mlp_width,
            n_layers=c.mlp_depth,
            skip_in=tuple(c.skip_in), multires=c.multires, geometric_init=c.geometric_init,
            bias=c.bias, softplus_beta=c.softplus_beta, use_weight_norm=c.use_weight_norm,
        )
        self.colour_net = IDRRenderingNetwork(
            feature_dim=c.feature_dim,
            d_hidden=c.mlp_width if c.render_hidden is None else c.render_hidden,
            n_layers=c.render_layers,
            multires_view=c.multires_view, use_weight_norm=c.use_weight_norm,
        )
        self.laplace = LaplaceDensity(c.beta_init, c.beta_min)

    # ------------------------------------------------------------------ geometry
    def _check(self, x: Tensor) -> None:
        if x.ndim != 2 or x.shape[-1] != 3:
            raise ValueError(f"VolSDFField: points must be (N, 3), got {tuple(x.shape)}")

    def _clamp(self, sdf: Tensor, x: Tensor) -> Tensor:
        """sdf <- min(sdf, sphere_scale (R - |x|))  (docs/method.md 5.2)."""
        if not self.config.sphere_clamp:
            return sdf
        return torch.minimum(sdf, self.config.sphere_scale * (self.radius - x.norm(dim=-1)))

    def forward(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """x: (N, 3) -> raw (unclamped) sdf (N,), feature (N, F)."""
        self._check(x)
        out = self.sdf_net(x)
        return out[:, 0], out[:, 1:]

    def sdf(self, x: Tensor, clamp: bool = True) -> Tensor:
        """x: (N, 3) -> (N,) signed distance (sphere-clamped unless ``clamp=False``)."""
        s, _ = self(x)
        return self._clamp(s, x) if clamp else s

    def sdf_and_grad(
        self, x: Tensor, create_graph: bool = True, clamp: bool = True
    ) -> tuple[Tensor, Tensor, Tensor]:
        """x: (N, 3) -> sdf (N,), d sdf / dx (N, 3), feature (N, F).

        The gradient is taken by autograd even under ``torch.no_grad()`` (grad mode is enabled
        locally). With ``create_graph=True`` (training) the gradient stays differentiable, as
        the eikonal loss and the colour network's normal input need; otherwise it is detached.
        ``clamp=False`` gives the raw MLP SDF, which the eikonal loss uses (docs/method.md 4.5).
        """
        self._check(x)
        with torch.enable_grad():
            xg = x if x.requires_grad else x.detach().requires_grad_(True)
            s, feat = self(xg)
            if clamp:
                s = self._clamp(s, xg)
            (g,) = torch.autograd.grad(
                s, xg, torch.ones_like(s), create_graph=create_graph, retain_graph=True
            )
        if not create_graph:
            g = g.detach()
        return s, g, feat

    # ------------------------------------------------------------------ appearance
    def colour(self, x: Tensor, view_dir: Tensor, normal: Tensor, feature: Tensor) -> Tensor:
        """x, view_dir (ray direction), normal (unnormalised grad sdf): (N, 3), feature (N, F)
        -> rgb (N, 3) in (0, 1)  (docs/method.md 5.3)."""
        return self.colour_net(x, view_dir, normal, feature)

    def density(self, sdf: Tensor, beta: Tensor | None = None) -> Tensor:
        """sdf: (...) -> sigma (...) (docs/method.md 5.4); ``beta`` overrides the learned scale."""
        return self.laplace(sdf, beta)

    @property
    def beta(self) -> Tensor:
        """() current Laplace beta."""
        return self.laplace.get_beta()
