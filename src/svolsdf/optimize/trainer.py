"""The S-VolSDF optimization loop (docs/method.md 4): RGB + eikonal + GCE weight loss + sparsity
loss.

One step (docs/method.md 4.6): one random input view, ``rays`` random pixels, samples along the rays
(error-bounded sampler, docs/method.md 5.4, or the MVS-guided sampler of the fast preset), volume
rendering, the soft-consistency label P' at the same samples (docs/method.md 3), the losses of
`svolsdf.optimize.losses`, Adam, global-norm clipping and a NaN-safe update. Checkpoints every N
steps make a killed run resume where it stopped.

The parts of a step are labelled for ``torch.profiler`` (``record_function("svolsdf.<part>")``;
without an active profiler a label does nothing): grid_growth, rays, sampling, render, losses,
eikonal, backward, clip and optimizer, inside ``svolsdf.train_step``. The grid field, the
compositing and the MVS prior label their own parts wherever they are called (sdf_lookup,
feature_lookup, colour_mlp, composite, prior_lookup). ``benchmarks/profile_fast.py`` reads them.
"""

from __future__ import annotations

import csv
import logging
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor
from torch.profiler import record_function

from svolsdf.config import TrainConfig
from svolsdf.errors import raise_if_interrupted
from svolsdf.field.base import SurfaceModel
from svolsdf.field.saved import field_state, load_field, read_field
from svolsdf.optimize import losses as L
from svolsdf.optimize.modes import ABLATIONS, supervised_by_mvs_depth, uses_prior
from svolsdf.render.rays import RayBundle, rays_from_cameras
from svolsdf.render.volume import render_rays
from svolsdf.scene.cameras import Cameras

__all__ = ["Trainer", "TrainData", "distinct_pixels"]

log = logging.getLogger(__name__)

@dataclass
class TrainData:
    """What the optimization sees of the scene, in the unit frame.

    Attributes:
        images: (V, 3, H, W) input views in [0, 1].
        cameras: unit-frame `Cameras` of the V views (``Scene.cameras_unit``).
        near_far: (V, 2) z-depth range per view in unit-frame units (rays are clipped to it,
            padded), or None for the whole bounding sphere.
        mvs_depth: (V, H, W) filtered MVS z-depth in unit-frame units (0 = none), used by the
            "mse" and "no-prob-volume" ablations.
        focus: (V, H, W) bool pixels where ``TrainConfig.object_ray_fraction`` of the rays are
            drawn (the dilated object masks), or None.
    """

    images: Tensor
    cameras: Cameras
    near_far: Tensor | None = None
    mvs_depth: Tensor | None = None
    focus: Tensor | None = None


def distinct_pixels(count: int, n: int, generator: torch.Generator | None = None,
                    device=None) -> Tensor:
    """(min(n, count),) distinct pixel indices in [0, count), uniform over the subsets (as
    ``randperm(count)[:n]``, docs/method.md 4.6): n draws with replacement, the repeated ones
    drawn again until none is left, in increasing order. A step's 512 of 442k pixels repeat
    about once in three steps, so this costs the draws, not a permutation of every pixel."""
    n = min(n, count)
    if 4 * n > count:  # a large share of the pixels: the permutation is as cheap
        return torch.randperm(count, generator=generator, device=device)[:n]
    pix = torch.unique(torch.randint(count, (n,), generator=generator, device=device))
    while len(pix) < n:
        more = torch.randint(count, (n - len(pix),), generator=generator, device=device)
        pix = torch.unique(torch.cat([pix, more]))
    return pix


