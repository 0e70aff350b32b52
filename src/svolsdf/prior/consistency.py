"""Soft consistency: P'(x) = P_ref(x) * sum_{j != ref} P_src^j(x) at 3D points (docs/method.md 3).

The stage-1 probability volumes are looked up at the samples of VolSDF rays only (the released
code never builds a consistency-weighted volume). No gradients flow through this module.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor
from torch.profiler import record_function

from svolsdf.mvs.volume import ProbabilityVolume
from svolsdf.scene.cameras import Cameras
from svolsdf.scene.scene import Normalization

__all__ = ["PriorView", "MVSPrior", "consistency_depth", "p_prime", "lookup_reference"]

#: validity thresholds of docs/method.md 3 (steps 4 and 7)
_MIN_Z = 1e-5
_UV_LIMIT = 1.001
_Z_LIMIT = 1.01


def p_prime(p_ref: Tensor, p_src_sum: Tensor) -> Tensor:
    """P' = P_ref * sum_j P_src^j (docs/method.md 3, "consistency-weighted label"); (...) ->
    (...)."""
    return p_ref * p_src_sum


@dataclass
class PriorView:
    """One view's volume in the unit frame, ready for lookup.

    Attributes:
        prob: (D, H, W) probabilities.
        near: (H, W) first hypothesis depth, unit frame (depths[0] / scale).
        far: (H, W) last hypothesis depth, unit frame.
        K: (3, 3) intrinsics used to project (the volume's own, or the quirk image's).
        w2c: (4, 4) unit-frame world-to-camera.
        norm_size: (W_n, H_n) image size whose pixel range [0, W_n - 1] maps onto [-1, 1].
        inverse_depth: hypotheses uniform in inverse depth (docs/method.md 3, step 6).
    """

    prob: Tensor
    near: Tensor
    far: Tensor
    K: Tensor
    w2c: Tensor
    norm_size: tuple[int, int]
    inverse_depth: bool


def _unit_view(vol: ProbabilityVolume, norm: Normalization, align_quirk: bool,
               quirk_image_size: tuple[int, int] | None) -> PriorView:
    D, H, W = vol.prob.shape
    cams: Cameras = vol.cameras.transformed(norm.center, norm.scale)
    if align_quirk:
        # docs/method.md 3 step 3: pixels at the VolSDF image size (2x the stage-1 volume),
        # normalised with align_corners=True onto the smaller volume.
        Wi, Hi = quirk_image_size or (2 * W, 2 * H)
        cams = cams.resize(Wi, Hi)
        size = (Wi, Hi)
    else:
        size = (W, H)
    return PriorView(
        prob=vol.prob.float(),
        near=(vol.depths[0] / norm.scale).float(),
        far=(vol.depths[-1] / norm.scale).float(),
        K=cams.K[0].float(),
        w2c=cams.w2c[0].float(),
        norm_size=size,
        inverse_depth=bool(vol.inverse_depth),
    )


def _project(view: PriorView, pts: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """pts (N, 3) -> normalised u_hat, v_hat (N,), camera z (N,), image-valid (N,) (steps 1-4)."""
    pc = pts @ view.w2c[:3, :3].T + view.w2c[:3, 3]
    z = pc[:, 2]
    zs = torch.where(z.abs() < 1e-12, torch.full_like(z, 1e-12), z)
    x_t, y_t = pc[:, 0] / zs, pc[:, 1] / zs
    K = view.K
    v = y_t * K[1, 1] + K[1, 2]
    u = x_t * K[0, 0] + K[0, 2] + (v - K[1, 2]) * K[0, 1] / K[1, 1]
    Wn, Hn = view.norm_size
    uh = u / ((Wn - 1) / 2.0) - 1.0
    vh = v / ((Hn - 1) / 2.0) - 1.0
    valid = (z >= _MIN_Z) & (uh.abs() <= _UV_LIMIT) & (vh.abs() <= _UV_LIMIT)
    return uh, vh, z, valid


def _depth_coord(view: PriorView, z: Tensor, near: Tensor, far: Tensor) -> Tensor:
    """Normalised depth coordinate z_hat in [-1, 1] over the hypotheses (step 6)."""
    if view.inverse_depth:
        far = torch.where(far.abs() < 1e-8, torch.full_like(far, 1e-8), far)
        zs = torch.where(z.abs() < 1e-12, torch.full_like(z, 1e-12), z)
        return 2.0 * (1.0 - near / zs) / (1.0 - near / far) - 1.0
    return 2.0 * (z - near) / (far - near) - 1.0


class MVSPrior:
    """Soft-consistency lookup into one stage-1 volume per input view (docs/method.md 3).

    Args:
        volumes: one :class:`ProbabilityVolume` per input view, in the order of the ray
            ``ref_view`` indices (the optimization's view order).
        normalization: the scene's world <-> unit similarity.
        align_quirk: reproduce the released code's sampling (docs/method.md 3 step 3): pixel
            coordinates at ``quirk_image_size`` (default twice the volume's size), normalised
            with align_corners=True onto the volume, which drifts by up to half a cell. Default
            False: pixel centres of the volume's own camera map exactly onto its cells.
        quirk_image_size: (W, H) of the VolSDF images for ``align_quirk``.
        device: where the volumes live (default: where they are).
        sources: for each view (the volumes' order) the indices of its source views, whose
            P_src enter the sum (``train.prior_sources = selected``: the MVS's selected sources,
            `svolsdf.mvs.backbone.select_sources`); None: every other view (docs/method.md 3).
        prior_floor: `label` reads the source views only at points where P_ref exceeds it
            (0: where P_ref > 0, which leaves P' exact; the trainer sets ``train.prior_floor``).

    Example:
        >>> prior = MVSPrior(volumes, scene.normalization)            # doctest: +SKIP
        >>> p_ref, p_src, valid = prior.lookup(points, ref_view)       # doctest: +SKIP
        >>> label = p_prime(p_ref, p_src)                              # doctest: +SKIP
    """

    def __init__(self, volumes: list[ProbabilityVolume], normalization: Normalization,
                 align_quirk: bool = False, quirk_image_size: tuple[int, int] | None = None,
                 device=None, prior_floor: float = 0.0,
                 sources: list[list[int]] | None = None):
        if not volumes:
            raise ValueError("MVSPrior: no probability volumes given")
        self.align_quirk = bool(align_quirk)
        self.prior_floor = float(prior_floor)
        # `label`'s skipping reads which points pass on the host (a sync on a GPU); the
        # trainer sets False where its steps must not wait for the device
        self.host_reads = True
        self.views = [_unit_view(v.to(device) if device is not None else v, normalization,
                                 self.align_quirk, quirk_image_size) for v in volumes]
        V = len(volumes)
        # is_source[r, i]: view i's P_src enters the label of rays of view r
        self.is_source = ~torch.eye(V, dtype=torch.bool)
        if sources is not None:
            if len(sources) != V or any(not 0 <= i < V or i == r
                                        for r, s in enumerate(sources) for i in s):
                raise ValueError(f"MVSPrior: sources must list, for each of the {V} views, "
                                 f"other views' indices, got {sources}")
            self.is_source = torch.zeros(V, V, dtype=torch.bool)
            for r, s in enumerate(sources):
                self.is_source[r, list(s)] = True
        self.is_source = self.is_source.to(self.views[0].prob.device)

    def __len__(self) -> int:
        return len(self.views)

    def view_lookup(self, i: int, pts: Tensor) -> tuple[Tensor, Tensor]:
        """Probability of view i at points (steps 1-8).

        Args:
            i: view index.
            pts: (N, 3) unit-frame points.

        Returns:
            cost (N,) interpolated probability (0 where invalid), valid (N,) bool.
        """
        view = self.views[i]
        uh, vh, z, valid = _project(view, pts)
        uh = torch.where(valid, uh, torch.full_like(uh, -99.0))
        vh = torch.where(valid, vh, torch.full_like(vh, -99.0))
        grid2 = torch.stack([uh, vh], dim=-1)[None, None]  # (1, 1, N, 2)
        nf = torch.stack([view.near, view.far])[None]  # (1, 2, H, W)
        nf_s = F.grid_sample(nf, grid2, mode="bilinear", padding_mode="zeros",
                             align_corners=True)[0, :, 0]  # (2, N)
        near, far = nf_s[0], nf_s[1]
        zh = _depth_coord(view, z, near, far)
        valid = valid & (near >= _MIN_Z) & (far >= _MIN_Z) & (zh.abs() <= _Z_LIMIT)
        zh = torch.where(valid, zh, torch.full_like(zh, -99.0))
        g = torch.stack([uh, vh, zh], dim=-1)  # (N, 3)
        # grid_sample's 3-D CPU kernel parallelises over the batch only (ATen GridSampler.cpp),
        # so the points are split into one batch entry per thread over the same (expanded, not
        # copied) volume: identical values, 1.5x faster on two cores
        # (benchmarks/results/history/train_step_speed.md)
        parts = max(1, torch.get_num_threads()) if g.device.type == "cpu" else 1
        n = g.shape[0]
        m = -(-n // parts)
        if m * parts != n:
            g = torch.cat([g, g.new_full((m * parts - n, 3), -99.0)])
        D, H, W = view.prob.shape
        cost = F.grid_sample(view.prob[None, None].expand(parts, 1, D, H, W),
                             g.view(parts, 1, 1, m, 3), mode="bilinear", padding_mode="zeros",
                             align_corners=True).reshape(-1)[:n]
        return torch.where(valid, cost, torch.zeros_like(cost)), valid

    @torch.no_grad()
    def lookup(self, points: Tensor, ref_view: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """P_ref, sum of P_src and validity at ray samples (docs/method.md 3, steps 1-9).

        For each view i, the points are projected into its volume; the ray's own view gives
        P_ref, its sources (every other view unless the prior was given ``sources``) add to
        P_src_sum and OR their validity into ``valid``. P_ref is set to
        0 where no source view is valid. Views are processed in a loop, points all at once.

        Args:
            points: (R, S, 3) unit-frame sample positions.
            ref_view: (R,) long index of each ray's view into the volumes.

        Returns:
            P_ref (R, S), P_src_sum (R, S), valid (R, S) bool; no gradients.
        """
        if points.ndim != 3 or points.shape[-1] != 3:
            raise ValueError(
                f"MVSPrior.lookup: points must be (R, S, 3), got {tuple(points.shape)}"
            )
        R, S, _ = points.shape
        if ref_view.shape != (R,):
            raise ValueError(f"MVSPrior.lookup: ref_view must be (R,) = ({R},), "
                             f"got {tuple(ref_view.shape)}")
        with record_function("svolsdf.prior_lookup"):
            pts = points.detach().reshape(-1, 3).float()
            ref = ref_view.to(pts.device).long()[:, None].expand(R, S).reshape(-1)
            p_ref = torch.zeros(R * S, device=pts.device)
            p_src = torch.zeros_like(p_ref)
            valid = torch.zeros(R * S, dtype=torch.bool, device=pts.device)
            for i in range(len(self.views)):
                cost, ok = self.view_lookup(i, pts)
                is_ref = ref == i
                is_src = self.is_source[ref, i]
                p_ref = torch.where(is_ref, cost, p_ref)
                p_src = p_src + torch.where(is_src, cost, torch.zeros_like(cost))
                valid = valid | (ok & is_src)
            p_ref = torch.where(valid, p_ref, torch.zeros_like(p_ref))
            return p_ref.reshape(R, S), p_src.reshape(R, S), valid.reshape(R, S)

    @torch.no_grad()
    def label(self, points: Tensor, ref_view: Tensor) -> Tensor:
        """P' = P_ref * sum_j P_src^j at ray samples (docs/method.md 3), the ray's own view read
        first and the source views only where P_ref > ``prior_floor``: P' is left at 0 where
        P_ref <= prior_floor, which with the default 0 is P' exactly (`lookup`'s P_ref * P_src,
        bit for bit) and otherwise drops less than prior_floor * (views - 1) per point. About a
        third of a step's samples have P_ref = 0 (outside the view's frustum or depth range),
        half have P_ref < 1e-4. With ``host_reads`` False every view is read at every point
        (no data-dependent sizes: no device-host synchronisation) and P' is exact.

        Args:
            points: (R, S, 3) unit-frame sample positions.
            ref_view: (R,) long index of each ray's view into the volumes.

        Returns:
            (R, S) P', no gradients.
        """
        if points.ndim != 3 or points.shape[-1] != 3:
            raise ValueError(f"MVSPrior.label: points must be (R, S, 3), got "
                             f"{tuple(points.shape)}")
        R, S, _ = points.shape
        if ref_view.shape != (R,):
            raise ValueError(f"MVSPrior.label: ref_view must be (R,) = ({R},), "
                             f"got {tuple(ref_view.shape)}")
        if not self.host_reads:
            p_ref, p_src, _ = self.lookup(points, ref_view)
            return p_ref * p_src
        with record_function("svolsdf.prior_lookup"):
            pts = points.detach().reshape(-1, 3).float()
            ref = ref_view.to(pts.device).long()[:, None].expand(R, S).reshape(-1)
            refs = ref.unique().tolist()
            p_ref = torch.zeros(R * S, device=pts.device)
            for i in refs:
                if len(refs) == 1:
                    p_ref = self.view_lookup(i, pts)[0]
                else:
                    sel = (ref == i).nonzero()[:, 0]
                    p_ref[sel] = self.view_lookup(i, pts[sel])[0]
            idx = (p_ref > self.prior_floor).nonzero()[:, 0]
            q, rq = pts[idx], ref[idx]
            p_src = torch.zeros(len(idx), device=pts.device)
            valid = torch.zeros(len(idx), dtype=torch.bool, device=pts.device)
            for i in range(len(self.views)):
                if not bool(self.is_source[refs, i].any()):  # no ray's source
                    continue
                cost, ok = self.view_lookup(i, q)
                is_src = self.is_source[rq, i]
                p_src = p_src + torch.where(is_src, cost, torch.zeros_like(cost))
                valid = valid | (ok & is_src)
            label = torch.zeros(R * S, device=pts.device)
            label[idx] = torch.where(valid, p_ref[idx], torch.zeros_like(p_src)) * p_src
            return label.reshape(R, S)

    def p_prime(self, points: Tensor, ref_view: Tensor) -> tuple[Tensor, Tensor]:
        """(R, S, 3), (R,) -> P' (R, S) and valid (R, S)."""
        p_ref, p_src, valid = self.lookup(points, ref_view)
        return p_prime(p_ref, p_src), valid


# ---------------------------------------------------------------------- slow reference
def _bilinear_ref(img: Tensor, x: float, y: float) -> float:
    """Bilinear sample of (H, W) at pixel (x, y) with zero padding (align_corners=True)."""
    H, W = img.shape
    x0, y0 = int(torch.floor(torch.tensor(x))), int(torch.floor(torch.tensor(y)))
    out = 0.0
    for dy in (0, 1):
        for dx in (0, 1):
            xi, yi = x0 + dx, y0 + dy
            wgt = (1 - abs(x - xi)) * (1 - abs(y - yi))
            if 0 <= xi < W and 0 <= yi < H:
                out += wgt * float(img[yi, xi])
    return out


def _trilinear_ref(vol: Tensor, x: float, y: float, d: float) -> float:
    """Trilinear sample of (D, H, W) at voxel (x, y, d) with zero padding (align_corners=True)."""
    D, H, W = vol.shape
    x0 = int(torch.floor(torch.tensor(x)))
    y0 = int(torch.floor(torch.tensor(y)))
    d0 = int(torch.floor(torch.tensor(d)))
    out = 0.0
    for dd in (0, 1):
        for dy in (0, 1):
            for dx in (0, 1):
                xi, yi, di = x0 + dx, y0 + dy, d0 + dd
                wgt = (1 - abs(x - xi)) * (1 - abs(y - yi)) * (1 - abs(d - di))
                if 0 <= xi < W and 0 <= yi < H and 0 <= di < D:
                    out += wgt * float(vol[di, yi, xi])
    return out


def lookup_reference(prior: MVSPrior, points: Tensor, ref_view: Tensor
                     ) -> tuple[Tensor, Tensor, Tensor]:
    """Slow, loop-per-point twin of :meth:`MVSPrior.lookup` for tests (float64 scalar maths).

    Same inputs and outputs; interpolation written out by hand (align_corners=True maps the
    normalised coordinate c in [-1, 1] to index (c + 1) (n - 1) / 2; outside cells count 0).
    """
    R, S, _ = points.shape
    p_ref = torch.zeros(R, S, dtype=torch.float64)
    p_src = torch.zeros(R, S, dtype=torch.float64)
    valid = torch.zeros(R, S, dtype=torch.bool)
    for r in range(R):
        for s in range(S):
            x = points[r, s].double()
            for i, view in enumerate(prior.views):
                w2c, K = view.w2c.double(), view.K.double()
                pc = w2c[:3, :3] @ x + w2c[:3, 3]
                pz = float(pc[2])
                if abs(pz) < 1e-12:
                    pz = 1e-12
                xt, yt = float(pc[0]) / pz, float(pc[1]) / pz
                v = yt * float(K[1, 1]) + float(K[1, 2])
                u = xt * float(K[0, 0]) + float(K[0, 2]) + (v - float(K[1, 2])) * float(
                    K[0, 1]) / float(K[1, 1])
                Wn, Hn = view.norm_size
                uh, vh = u / ((Wn - 1) / 2) - 1, v / ((Hn - 1) / 2) - 1
                ok = float(pc[2]) >= _MIN_Z and abs(uh) <= _UV_LIMIT and abs(vh) <= _UV_LIMIT
                cost = 0.0
                if ok:
                    D, H, W = view.prob.shape
                    px, py = (uh + 1) * (W - 1) / 2, (vh + 1) * (H - 1) / 2
                    near = _bilinear_ref(view.near.double(), px, py)
                    far = _bilinear_ref(view.far.double(), px, py)
                    if view.inverse_depth:
                        far_ = far if abs(far) >= 1e-8 else 1e-8
                        zh = 2 * (1 - near / float(pc[2])) / (1 - near / far_) - 1
                    else:
                        span = far - near if far != near else 1e-30
                        zh = 2 * (float(pc[2]) - near) / span - 1
                    ok = near >= _MIN_Z and far >= _MIN_Z and abs(zh) <= _Z_LIMIT
                    if ok:
                        pd = (zh + 1) * (D - 1) / 2
                        cost = _trilinear_ref(view.prob.double(), px, py, pd)
                if i == int(ref_view[r]):
                    p_ref[r, s] = cost
                else:
                    p_src[r, s] += cost
                    valid[r, s] |= ok
            if not valid[r, s]:
                p_ref[r, s] = 0.0
    return p_ref.float(), p_src.float(), valid


def consistency_depth(volumes: list[ProbabilityVolume], norm: Normalization
                      ) -> dict[int, Tensor]:
    """The expected depth under the consistency-weighted stage-1 volume P_ref * sum P_src
    (docs/method.md 3, 9.2.3) at each input view's hypotheses: the guide depth of the ablation
    "soft-consistency-only".

    Args:
        volumes: the stage-1 volumes of the input views (hypotheses (D, H, W)).
        norm: the scene's normalization (world <-> unit frame).

    Returns:
        {view id: (H, W) world z-depth}; a pixel without consistent weight keeps the volume's
        depth.
    """
    prior = MVSPrior(volumes, norm)
    out = {}
    for i, vol in enumerate(volumes):
        D, H, W = vol.depths.shape
        cam = vol.cameras.to(dtype=torch.float64)
        uv = cam.pixel_grid(dtype=torch.float64).reshape(1, -1, 2)
        num = torch.zeros(H * W)
        den = torch.zeros(H * W)
        for k in range(D):
            X = cam.unproject(uv, vol.depths[k].double().reshape(1, -1))[0]
            pts = norm.to_unit(X).float()[:, None]
            p_ref, p_src, _ = prior.lookup(pts, torch.full((H * W,), i, dtype=torch.long))
            w = (p_ref * p_src)[:, 0]
            num += w * vol.depths[k].reshape(-1)
            den += w
        d = torch.where(den > 1e-6, num / den.clamp_min(1e-12), vol.depth.reshape(-1))
        out[vol.view_id] = d.reshape(H, W).float()
    return out
