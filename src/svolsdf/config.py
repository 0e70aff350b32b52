"""Dataclass configs for a reconstruction run, the named presets, and YAML round trips.

One `Config` describes a whole run. `svolsdf reconstruct` maps its options onto it and writes it as
OUT/config.yaml, which can be passed back with ``--config`` to rerun. Presets (ARCHITECTURE.md
"Presets"): ``paper`` reproduces METHOD.md's constants; ``fast`` (the default) keeps the prior and
the losses and changes the field, the sampling and the schedule.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
import os
import types
from collections.abc import Mapping
from dataclasses import asdict, dataclass, fields
from dataclasses import field as dc_field
from pathlib import Path
from typing import Any, Literal, Union, get_args, get_origin, get_type_hints

import yaml

from svolsdf.errors import InputError

__all__ = [
    "Config",
    "SceneConfig",
    "MVSConfig",
    "FieldConfig",
    "TrainConfig",
    "OutputConfig",
    "preset",
    "PRESETS",
    "load_config",
    "save_config",
    "apply_overrides",
    "validate_config",
]


def _limited(default: Any = dataclasses.MISSING, *, factory: Any = dataclasses.MISSING,
             **limits: Any) -> Any:
    """A dataclass field with limits that `validate_config` checks beside its type.

    Limits: ``min`` / ``max`` (inclusive) and ``gt`` (exclusive) bound a number or every item of
    a list; ``len`` / ``min_len`` the length of a list; ``unique`` forbids repeated items;
    ``choices`` is a function returning the allowed strings (for registries that can grow, where
    a ``Literal`` would be too narrow).
    """
    return dc_field(default=default, default_factory=factory, metadata={"limits": limits})


def _backbone_names() -> list[str]:
    from svolsdf.mvs.backbone import available_backbones

    return available_backbones()


#: DTU protocol input views (METHOD.md 1.4): the first num_view of this list.
DTU_TRAIN_IDS = [25, 22, 28, 40, 44, 48, 0, 8, 13]
#: DTU views never used for testing (METHOD.md 1.4).
DTU_EXCLUDED_IDS = [3, 4, 5, 6, 7, 16, 17, 18, 19, 20, 21, 36, 37, 38, 39]


@dataclass
class SceneConfig:
    path: str = ""
    """Scene folder (any format `load_scene` reads)."""
    views: list[int] | None = _limited(None, min_len=2, unique=True)
    """Input view ids (at least two, each once); default: DTU's 25 22 28 on 49-view DTU scans,
    else a central view and its two best source views."""
    num_views: int = _limited(3, min=2)
    """Number of input views when ``views`` is not given."""
    view_selection: Literal["default", "auto"] = "default"
    """How views are picked when ``views`` is not given: default (DTU's 25 22 28 on 49-view DTU
    scans, else a central view and its best source views) or auto (``--views auto``: views with
    good overlap and baselines on any calibrated scene, `svolsdf.pipeline.auto_views`)."""
    image_size: list[int] | None = _limited(None, len=2, min=8)
    """Working size [W, H] for the field; default: 768 wide (4:3 -> 768x576), never upsampled."""
    lighting: int | Literal["max"] = _limited(3, min=0, max=6)
    """DTU raw layout only: the lighting index 0..6 of the rectified images, or max."""


@dataclass
class MVSConfig:
    backbone: str = _limited("planesweep", choices=_backbone_names)
    """planesweep (training-free, default) | casmvsnet (needs --weights) | patchmatchnet."""
    weights: str | None = None
    """Weights file for learned backbones."""
    ndepths: list[int] = _limited(factory=lambda: [192, 32, 8], len=3, min=2)
    """Hypotheses per cascade stage (METHOD.md 0)."""
    width: Literal["paper", "released"] = "paper"
    """Finer-stage search width: paper (half the default CasMVSNet width) | released
    (METHOD.md 2.5)."""
    inverse_depth: bool = False
    """Stage-1 planes uniform in inverse depth (unbounded scenes; METHOD.md 2.5, 9.1)."""
    max_sources: int = _limited(4, min=0)
    """Source views per reference view in MVS, the best by the scene's pair score (METHOD.md 1.4:
    the released code feeds at most 5 views, the reference and 4 sources); 0 = every other input
    view. Three inputs use both others either way; with more inputs the cap keeps the MVS time
    linear in the number of views (`svolsdf.mvs.backbone.select_sources`)."""
    scale: float | None = _limited(None, gt=0)
    """The cascade runs at ``scale`` x the working size (stage 3 at scale x; images upsampled
    bicubically, as the released code's x2_mvsres, METHOD.md 9.2.2), the field at the working
    size. planesweep: any scale > 0; casmvsnet: 1 or 2 (its x2_mvsres); the patchmatchnet
    adapter runs at the working size. None = the backbone's own default."""
    native_images: bool = False
    """A cascade larger than the working size reads its images from the files when they are
    larger (`Scene.images_at`; a 1600x1200 photo gives stage 3 its own detail). false: the
    working-size images upsampled, as the released code (METHOD.md 9.2.2). On dtu_scan65 against
    its pseudo ground truth the two gave the same fast-preset Chamfer (1.93 mm) and the backbone
    alone 2.68 against 2.62 mm (benchmarks/results/dtu_pseudo_gt_dtu_scan65.md, session 18), so
    the released behaviour stays the default."""
    guide_network: bool = True
    """Backbones that can start from a depth map (patchmatchnet): rerun the network from the
    field's guide depth at the guided stage 2, so that the surface guides the network itself, as
    it replaces CasMVSNet's stage-1 depth (`svolsdf.mvs.adapters`). false: the network runs once
    per view and the guide only centres the hypotheses. Other backbones ignore it."""


@dataclass
class FieldConfig:
    kind: Literal["grid", "mlp"] = "grid"
    """grid (the fast preset's multi-resolution grid field) | mlp (the paper's VolSDF 8x256 MLP)."""
    mlp_depth: int = _limited(8, min=1)
    """mlp: hidden layers of the SDF MLP (METHOD.md 5.2)."""
    mlp_width: int = _limited(256, min=1)
    """mlp: hidden width of the SDF and colour MLPs."""
    background: bool = False
    """Add the NeRF++ inverted-sphere background model (unbounded scenes, METHOD.md 5.5): the
    field's sphere clamp is off and rays end at the bounding sphere, beyond which the
    background MLP (field/background.py) renders."""
    grid_resolution: int = _limited(128, min=4)
    """grid: final resolution of the dense SDF grid."""
    grid_start_resolution: int = _limited(64, min=4)
    """grid: resolution at the start (coarse to fine)."""
    init: Literal["mvs", "sphere"] = "mvs"
    """grid: initial surface. mvs: signed distance of the fused stage-1 MVS depth (fast preset,
    svolsdf mode; field/init.py) | sphere: VolSDF's geometric init (METHOD.md 5.2)."""
    sphere_radius: float = _limited(0.3, min=0.01)
    """grid started from a sphere (volsdf mode, or init = sphere): radius of VolSDF's initial
    sphere |x| - r (METHOD.md 5.2), unit frame, centred at the origin, in a grid over the box of
    the bounding sphere [-1, 1]^3 (the unit frame's region of interest): only the cameras and the
    sphere, nothing from MVS. Smaller than VolSDF's 0.6 so that the surface grows outward to the
    object instead of carving a sphere that hides it (benchmarks/results/volsdf_baseline.md)."""
    sphere_start_resolution: int = _limited(16, min=4)
    """grid started from a sphere: SDF grid resolution at the start; it doubles at evenly spaced
    steps until ``grid_resolution`` by 3/4 of the steps (coarse to fine: a coarse grid moves the
    surface as a whole; a fine one from the start paints the photos on the sphere)."""
    init_unverified_weight: float = _limited(0.0, min=0)
    """grid, init = mvs: vote weight (times the MVS confidence) of the stage-1 depths that no
    other view confirms, in the initial surface (field/init.py); only inside the object masks,
    so scenes without masks keep the 0 rule. 0 = they do not vote: a region only one view sees
    then starts at the hull the other views' free space leaves."""


@dataclass
class TrainConfig:
    mode: Literal["svolsdf", "volsdf", "mvs-only"] = "svolsdf"
    """svolsdf (MVS prior + losses) | volsdf (the same model without the prior) | mvs-only."""
    ablation: Literal["soft-consistency-only", "mse", "no-prob-volume", "ce"] | None = None
    """None | soft-consistency-only | mse | no-prob-volume | ce (paper ablations)."""
    steps: int = _limited(1000, min=0)
    """Optimization steps (fast preset: 1000 from the MVS-initialised grid; 500 until session
    14, when the faster step made 1000 affordable. Paired runs: points Chamfer lower by
    0.01-0.09 mm on five of six synthetic scenes, 0.02 mm higher on one; ~2 min more on two
    cores (benchmarks/results/fast_preset.md, session-14 notes)."""
    rays: int = _limited(512, min=1)
    """Rays per step, from one random input view (METHOD.md 4.6)."""
    object_ray_fraction: float = _limited(0.0, min=0, max=1)
    """Share of each step's rays drawn inside the view's object mask (dilated by
    ``object_ray_dilation`` px); the rest are uniform over the image, as released (0 = all
    uniform). Scenes without masks ignore it. Measured on five scenes at 0.5: no gain beyond
    the training-seed noise (benchmarks/results/fast_preset.md, session 11), so no preset
    sets it."""
    object_ray_dilation: int = _limited(12, min=0)
    """Dilation in pixels (working size) of the masks for ``object_ray_fraction``."""
    lr: float = _limited(5e-4, min=0)
    """Adam learning rate for networks (constant, METHOD.md 4.6)."""
    lr_grid: float = _limited(1e-2, min=0)
    """grid field: learning rate of the feature grids."""
    lr_sdf: float = _limited(3e-4, min=0)
    """grid field: learning rate of the SDF grid when it starts from the MVS surface (per node:
    keep it well below a cell size, or Adam's normalized steps roughen the surface). 3e-4 lets
    the surface move ~0.15 unit-frame units per 500 steps (tuned at 500 steps); 1e-4 held it
    within a few mm of the MVS initialisation (benchmarks/results/fast_preset.md, notes)."""
    lr_sdf_sphere: float = _limited(5e-3, min=0)
    """grid field: learning rate of the SDF grid when it starts from a sphere (volsdf mode,
    field.init = sphere): the surface has to travel, not just be refined."""
    grid_eikonal_weight: float = _limited(0.1, min=0)
    """grid field started from a sphere: weight of an eikonal term over every cell of the SDF
    grid (finite differences, `GridSDFField.grid_eikonal_loss`), besides METHOD.md 4.5's term at
    sampled points, which reaches few of the nodes a travelling surface passes. Not used when
    the grid starts from the MVS surface."""
    grad_clip: float = _limited(1.0, min=0)
    """Global-norm gradient clipping (0 = off)."""
    eikonal_weight: float = _limited(0.1, min=0)
    rgb_weight: float = _limited(1.0, min=0)
    mvs_weight: float = _limited(1.0, min=0)
    sparse_weight: float = _limited(1.0, min=0)
    smooth_weight: float = _limited(0.0, min=0)
    """grid field: weight of the grid smoothness regularizer (not in the paper)."""
    gce_q: float = _limited(0.5, min=0, max=1)
    """GCE exponent q (METHOD.md 4.2); 0 gives cross-entropy."""
    gce_form: Literal["paper", "released"] = "paper"
    """paper: P'(1 - w^q)/q | released: -P' sg(w)^q log w (same gradient; METHOD.md 9.2.4)."""
    sparse_norm: Literal["unsupervised", "all"] = "unsupervised"
    """unsupervised: divide by |Q| (paper) | all: divide by all rays (released; METHOD.md 9.2.5)."""
    sparse_decay: bool = False
    """Released code's linear decay of the sparsity weight over the warm-up (METHOD.md 4.3)."""
    anneal_rgb: int = _limited(200, min=0)
    """Warm-up steps with the Gaussian-smoothed RGB target and the sparsity loss (METHOD.md 4.4)."""
    warmup_mask_supervised: bool = False
    """Released code: no RGB loss on MVS-supervised rays during the warm-up (METHOD.md 9.2.6)."""
    sampler: Literal["mvs", "error_bounded"] = "mvs"
    """mvs: samples where P' and the current surface are (fast) | error_bounded (METHOD.md 5.4)."""
    samples_uniform: int = _limited(32, min=1)
    """mvs sampler: stratified samples along the ray."""
    samples_fine: int = _limited(48, min=0)
    """mvs sampler: importance samples from P' and the current weights."""
    beta_min: float = _limited(0.0, min=0)
    """> 0: replaces the Laplace density's floor beta_min (METHOD.md 5.4: 1e-4); 0 keeps it."""
    beta_start: float = _limited(0.0, min=0)
    """> 0: beta is not learned but annealed log-linearly from beta_start to beta_end over the
    steps (unit-frame units; fast preset: a short run cannot wait for the learned beta to
    sharpen). 0: learnable beta (METHOD.md 5.4, the paper)."""
    beta_end: float = _limited(0.0025, gt=0)
    """Final beta of the anneal (unit frame; ~0.5 mm on DTU-scale scenes). 0.0025 against 0.005:
    points Chamfer 2.00 vs 2.12 mm and 1.62 vs 1.66 mm on two synthetic 768x576 scenes
    (benchmarks/results/fast_preset.md, notes)."""
    checkpoint_every: int = _limited(100, min=0)
    """Save a checkpoint every N steps (resume after a kill); 0 = never."""
    seed: int = _limited(0, min=0)
    """Random seed."""


@dataclass
class OutputConfig:
    mesh_resolution: int = _limited(256, min=8)
    """Marching-cubes grid resolution in the unit frame."""
    mesh_format: Literal["ply", "obj"] = "ply"
    """ply | obj."""
    mesh_cull_unseen: bool = False
    """Mesh: also remove the faces no input view sees, i.e. whose centroid lies more than
    ``mesh_cull_tol`` behind the field's rendered depth in every view that contains it
    (`svolsdf.fusion.mesh.cull_unseen`). Off as released (mask culling only, METHOD.md 8.3).
    The fast preset turns it on: the interior of a sparse-view reconstruction is unconstrained
    and may hold cavities (benchmarks/results/fast_preset.md, session 8)."""
    mesh_cull_tol: float = _limited(0.01, min=0)
    """Mesh: relative depth slack of ``mesh_cull_unseen``."""
    mesh_watertight: bool = False
    """Mesh: keep the whole closed zero level (its largest connected part) instead of the parts
    the input views judge: no frustum, mask or visibility culling, so the mesh has no holes
    (for printing or simulation). Parts no view sees are the field's guess, so it scores worse
    against ground truth than the culled mesh."""
    fusion_dist: float = _limited(1.0, min=0)
    """Fusion: reprojection distance threshold in pixels (METHOD.md 6.3)."""
    fusion_rel: float = _limited(0.01, min=0)
    """Fusion: relative depth difference threshold (METHOD.md 6.3)."""
    fusion_views: int = _limited(1, min=0)
    """Fusion: minimum number of consistent source views (METHOD.md 6.3)."""
    fusion_conf: float = _limited(0.0, min=0, max=1)
    """Fusion: photometric confidence threshold (0 = off, as released; METHOD.md 9.2.9)."""
    fusion_surface: float = _limited(0.0, min=0)
    """Fusion: a depth within this relative difference of the optimized surface's rendered depth
    (the guide) counts as one consistent source (`FusionConfig.surface_rel_thresh`; 0 = off, as
    released). Not used without a field (mvs-only)."""
    fusion_guided_dilation: int | None = _limited(None, min=0)
    """Fusion: object-mask dilation, in pixels, for the field-guided depth maps (svolsdf mode);
    None = the released 12 px for every depth map (METHOD.md 6.3). The unguided set
    (``fusion_unguided``) takes ``fusion_unguided_dilation``. Near the silhouette the guided
    stages 2-3 inherit the field's errors (a surface fattened into the background), and because
    those errors form one 3D surface the multi-view check passes them
    (`FusionConfig.primary_mask_dilation`)."""
    fusion_unguided_dilation: int | None = _limited(None, min=0)
    """Fusion: object-mask dilation, in pixels, for the unguided set of ``fusion_unguided``;
    None = the released 12 px (`FusionConfig.alt_mask_dilation`). As a second hypothesis beside
    the guided depth, its points 4-12 px outside the masks were mostly background (6-8 mm off
    on synthetic scenes). A small gain: points Chamfer 0.6 % lower on average by the clipped
    rule, 1.2 % by the DTU rule, over six scenes (benchmarks/results/fast_preset.md, session
    16)."""
    fusion_unguided: bool = False
    """Fusion: also run MVS stages 2-3 centred on the stage-1 depth, as the backbone alone does,
    and give every view that unguided depth as a second hypothesis: each hypothesis is a
    reference in turn, and a source view is consistent when either of its hypotheses agrees
    (`fuse_depth_maps` ``alt_depths``). Where the field is wrong, its guide centres stages 2-3
    away from the surface and their narrow search cannot find it; the unguided pass still can.
    An extension: neither the paper nor the released code has it (svolsdf mode only).
    OUT/unguided/{depth,confidence}/<view>.npy."""
    fusion_network: str | None = _limited(None, choices=_backbone_names)
    """Fusion: a learned backbone that can start from a depth map (patchmatchnet, with
    ``fusion_network_weights``), started from the field's guide depth in every input view; its
    depth joins fusion as a further hypothesis of each view, like ``fusion_unguided``'s (svolsdf
    mode only; OUT/network/{depth,confidence}/<view>.npy). A second matcher adds multi-view
    evidence where the main backbone fails: with the plane sweep, points Chamfer 7-17 % lower on
    four masked synthetic scenes, 2 % on a mask-free one, 15 % on dtu_scan65 against a pseudo
    ground truth PatchmatchNet built; ~15 s more for three views
    (benchmarks/results/fusion_network.md). None = off (the paper; no weights ship with this
    package)."""
    fusion_network_weights: str | None = None
    """Weights file of ``fusion_network``."""
    use_masks: bool = True
    """Apply (dilated) object masks when the scene has them (METHOD.md 6.3)."""
    guide_mask_dilation: int | None = _limited(None, min=0)
    """Render the guide depth (METHOD.md 6.1) only inside the object masks dilated by this many
    pixels; the other pixels count as rendered with no surface (weight 0, so
    ``low_weight_rule`` applies). None = every pixel (released). Scenes without masks render
    every pixel."""
    low_weight_rule: Literal["max", "mvs"] = "max"
    """Rendered-depth pixels with weight < 0.2: max (the map's maximum depth, released) |
    mvs (keep the stage-1 MVS depth)."""
    mesh_fit_points: int = _limited(0, min=0)
    """Mesh: before marching cubes, refine the SDF grid for this many steps so that its zero
    level passes through the fused points (`svolsdf.field.fit`; svolsdf mode with the grid
    field; 0 = off, the paper: the mesh is the optimized field's zero level). The finer MVS
    stages place depth more precisely than the surface that guided them, so the fused points
    are more accurate than the field; this brings the mesh to them. OUT/field/surface.pt."""
    mesh_method: Literal["field", "poisson"] = "field"
    """Mesh source: field (the optimized field's zero level by marching cubes, the paper) |
    poisson (the screened Poisson surface of OUT/points.ply, trimmed where the points are
    sparse: `svolsdf.fusion.poisson`, COLMAP's mesher through pycolmap). The fused points come
    from the finer MVS stages and are more accurate than the field; poisson brings the mesh to
    them. Culling (frusta, masks, ``mesh_cull_unseen`` by the mesh's own depth) is the same;
    vertex colours come from the points."""
    poisson_depth: int = _limited(10, min=5, max=14)
    """Mesh (poisson): octree depth; the finest cell is the points' box / 2^depth."""
    poisson_trim: float = _limited(5.0, min=0, max=14)
    """Mesh (poisson): remove the surface whose sample density, in octree levels, is below
    this (0 = keep the closed surface)."""
    finer_stage_optimization: bool = False
    """Paper option (METHOD.md 9.2.13; the released code forbids it): after stage 2, optimize
    the field for steps/5 more steps against the stage-2 volumes' soft-consistency prior, render
    its depth again and centre stage 3 on it (svolsdf mode; Pipeline._finer_stage_cascade)."""


@dataclass
class Config:
    preset: Literal["fast", "paper"] = "fast"
    """fast (default; minutes on a CPU) | paper (METHOD.md constants; a GPU)."""
    device: Literal["auto", "cpu", "cuda"] = "auto"
    """auto | cpu | cuda."""
    threads: int = _limited(0, min=0)
    """torch intra-op threads; 0 = the cores this process may run on (its CPU affinity), unless
    OMP_NUM_THREADS is set, which then decides (`svolsdf.pipeline.set_threads`)."""
    scene: SceneConfig = dc_field(default_factory=SceneConfig)
    mvs: MVSConfig = dc_field(default_factory=MVSConfig)
    field: FieldConfig = dc_field(default_factory=FieldConfig)
    train: TrainConfig = dc_field(default_factory=TrainConfig)
    output: OutputConfig = dc_field(default_factory=OutputConfig)


# --------------------------------------------------------------------------- validation
class _Rejected(Exception):
    """A value does not fit its field; ``args[0]`` says what would. ``near``: the value has the
    right type but is out of range (a union then reports this member alone)."""

    def __init__(self, wanted: str, near: bool = False):
        super().__init__(wanted)
        self.near = near


def _range_text(lim: dict) -> str:
    lo, hi, gt = lim.get("min"), lim.get("max"), lim.get("gt")
    if lo is not None and hi is not None:
        return f" in [{lo}, {hi}]"
    if gt is not None:
        return f" > {gt}"
    if lo is not None:
        return f" >= {lo}"
    if hi is not None:
        return f" <= {hi}"
    return ""


def _check_range(x: float, lim: dict, what: str) -> None:
    lo, hi, gt = lim.get("min"), lim.get("max"), lim.get("gt")
    if (lo is not None and x < lo) or (hi is not None and x > hi) or (gt is not None and x <= gt):
        raise _Rejected(what + _range_text(lim), near=True)


def _check_value(value: Any, tp: Any, lim: dict) -> Any:
    """``value`` checked against the annotation ``tp`` and the field's limits, normalized (an int
    where a float is wanted becomes a float, a tuple a list, a path a string).

    Raises:
        _Rejected: with the description of what is allowed.
    """
    origin, args = get_origin(tp), get_args(tp)
    if origin is Union or origin is types.UnionType:
        if value is None and type(None) in args:
            return None
        options = [a for a in args if a is not type(None)]
        wanted = []
        for a in options:
            try:
                return _check_value(value, a, lim)
            except _Rejected as e:
                if e.near:
                    raise
                wanted.append(str(e))
        if type(None) in args:
            wanted.append("null")
        raise _Rejected(" or ".join(wanted))
    if origin is Literal:
        if isinstance(value, str) and value in args:
            return value
        raise _Rejected(("one of " if len(args) > 1 else "") + ", ".join(repr(a) for a in args))
    if tp is bool:
        # YAML's quoted 'no' is a (truthy) string: only real booleans are accepted
        if isinstance(value, bool):
            return value
        raise _Rejected("true or false")
    if tp is int:
        what = "an integer" + _range_text(lim)
        if isinstance(value, bool) or not isinstance(value, numbers.Integral):
            raise _Rejected(what)
        value = int(value)  # numpy integers too
        _check_range(value, lim, "an integer")
        return value
    if tp is float:
        what = "a number" + _range_text(lim)
        if isinstance(value, str):
            # YAML 1.1 (PyYAML) reads 1e-3 as a string: a plain number in a string is accepted
            try:
                value = float(value)
            except ValueError:
                raise _Rejected(what) from None
        if isinstance(value, bool) or not isinstance(value, numbers.Real):
            raise _Rejected(what)
        value = float(value)
        if not math.isfinite(value):
            raise _Rejected("a finite number" + _range_text(lim))
        _check_range(value, lim, "a number")
        return value
    if tp is str:
        if isinstance(value, os.PathLike):
            value = os.fspath(value)
        choices = lim.get("choices")
        if choices is not None:
            allowed = list(choices())
            if value not in allowed:
                raise _Rejected("one of " + ", ".join(repr(a) for a in allowed))
        if not isinstance(value, str):
            raise _Rejected("a string")
        return value
    if origin in (list, tuple):
        item_tp = args[0] if args else Any
        n, n_min = lim.get("len"), lim.get("min_len")
        item_lim = {k: v for k, v in lim.items() if k in ("min", "max", "gt")}
        item_what = {int: "integers", float: "numbers", str: "strings"}.get(item_tp, "items")
        what = (f"a list of {n} " if n is not None else
                f"a list of at least {n_min} " if n_min is not None else "a list of ") + \
            item_what + _range_text(item_lim)
        if lim.get("unique"):
            what += ", each once"
        if not isinstance(value, (list, tuple)):
            raise _Rejected(what)
        if (n is not None and len(value) != n) or (n_min is not None and len(value) < n_min):
            raise _Rejected(what, near=True)
        try:
            out = [_check_value(v, item_tp, item_lim) for v in value]
        except _Rejected as e:
            raise _Rejected(what, near=e.near) from None
        if lim.get("unique"):
            seen = set()
            for v in out:
                if v in seen:
                    raise _Rejected(f"{what} ({v} is repeated)", near=True)
                seen.add(v)
        return out
    if tp is Any:
        return value
    raise TypeError(f"validate_config: no rule for the annotation {tp!r}")  # a new field's


def _short(value: Any) -> str:
    r = repr(value)
    return r if len(r) <= 60 else r[:57] + "..."


def _validate_dataclass(obj: Any, prefix: str, where: str | None,
                        labels: Mapping[str, str]) -> None:
    hints = get_type_hints(type(obj))
    for f in fields(obj):
        key = prefix + f.name
        value = getattr(obj, f.name)
        tp = hints[f.name]
        if dataclasses.is_dataclass(tp):
            if not isinstance(value, tp):
                raise InputError(f"{where + ': ' if where else ''}{key}: expected a mapping of "
                                 f"{', '.join(g.name for g in fields(tp))}")
            _validate_dataclass(value, key + ".", where, labels)
            continue
        try:
            setattr(obj, f.name, _check_value(value, tp, f.metadata.get("limits", {})))
        except _Rejected as e:
            name = f"{labels[key]} ({key})" if key in labels else key
            raise InputError(f"{where + ': ' if where else ''}{name} = {_short(value)}: "
                             f"expected {e}") from None


def validate_config(cfg: Config, where: str | None = None,
                    labels: Mapping[str, str] | None = None) -> Config:
    """Check every field of ``cfg`` against its type annotation and limits, in place.

    The one check of a run's configuration, made when it is built (from YAML, from command-line
    options or in code) and before any stage runs: types (a string where a number is wanted, a
    quoted 'no' where a boolean is), enumerations (``Literal``), ranges and list lengths
    (`_limited`), and the combinations of options that cannot run. Ints given for floats
    become floats, tuples lists.

    Args:
        cfg: the configuration; normalized in place and returned.
        where: what the values came from (a file name), to begin the message with.
        labels: dotted key -> the option that set it (``{"train.steps": "--steps"}``).

    Raises:
        InputError: naming the dotted key (and its option), the value and what is allowed.
    """
    if not isinstance(cfg, Config):
        raise InputError(f"{where or 'config'}: expected a Config, got {type(cfg).__name__}")
    labels = labels or {}
    _validate_dataclass(cfg, "", where, labels)
    head = f"{where}: " if where else ""
    if cfg.output.finer_stage_optimization and (cfg.train.mode != "svolsdf"
                                                or cfg.train.ablation is not None):
        raise InputError(f"{head}output.finer_stage_optimization needs train.mode svolsdf "
                         "without train.ablation (it optimizes the field against the stage-2 "
                         "volumes)")
    return cfg


def _paper() -> Config:
    c = Config(preset="paper")
    c.field = FieldConfig(kind="mlp")
    c.train = TrainConfig(steps=100_000, sampler="error_bounded", lr=5e-4, checkpoint_every=5000)
    c.mvs = MVSConfig(backbone="planesweep", width="paper")
    c.output = OutputConfig(mesh_resolution=512)
    return c


def _fast() -> Config:
    c = Config(preset="fast")
    # measured on a 384x288 synthetic scene (notes of issue 5): an annealed beta and a 50-step
    # warm-up (the paper's 200 of 100k steps would be 40% of this run) gave Chamfer 2.35 mm vs
    # 2.50 mm with the learned beta and 200 steps; MVS alone 2.63 mm
    c.train.beta_start = 0.05
    c.train.anneal_rgb = 50
    # a stage-3 depth on the optimized surface counts as one consistent source in fusion:
    # points Chamfer 1.91 -> 1.79 mm (seed 0) and 1.56 -> 1.50 mm (seed 3), 768x576 synthetic
    # scenes (benchmarks/results/fast_preset.md); 0.1 % gave 1.81 / 1.49. With the unguided set
    # and the unverified init votes below (session 9, fusion rerun on the session-8 runs), 0.1 %
    # beats 0.05 % on all four scenes and by both rules: clipped 1.405 / 1.242 / 1.220 / 2.187 ->
    # 1.394 / 1.214 / 1.208 / 2.128 mm, DTU rule 1.179 / 1.078 / 1.134 / 1.590 -> 1.169 / 1.075
    # / 1.119 / 1.586; 0.2 % is worse on seed 0 and by the DTU rule on seed 11. But on the real
    # DTU scan 65 against a 49-view pseudo ground truth (benchmarks/dtu_pseudo_gt.py) 0.1 % is
    # worse (points Chamfer 2.08 -> 2.12 mm, accuracy 1.77 -> 1.98), so 0.05 % stays
    c.output.fusion_surface = 5e-4
    # the field-guided depth fused only inside masks dilated by 4 px (the unguided set keeps the
    # released 12): session 9, fusion rerun on the session-8 runs, points Chamfer 1.405 / 1.242 /
    # 1.220 / 2.187 -> 1.377 / 1.223 / 1.201 / 2.161 mm on the four synthetic scenes (DTU rule
    # better on all four too) and, on DTU scan 65 against the pseudo ground truth, ratio to the
    # MVS backbone alone 0.78 -> 0.75 (benchmarks/results/fast_preset.md, notes)
    c.output.fusion_guided_dilation = 4
    # and the unguided set too (session 16, fusion rerun on fresh runs; the MVS backbone alone
    # keeps the released 12): points Chamfer 1.343 -> 1.327 mm (seed 0), 2.100 -> 2.088 (seed
    # 11), DTU rule better on both, and dtu_scan65's object 1.97 -> 1.92 mm against its pseudo
    # ground truth (DTU rule 1.89 -> 1.84)
    c.output.fusion_unguided_dilation = 4
    # the unguided stages 2-3 as every view's second depth hypothesis in fusion: points Chamfer
    # 1.76 -> 1.45 mm (seed 0), 1.50 -> 1.28, 1.39 -> 1.22, 2.61 -> 2.35 on three more synthetic
    # scenes, for ~30 s more (benchmarks/results/fast_preset.md)
    c.output.fusion_unguided = True
    # stage-1 depths no other view confirms still vote (weight 0.05 x confidence) in the SDF
    # grid's initial surface: points Chamfer 1.45 -> 1.39 mm (seed 0), 1.28 -> 1.24 (seed 3),
    # 1.22 -> 1.22 (blobs 7), 2.35 -> 2.19 (seed 11); a trade: F-score -0.005 to -0.01 and the
    # DTU-rule Chamfer worse on three of the four (benchmarks/results/fast_preset.md, session 8)
    c.field.init_unverified_weight = 0.05
    # and the mesh keeps the surface the input views see: with the line above, the unseen
    # interior holds cavities (mesh Chamfer 3.8 -> 2.6 / 3.3 -> 2.1 / 3.8 -> 2.0 / 4.2 -> 2.9)
    c.output.mesh_cull_unseen = True
    # the guide depth is rendered only within 32 px of the object masks (fusion keeps the
    # guided depth within 4 px, and the unguided set within 12 until session 16): the guide
    # stage 4.35x faster on the seed-0 scene (benchmarks/results/guide_speed.md), points
    # Chamfer unchanged within noise on five synthetic scenes (fast_preset.md, session-14 notes)
    c.output.guide_mask_dilation = 32
    # the mesh is the surface refined to pass through the fused points (issue 28): mesh Chamfer
    # 1.36 -> 1.19 mm and 1.48 -> 1.33 mm on two synthetic scenes (points 0.52-0.54 / 0.50),
    # ~30-40 s (benchmarks/results/volsdf_baseline.md)
    c.output.mesh_fit_points = 300
    return c


PRESETS = {"fast": _fast, "paper": _paper}


def preset(name: str) -> Config:
    """A fresh `Config` of the named preset."""
    if not isinstance(name, str) or name not in PRESETS:
        raise InputError(f"unknown preset {name!r} (choose from {', '.join(PRESETS)})")
    return PRESETS[name]()


def _from_dict(cls, data: dict, where: str, prefix: str = ""):
    obj = cls()
    names = {f.name: f for f in fields(cls)}
    for k, v in data.items():
        if k not in names:
            raise InputError(f"{where}: unknown key {prefix + str(k)!r} (known in "
                             f"{prefix.rstrip('.') or 'the top level'}: {', '.join(names)})")
        cur = getattr(obj, k)
        if dataclasses.is_dataclass(cur):
            if not isinstance(v, dict):
                raise InputError(f"{where}: {prefix}{k} = {_short(v)}: expected a mapping of "
                                 f"{', '.join(f.name for f in fields(cur))}")
            setattr(obj, k, _from_dict(type(cur), v, where, f"{prefix}{k}."))
        else:
            setattr(obj, k, v)
    return obj


def config_from_dict(data: dict, where: str = "config") -> Config:
    """A validated `Config` from a nested dict: the keys it gives over its preset's values.

    Raises:
        InputError: an unknown key or a value `validate_config` rejects, named with ``where``.
    """
    name = data.get("preset", "fast")
    if not isinstance(name, str) or name not in PRESETS:
        raise InputError(f"{where}: preset = {_short(name)}: expected one of "
                         f"{', '.join(repr(p) for p in PRESETS)}")
    merged = _merge(asdict(preset(name)), data)
    return validate_config(_from_dict(Config, merged, where), where)


def _merge(a: dict, b: dict) -> dict:
    out = dict(a)
    for k, v in b.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = _merge(out[k], v)
        else:
            out[k] = v
    return out


def load_config(path: str | Path) -> Config:
    """Read a YAML config (as written by `save_config`)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: config file not found")
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as e:
        raise InputError(f"{path}: not valid YAML ({e.__class__.__name__})") from None
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(f"{path}: cannot read the config file ({e})") from None
    if not isinstance(data, dict):
        raise InputError(f"{path}: expected a mapping at the top level")
    return config_from_dict(data, where=str(path))


def save_config(cfg: Config, path: str | Path) -> None:
    """Write ``cfg`` as YAML atomically."""
    import os

    path = Path(path)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(yaml.safe_dump(asdict(cfg), sort_keys=False))
    os.replace(tmp, path)


def apply_overrides(cfg: Config, overrides: dict[str, Any],
                    labels: Mapping[str, str] | None = None) -> Config:
    """Set dotted keys (``{"train.steps": 100}``; None values are skipped), then validate.

    Args:
        labels: dotted key -> the option that gave it, for the messages of `validate_config`.

    Raises:
        InputError: an unknown key, or a value `validate_config` rejects.
    """
    for key, value in overrides.items():
        if value is None:
            continue
        obj = cfg
        parts = key.split(".")
        for p in parts[:-1]:
            obj = getattr(obj, p, None)
            if not dataclasses.is_dataclass(obj):
                raise InputError(f"unknown config key {key!r}")
        if not hasattr(obj, parts[-1]):
            raise InputError(f"unknown config key {key!r}")
        setattr(obj, parts[-1], value)
    given = {k: v for k, v in (labels or {}).items() if overrides.get(k) is not None}
    return validate_config(cfg, labels=given)