class Trainer:
    """Fits a `SurfaceModel` to the input views under the MVS prior.

    Args:
        model: the field (unit frame).
        data: `TrainData`.
        cfg: `TrainConfig` (steps, rays, learning rates, loss weights, mode, ablation).
        prior: `svolsdf.prior.consistency.MVSPrior` over the stage-1 volumes of the same views
            (same order), or None (mode ``volsdf``).
        sampler: ``sampler(model, rays, training) -> SamplerOutput``.
        out_dir: where checkpoints and the loss log go (None: nowhere).
        device: torch device.
    """

    def __init__(self, model: SurfaceModel, data: TrainData, cfg: TrainConfig, prior=None,
                 sampler=None, out_dir: str | Path | None = None, device="cpu",
                 grid_schedule: list[tuple[int, int]] | None = None):
        if cfg.ablation not in ABLATIONS:
            raise ValueError(f"unknown ablation {cfg.ablation!r} (choose from {ABLATIONS[1:]})")
        if uses_prior(cfg) and prior is None and not supervised_by_mvs_depth(cfg):
            raise ValueError("mode svolsdf needs an MVS prior")
        self.model = model.to(device)
        self.device = torch.device(device)
        self.cfg = cfg
        self.prior = prior
        self.sampler = sampler
        self.images = data.images.to(self.device)
        self.cameras = data.cameras.to(self.device, dtype=torch.float32)
        self.near_far = None if data.near_far is None else data.near_far.to(self.device).float()
        self.mvs_depth = None if data.mvs_depth is None else data.mvs_depth.to(self.device)
        V, _, H, W = self.images.shape
        self.V, self.H, self.W = V, H, W
        # pixel indices (into H*W) of each view's focus region, padded: (V, max count), (V,)
        self.focus_index = self.focus_count = None
        if cfg.colour_steps > 0 and model.colour_parameters() is None:
            raise ValueError("train.colour_steps needs a field whose colour trains alone "
                             "(colour_parameters: the grid field)")
        if data.focus is not None and (cfg.object_ray_fraction > 0 or cfg.colour_steps > 0):
            if tuple(data.focus.shape) != (V, H, W):
                raise ValueError(f"TrainData.focus is {tuple(data.focus.shape)}, expected "
                                 f"{(V, H, W)}")
            flat = data.focus.reshape(V, -1).bool()
            count = flat.sum(1)
            if bool((count > 0).all()):
                idx = torch.zeros(V, int(count.max()), dtype=torch.long)
                for v in range(V):
                    idx[v, :count[v]] = flat[v].nonzero()[:, 0]
                self.focus_index = idx.to(self.device)
                self.focus_count = count.to(self.device)
            else:
                log.warning("object_ray_fraction: view(s) %s have an empty object mask; every "
                            "ray is drawn uniformly", (count == 0).nonzero()[:, 0].tolist())
        self.smoothed = None
        if uses_prior(cfg) and cfg.sparse_weight > 0 and cfg.anneal_rgb > 0:
            # docs/method.md 4.4: heavily smoothed targets for the first anneal_rgb steps
            self.smoothed = L.warmup_rgb_target(self.images)
        self.grid_schedule = sorted(grid_schedule or [])
        self._surface_frozen = False  # colour steps (`_freeze_surface`)
        self.step = 0
        self.out_dir = Path(out_dir) if out_dir is not None else None
        # on the training device: the view and pixel draws never leave it (no host copy and no
        # host read inside a step; a blocking host-to-device copy synchronises CUDA)
        self.generator = torch.Generator(device=self.device).manual_seed(cfg.seed)
        self._build_optimizer()
        self.history: list[dict] = []
        # the NaN-safe update (`_safe_clip`), the step's pixels, the colour only where it counts
        # (train.colour_min_weight) and the prior's sources only where P_ref counts
        # (`MVSPrior.label`) read sizes or flags on the host where that costs nothing
        self.host_branch = torch.device(self.device).type == "cpu"
        if prior is not None:
            prior.prior_floor = cfg.prior_floor  # (the sampler reads the same prior)

    # ------------------------------------------------------------------ setup
    def _build_optimizer(self) -> None:
        # the field's groups and rates (`SurfaceModel.get_param_groups`: the grid's SDF grid
        # apart at its own small rate)
        groups = self.model.get_param_groups(self.cfg)
        # docs/method.md 4.6: Adam, default betas, constant learning rate. The fused kernel does the
        # same update in one pass per tensor: on the fast preset's dense grids (~11 M
        # parameters) it measured ~6x faster than the per-tensor loop on the CPU, 1.36x on a
        # whole step (benchmarks/results/history/train_step_speed.md).
        fused = all(p.device.type in ("cpu", "cuda") and p.dtype.is_floating_point
                    for g in groups for p in g["params"])
        self.optimizer = torch.optim.Adam(groups, fused=fused or None)

    def _maybe_grow_grid(self) -> None:
        for at_step, res in self.grid_schedule:
            if self.step == at_step:
                with record_function("svolsdf.grid_growth"):
                    grown = self.model.grow(res)
                    if grown:
                        self._build_optimizer()
                if grown:
                    log.info("grid grown to %d at step %d", res, self.step)

    # ------------------------------------------------------------------ rays
    def sample_rays(self, n: int, focus_share: float | None = None
                    ) -> tuple[RayBundle, Tensor, Tensor]:
        """n random pixels of one random view (docs/method.md 4.6), drawn on the device; a share
        ``focus_share`` (default ``object_ray_fraction``) inside the view's focus region.

        Returns:
            rays (R,), pixel index (R,) long into H*W, view index (1,) long (a 1-element
            tensor, not 0-dim: indexing with a 0-dim tensor reads it on the host).
        """
        t = torch.randint(self.V, (1,), generator=self.generator, device=self.device)
        n_focus = 0
        if self.focus_index is not None:
            share = self.cfg.object_ray_fraction if focus_share is None else focus_share
            n_focus = min(n, int(round(share * n)))
        if self.host_branch:  # (unique's size is read on the host)
            pix = distinct_pixels(self.H * self.W, n - n_focus, self.generator, self.device)
        else:
            pix = torch.randperm(self.H * self.W, generator=self.generator,
                                 device=self.device)[:n - n_focus]
        if n_focus:  # uniform inside the view's dilated object mask (with replacement)
            r = torch.rand(n_focus, generator=self.generator, device=self.device)
            k = (r * self.focus_count[t]).long().clamp_max(self.focus_count[t] - 1)
            pix = torch.cat([self.focus_index[t, k], pix])
        uv = torch.stack([pix % self.W, pix // self.W], dim=-1).float()
        rays = self.make_rays(t, uv)
        return rays, pix, t

    def make_rays(self, t: int | Tensor, uv: Tensor) -> RayBundle:
        """Rays of view t (an int or a (1,) long tensor) through pixels uv (R, 2), clipped to
        the view's depth range (only the near bound with a background model: the foreground
        then ends at the bounding sphere, docs/method.md 5.5)."""
        radius = float(self.model.radius)
        R = uv.shape[0]
        view = (torch.full((R,), t, device=self.device) if isinstance(t, int)
                else t.reshape(1).expand(R))
        rays = rays_from_cameras(self.cameras, view, uv, radius=radius, near=1e-4,
                                 far_mode="sphere")
        if self.near_far is not None:
            near = self.near_far[t, 0] / rays.cos
            rays.near = torch.maximum(rays.near, near)
            far = rays.far if self.background is not None else torch.minimum(
                rays.far, self.near_far[t, 1] / rays.cos)
            rays.far = torch.maximum(far, rays.near + 1e-3)
        return rays

    @property
    def background(self):
        """The model's background (``model.background``, docs/method.md 5.5) or None."""
        return self.model.get_background()

    # ------------------------------------------------------------------ one step
    def losses(self) -> dict[str, Tensor]:
        """One batch -> dict of loss terms and "total" (docs/method.md 4.6)."""
        cfg = self.cfg
        model = self.model
        # the shortcuts that read sizes on the host (the colour where it counts, the prior's
        # sources where P_ref counts) only where that costs nothing (host_branch: the CPU)
        host = self.host_branch
        if self.prior is not None:
            self.prior.host_reads = host
        with record_function("svolsdf.rays"):
            rays, pix, t = self.sample_rays(cfg.rays)
        with record_function("svolsdf.sampling"):
            s = self.sampler(model, rays, training=True)
        with record_function("svolsdf.render"):
            out = render_rays(model, rays, s.z, background=self.background, create_graph=True,
                              colour_min_weight=cfg.colour_min_weight if host else 0.0)
        R = len(rays)
        target = self.images[t].reshape(3, -1)[:, pix].T  # (R, 3)
        terms: dict[str, Tensor] = {}

        # labels P' (docs/method.md 3) or an ablation's replacement
        p_label = None
        if uses_prior(cfg):
            if supervised_by_mvs_depth(cfg):
                mvs_d = self.mvs_depth[t].reshape(-1)[pix]
                if cfg.ablation == "no-prob-volume":
                    p_label = L.onehot_label(out.z, mvs_d, rays.cos)
            else:  # (MVSPrior.label labels itself svolsdf.prior_lookup)
                # P' = P_ref * sum_j P_src^j (docs/method.md 3)
                p_label = self.prior.label(out.points, rays.view)

        with record_function("svolsdf.losses"):
            warm = self.smoothed is not None and self.step < cfg.anneal_rgb
            if warm:
                # docs/method.md 4.4: smoothed target during the warm-up
                tgt = self.smoothed[t].reshape(3, -1)[:, pix].T
                mask = None
                if p_label is not None:
                    rule = "released" if cfg.warmup_mask_supervised else "all"
                    mask = L.warmup_ray_mask(p_label, rule=rule)
                terms["rgb"] = L.rgb_l1_loss(out.rgb, tgt, mask)
            else:
                terms["rgb"] = L.rgb_l1_loss(out.rgb, target)

        with record_function("svolsdf.eikonal"):
            # eikonal (docs/method.md 4.5): R uniform points in the box + one sample per ray
            lo, hi = self._eikonal_box()
            u = torch.rand(R, 3, device=self.device) * (hi - lo) + lo
            # the raw field, without the sphere clamp (docs/method.md 4.5)
            _, g_u = model.sdf_grad(u, create_graph=True, clamp=False)
            g_all = torch.cat([g_u, out.grad[torch.arange(R, device=self.device),
                                             s.eik_index.clamp_max(out.grad.shape[1] - 1)]], 0)
            terms["eikonal"] = L.eikonal_loss(g_all)

        with record_function("svolsdf.losses"):
            total = cfg.rgb_weight * terms["rgb"] + cfg.eikonal_weight * terms["eikonal"]
            if uses_prior(cfg):
                if cfg.ablation == "mse":
                    valid = mvs_d > 0
                    terms["mvs"] = L.depth_mse_loss(out.depth, mvs_d, valid)
                else:
                    q = 0.0 if cfg.ablation == "ce" else cfg.gce_q
                    terms["mvs"] = L.gce_weight_loss(out.weights, p_label, q=q,
                                                     form=cfg.gce_form)
                total = total + cfg.mvs_weight * terms["mvs"]
                if p_label is not None and cfg.sparse_weight > 0 and self.step < cfg.anneal_rgb:
                    w_sp = L.sparse_weight_at(self.step, cfg.sparse_weight, cfg.anneal_rgb,
                                              "linear" if cfg.sparse_decay else "constant")
                    # depth over the foreground and the T_bg-scaled background
                    # (docs/method.md 5.5)
                    terms["sparse"] = L.sparse_loss(out.depth_all, p_label,
                                                    normalize=cfg.sparse_norm)
                    total = total + w_sp * terms["sparse"]
            for name, weight, loss in model.extra_losses(cfg):  # the field's own terms
                terms[name] = loss
                total = total + weight * loss
            terms["total"] = total
            terms["psnr"] = -10.0 * torch.log10(((out.rgb.detach() - target) ** 2).mean()
                                                + 1e-10)
        return terms

    def _eikonal_box(self) -> tuple[Tensor, Tensor]:
        b = self.model.sample_box(self.device)
        return b[0].to(self.device), b[1].to(self.device)

    def _anneal_beta(self) -> None:
        """TrainConfig.beta_start > 0: beta follows a log-linear anneal instead of being learned."""
        cfg = self.cfg
        lap = self.model.laplace_density()
        if cfg.beta_start <= 0 or lap is None:
            return
        t = min(self.step / max(cfg.steps, 1), 1.0)
        beta = cfg.beta_start * (cfg.beta_end / cfg.beta_start) ** t
        lap.beta_param.requires_grad_(False)
        lap.beta_param.data.fill_(max(beta - lap.beta_min, 0.0))

    def colour_losses(self) -> dict[str, Tensor]:
        """One batch of a colour step (``train.colour_steps``): ``colour_rays`` rays, a share
        ``colour_object_fraction`` in the object, the frozen surface's weights and the colour's
        L1 loss (docs/method.md 4.1); no eikonal, prior or sparsity term."""
        cfg = self.cfg
        rays, pix, t = self.sample_rays(cfg.colour_rays, cfg.colour_object_fraction)
        with torch.no_grad():
            s = self.sampler(self.model, rays, training=False)
        out = render_rays(self.model, rays, s.z, background=self.background, create_graph=False,
                          colour_min_weight=max(cfg.colour_min_weight, 1e-4))
        target = self.images[t].reshape(3, -1)[:, pix].T
        rgb = L.rgb_l1_loss(out.rgb, target)
        psnr = -10.0 * torch.log10(((out.rgb.detach() - target) ** 2).mean() + 1e-10)
        return {"colour_rgb": rgb, "total": cfg.rgb_weight * rgb, "psnr": psnr}

    def _freeze_surface(self, frozen: bool) -> None:
        """Colour steps: only `colour_parameters` keep ``requires_grad`` (``frozen``), or every
        parameter again (the model leaves the trainer as it came)."""
        keep = {id(p) for p in self.model.colour_parameters()} if frozen else None
        for p in self.model.parameters():
            p.requires_grad_(keep is None or id(p) in keep)
        self._surface_frozen = frozen

    def train_step(self) -> dict[str, Tensor]:
        """One optimization step; returns the (detached) loss terms. Steps from ``steps`` on
        are colour steps (`colour_losses`)."""
        with record_function("svolsdf.train_step"):
            colour = self.cfg.colour_steps > 0 and self.step >= self.cfg.steps
            self._maybe_grow_grid()
            if not colour:  # colour steps keep the surface's last beta, as its density
                self._anneal_beta()
            self.model.train()
            self.model.before_step()  # (the grid field reuses its dense gradients' memory)
            self.optimizer.zero_grad(set_to_none=True)
            if colour != self._surface_frozen:
                self._freeze_surface(colour)
            terms = self.colour_losses() if colour else self.losses()
            with record_function("svolsdf.backward"):
                terms["total"].backward()
            params = [p for p in self.model.parameters() if p.grad is not None]
            if params:
                with record_function("svolsdf.clip"):
                    self._safe_clip(params)
                with record_function("svolsdf.optimizer"):
                    self.optimizer.step()
            self.step += 1
        return {k: v.detach() for k, v in terms.items()}

    def _safe_clip(self, params: list[Tensor]) -> None:
        """NaN-safe update (docs/method.md 4.6 / 9.2.8): zero every gradient if any is non-finite,
        else clip their global norm to ``grad_clip`` (if > 0).

        The global norm is non-finite exactly when some gradient is (or when finite gradients
        are so large that their norm overflows, which is treated the same), so one pass over
        the gradients decides both. With ``host_branch`` (the default on the CPU, where reading a
        value is free) the decision is a Python branch; otherwise the flag stays on the device
        and multiplies the gradients (no device-host sync per step).
        """
        grads = [p.grad for p in params]
        total = torch.nn.utils.get_total_norm(grads)
        clip = self.cfg.grad_clip
        if self.host_branch:
            if not bool(torch.isfinite(total)):
                for g in grads:
                    g.zero_()
            elif clip > 0:
                torch.nn.utils.clip_grads_with_norm_(params, clip, total)
            return
        finite = torch.isfinite(total)
        for g in grads:
            g.nan_to_num_(0.0, 0.0, 0.0).mul_(finite)
        if clip > 0:  # zeroed gradients have norm 0 (the clip factor is then 1)
            torch.nn.utils.clip_grads_with_norm_(
                params, clip, torch.where(finite, total, torch.zeros_like(total)))

    # ------------------------------------------------------------------ loop
    def fit(self, steps: int | None = None, progress: bool = True, log_every: int = 10,
            on_checkpoint=None, on_step=None) -> list[dict]:
        """Run until ``steps`` (default cfg.steps + cfg.colour_steps) total steps,
        checkpointing as configured; ``on_step(step)`` after every step (surface snapshots)."""
        from tqdm.auto import tqdm

        steps = self.cfg.steps + self.cfg.colour_steps if steps is None else steps
        bar = tqdm(total=steps, initial=self.step, disable=not progress, desc="optimize",
                   dynamic_ncols=True)
        board = self._tensorboard()
        t0 = time.perf_counter()
        s0 = self.step
        stopped = False
        try:
            while self.step < steps:
                terms = self.train_step()
                bar.update(1)
                if self.step % log_every == 0 or self.step == steps:
                    # one device read per logged step (train_step itself never reads)
                    vals = torch.stack([v.float().reshape(()) for v in terms.values()]
                                       + [torch.as_tensor(self.model.beta).detach().float()
                                          .reshape(()).to(self.device)]).tolist()
                    row = {"step": self.step, **dict(zip(terms, vals[:-1], strict=True)),
                           "beta": vals[-1]}
                    rate = (self.step - s0) / max(time.perf_counter() - t0, 1e-9)
                    row["steps_per_s"] = rate
                    self.history.append(row)
                    if board is not None:  # live curves: tensorboard --logdir OUT/field
                        for k, v in row.items():
                            if k != "step" and math.isfinite(v):
                                board.add_scalar(f"train/{k}", v, self.step)
                    bar.set_postfix({k: f"{row[k]:.3g}" for k in
                                     ("rgb", "eikonal", "mvs", "sparse", "psnr") if k in row}
                                    | {"it/s": f"{rate:.2f}"})
                    if not math.isfinite(row["total"]):
                        log.warning("non-finite loss at step %d (update skipped)", self.step)
                if self.out_dir is not None and self.cfg.checkpoint_every > 0 \
                        and self.step % self.cfg.checkpoint_every == 0 and self.step < steps:
                    self.save_checkpoint()
                    if on_checkpoint is not None:
                        on_checkpoint(self.step)
                if on_step is not None:
                    on_step(self.step)
        except KeyboardInterrupt:
            stopped = True
            raise
        finally:
            bar.close()
            if board is not None:
                board.close()
            if self._surface_frozen:
                self._freeze_surface(False)
            if self.out_dir is not None:  # Ctrl-C: the CSV, not seconds of plotting
                self.write_log(plot=not stopped)
        return self.history

    def _tensorboard(self):
        """A TensorBoard writer into ``out_dir/tensorboard`` when the ``tensorboard`` package is
        installed (the ``tensorboard`` extra) and the trainer writes files; else None, and the
        curves are losses.csv alone (`write_log`)."""
        if self.out_dir is None:
            return None
        try:
            from torch.utils.tensorboard import SummaryWriter
        except ImportError:
            raise_if_interrupted()  # an import Ctrl-C stopped is no missing package
            log.debug("tensorboard is not installed: loss curves in losses.csv only")
            return None
        return SummaryWriter(log_dir=str(self.out_dir / "tensorboard"), purge_step=self.step)

    # ------------------------------------------------------------------ checkpoints
    def checkpoint_path(self) -> Path:
        return self.out_dir / "checkpoint.pt"

    def save_checkpoint(self, path: str | Path | None = None) -> Path:
        """Write model, optimizer, step and RNG state atomically."""
        path = Path(path) if path is not None else self.checkpoint_path()
        path.parent.mkdir(parents=True, exist_ok=True)
        state = {
            **field_state(self.model),
            "optimizer": self.optimizer.state_dict(),
            "iter_step": self.step,
            "generator": self.generator.get_state(),
            "torch_rng": torch.get_rng_state(),
            "cuda_rng": torch.cuda.get_rng_state(self.device)
            if self.device.type == "cuda" else None,
            "history": self.history,
        }
        tmp = path.with_suffix(".tmp")
        torch.save(state, tmp)
        os.replace(tmp, path)
        self.write_log()
        return path

    def load_checkpoint(self, path: str | Path | None = None) -> bool:
        """Resume from a checkpoint if it exists; returns whether one was loaded."""
        path = Path(path) if path is not None else self.checkpoint_path()
        if not path.is_file():
            return False
        state = read_field(path, map_location=self.device)
        before = [id(q) for q in self.model.parameters()]
        load_field(self.model, state)
        if [id(q) for q in self.model.parameters()] != before:
            # the grid field took the checkpoint's (grown, or other-box) grid shapes
            self._build_optimizer()
        try:
            self.optimizer.load_state_dict(state["optimizer"])
        except ValueError:  # parameter groups changed (grid grown): fresh moments
            log.info("optimizer state not restored (parameter groups changed)")
        self.step = int(state["iter_step"])
        # RNG states must be CPU byte tensors (map_location moved them to the device)
        self.generator.set_state(state["generator"].cpu())
        torch.set_rng_state(state["torch_rng"].cpu())
        if state.get("cuda_rng") is not None and self.device.type == "cuda":
            torch.cuda.set_rng_state(state["cuda_rng"].cpu(), self.device)
        self.history = list(state.get("history", []))
        log.info("resumed from %s at step %d", path, self.step)
        return True

    def write_log(self, plot: bool = True) -> None:
        """Loss curves as CSV (and, with ``plot``, a PNG plot) in out_dir."""
        if not self.history or self.out_dir is None:
            return
        self.out_dir.mkdir(parents=True, exist_ok=True)
        keys = sorted({k for row in self.history for k in row}, key=lambda k: (k != "step", k))
        tmp = self.out_dir / "losses.csv.tmp"
        with open(tmp, "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=keys)
            w.writeheader()
            for row in self.history:
                w.writerow(row)
        os.replace(tmp, self.out_dir / "losses.csv")
        if not plot:
            return
        try:
            import matplotlib

            matplotlib.use("Agg")
            import matplotlib.pyplot as plt

            fig, ax = plt.subplots(figsize=(7, 4))
            steps = [r["step"] for r in self.history]
            for k in ("total", "rgb", "eikonal", "mvs", "sparse"):
                ys = [r.get(k) for r in self.history]
                if any(y is not None for y in ys):
                    ax.plot(steps, [y if y is not None else float("nan") for y in ys], label=k)
            ax.set_yscale("log")
            ax.set_xlabel("step")
            ax.legend()
            fig.tight_layout()
            fig.savefig(self.out_dir / "losses.png", dpi=80)
            plt.close(fig)
        except Exception as e:  # plotting is a convenience; never fail a run on it
            raise_if_interrupted()
            log.debug("loss plot failed: %s", e)
