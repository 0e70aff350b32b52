"""The run configuration: one dataclass per component, a docstring under every option.

`Config` describes a whole run; `svolsdf config` prints it as YAML with these docstrings as
comments, and ``--set section.option=value`` sets any option. Limits beside the types are checked
by `svolsdf.config.validate.validate_config`.
"""

from __future__ import annotations

import dataclasses
import types
from dataclasses import dataclass
from dataclasses import field as dc_field
from typing import Any, Literal, Union, get_args, get_origin, get_type_hints

__all__ = ["Config", "SceneConfig", "MVSConfig", "FieldConfig", "TrainConfig", "GuideConfig",
           "FusionConfig", "MeshConfig", "PoissonConfig", "TSDFConfig",
           "DTU_TRAIN_IDS", "DTU_EXCLUDED_IDS", "choices"]


def _limited(default: Any = dataclasses.MISSING, *, factory: Any = dataclasses.MISSING,
             **limits: Any) -> Any:
    """A dataclass field with limits that `validate_config` checks beside its type.

    Limits: ``min`` / ``max`` (inclusive) and ``gt`` (exclusive) bound a number or every item of
    a list; ``len`` / ``min_len`` the length of a list; ``unique`` forbids repeated items;
    ``choices`` is a function returning the allowed strings (for registries that can grow, where
    a ``Literal`` would be too narrow); ``pattern`` a regular expression a string must match in
    full, with ``wanted`` saying in words what it allows.
    """
    return dc_field(default=default, default_factory=factory, metadata={"limits": limits})


def _backbone_names() -> list[str]:
    from svolsdf.mvs.backbone import available_backbones

    return available_backbones()


def _sampler_names() -> list[str]:
    from svolsdf.render.sampler_registry import registered_samplers

    return registered_samplers()


def _field_kind_names() -> list[str]:
    from svolsdf.field.kinds import registered_field_kinds

    return registered_field_kinds()


def _mesh_method_names() -> list[str]:
    from svolsdf.fusion.mesh_methods import registered_mesh_methods

    return registered_mesh_methods()


#: DTU protocol input views (docs/method.md 1.4): the first num_view of this list.
DTU_TRAIN_IDS = [25, 22, 28, 40, 44, 48, 0, 8, 13]
#: DTU views never used for testing (docs/method.md 1.4).
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
    use_masks: bool = True
    """Apply (dilated) object masks when the scene has them (docs/method.md 6.3)."""


@dataclass
class MVSConfig:
    backbone: str = _limited("planesweep", choices=_backbone_names)
    """planesweep (training-free, default) | casmvsnet (needs --weights) | patchmatchnet."""
    weights: str | None = None
    """Weights file for learned backbones."""
    ndepths: list[int] = _limited(factory=lambda: [192, 32, 8], len=3, min=2)
    """Hypotheses per cascade stage (docs/method.md 0)."""
    width: Literal["paper", "released", "half-default"] = "paper"
    """Finer-stage interval ratios: paper (1, 0.5, 0.5, the paper's explicit numbers) |
    released (the same, the released code's) | half-default (1, 1, 0.5: half CasMVSNet's
    default width, a reading of the paper's method section; docs/method.md 2.5)."""
    inverse_depth: bool = False
    """Stage-1 planes uniform in inverse depth (unbounded scenes; docs/method.md 2.5, 9.1)."""
    max_sources: int = _limited(4, min=0)
    """Source views per reference view in MVS, the best by the scene's pair score (docs/method.md
    1.4: the released code feeds at most 5 views, the reference and 4 sources); 0 = every other
    input view. Three inputs use both others either way; with more inputs the cap keeps the MVS time
    linear in the number of views (`svolsdf.mvs.backbone.select_sources`)."""
    scale: float | None = _limited(None, gt=0, max=4)
    """The cascade runs at ``scale`` x the working size (stage 3 at scale x; images upsampled
    bicubically, as the released code's x2_mvsres, docs/method.md 9.2.2), the field at the working
    size. planesweep and casmvsnet: any scale in (0, 4] (casmvsnet's input rounded to multiples of
    32; 1 and 2 are its x2_mvsres; 4/3 the paper's mid resolution); the patchmatchnet
    adapter runs at the working size. None = the backbone's own default."""
    native_images: bool = False
    """A cascade larger than the working size reads its images from the files when they are
    larger (`Scene.images_at`; a 1600x1200 photo gives stage 3 its own detail). false: the
    working-size images upsampled, as the released code (docs/method.md 9.2.2) and the default."""
    finer_stage_optimization: bool = False
    """Paper option (docs/method.md 9.2.13; the released code forbids it): after stage 2, optimize
    the field for steps/5 more steps against the stage-2 volumes' soft-consistency prior, render
    its depth again and centre stage 3 on it (svolsdf mode;
    `svolsdf.pipeline.finer.finer_stage_cascade`)."""
    third_stage_optimization: bool = False
    """With ``finer_stage_optimization``: after stage 3 too, optimize the field for steps/5
    more steps against the stage-3 volumes' prior (the paper's stages 1, 2, 3 of its
    limitations paragraph, docs/method.md 9.2.13); the mesh is that field's and fusion's
    surface hypothesis its rendered depth."""
    crop_to_masks: int | None = _limited(None, min=0)
    """planesweep: stages 2-3 run only in the box around each reference's object mask dilated by
    this many pixels (working size); outside it those stages give no depth (fusion keeps depth
    only within ``fusion.*_dilation`` px of the masks anyway). None, a scene without masks, or
    ``scene.use_masks = false``: every pixel. Other backbones ignore it."""
    save_volumes: bool = False
    """Also keep the stage-2 and stage-3 probability volumes (OUT/mvs/stage2, stage3, about 70 MB
    a view at 768x576); nothing in the pipeline reads them again. Stage 1's are always kept (the
    field's prior and a resumed run read them). `svolsdf mvs` writes every stage's."""
    guide_network: bool = True
    """Backbones that can start from a depth map (patchmatchnet): rerun the network from the
    field's guide depth at the guided stage 2, so that the surface guides the network itself, as
    it replaces CasMVSNet's stage-1 depth (`svolsdf.mvs.adapters`). false: the network runs once
    per view and the guide only centres the hypotheses. Other backbones ignore it."""


@dataclass
class FieldConfig:
    # the names registered with svolsdf.field.kinds.register_field_kind
    kind: str = _limited("grid", choices=_field_kind_names)
    """grid (the fast preset's multi-resolution grid field) | mlp (the paper's VolSDF 8x256 MLP)."""
    mlp_depth: int = _limited(8, min=1)
    """mlp: hidden layers of the SDF MLP (docs/method.md 5.2)."""
    mlp_width: int = _limited(256, min=1)
    """mlp: hidden width of the SDF and colour MLPs."""
    background: bool = False
    """Add the NeRF++ inverted-sphere background model (unbounded scenes, docs/method.md 5.5): the
    field's sphere clamp is off and rays end at the bounding sphere, beyond which the
    background MLP (field/background.py) renders."""
    background_model: Literal["nerf++", "sphere_map"] = "nerf++"
    """With ``background``: nerf++ (NeRF++'s inverted-sphere MLP, docs/method.md 5.5) |
    sphere_map (a colour painted on the bounding sphere where the ray leaves it, no network:
    the fast field's cheap stand-in, docs/novel-views.md)."""
    grid_resolution: int = _limited(128, min=4)
    """grid: final resolution of the dense SDF grid."""
    grid_start_resolution: int = _limited(64, min=4)
    """grid: resolution at the start (coarse to fine)."""
    init: Literal["mvs", "sphere"] = "mvs"
    """Initial surface. mvs: signed distance of the fused stage-1 MVS depth (the grid field in
    svolsdf mode, fast preset; field/initial.py) | sphere: VolSDF's geometric init
    (docs/method.md 5.2; the MLP field's only start, so ``kind`` mlp in svolsdf mode needs it).
    The volsdf mode always starts from the sphere (a baseline never sees MVS)."""
    sphere_radius: float = _limited(0.3, min=0.01)
    """grid started from a sphere (volsdf mode, or init = sphere): radius of VolSDF's initial sphere
    |x| - r (docs/method.md 5.2), unit frame, centred at the origin, in a grid over the box of the
    bounding sphere [-1, 1]^3 (the unit frame's region of interest): only the cameras and the
    sphere, nothing from MVS. Smaller than VolSDF's 0.6 so that the surface grows outward to the
    object instead of carving a sphere that hides it."""
    sphere_start_resolution: int = _limited(16, min=4)
    """grid started from a sphere: SDF grid resolution at the start; it doubles at evenly spaced
    steps until ``grid_resolution`` by 3/4 of the steps (coarse to fine: a coarse grid moves the
    surface as a whole; a fine one from the start paints the photos on the sphere)."""
    init_unverified_weight: float = _limited(0.0, min=0)
    """grid, init = mvs: vote weight (times the MVS confidence) of the stage-1 depths that no
    other view confirms, in the initial surface (field/initial.py); only inside the object masks,
    so scenes without masks keep the 0 rule. 0 = they do not vote: a region only one view sees
    then starts at the hull the other views' free space leaves."""


@dataclass
class TrainConfig:
    mode: Literal["svolsdf", "mvs-only", "volsdf"] = "svolsdf"
    """svolsdf (MVS prior + losses) | volsdf (the same model without the prior) | mvs-only."""
    ablation: Literal["soft-consistency-only", "mse", "no-prob-volume", "ce"] | None = None
    """soft-consistency-only | mse | no-prob-volume | ce (the paper's ablations; None = the full
    model)."""
    steps: int = _limited(1000, min=0)
    """Optimization steps (each draws ``rays`` rays from one input view)."""
    rays: int = _limited(512, min=1)
    """Rays per step, from one random input view (docs/method.md 4.6)."""
    object_ray_fraction: float = _limited(0.0, min=0, max=1)
    """Share of each step's rays drawn inside the view's object mask (dilated by
    ``object_ray_dilation`` px); the rest are uniform over the image, as released (0 = all
    uniform). Scenes without masks ignore it. No preset sets it."""
    object_ray_dilation: int = _limited(12, min=0)
    """Dilation in pixels (working size) of the masks for ``object_ray_fraction``."""
    colour_steps: int = _limited(0, min=0)
    """Steps after ``steps`` in which only the colour trains (the feature grids, the colour
    network and the background), the surface frozen: no SDF gradient, eikonal or prior, so a
    ray costs a fraction of a full step's. Grid field only; 0 = none, as the paper
    (docs/novel-views.md)."""
    colour_rays: int = _limited(2048, min=1)
    """Rays per colour step (``colour_steps``)."""
    colour_object_fraction: float = _limited(0.5, min=0, max=1)
    """Share of each colour step's rays drawn inside the view's object mask (dilated by
    ``object_ray_dilation`` px); scenes without masks draw every ray uniformly."""
    lr: float = _limited(5e-4, min=0)
    """Adam learning rate for networks (constant, docs/method.md 4.6)."""
    lr_grid: float = _limited(1e-2, min=0)
    """grid field: learning rate of the feature grids."""
    lr_sdf: float = _limited(3e-4, min=0)
    """grid field: learning rate of the SDF grid when it starts from the MVS surface (per node:
    keep it well below a cell size, or Adam's normalized steps roughen the surface)."""
    lr_sdf_sphere: float = _limited(5e-3, min=0)
    """grid field: learning rate of the SDF grid when it starts from a sphere (volsdf mode,
    field.init = sphere): the surface has to travel, not just be refined."""
    grid_eikonal_weight: float = _limited(0.1, min=0)
    """grid field started from a sphere: weight of an eikonal term over every cell of the SDF grid
    (finite differences, `GridSDFField.grid_eikonal_loss`), besides docs/method.md 4.5's term at
    sampled points, which reaches few of the nodes a travelling surface passes. Not used when the
    grid starts from the MVS surface."""
    grad_clip: float = _limited(1.0, min=0)
    """Global-norm gradient clipping (0 = off)."""
    eikonal_weight: float = _limited(0.1, min=0)
    """Weight of the eikonal loss |grad f| = 1 at sampled points (docs/method.md 4.5)."""
    rgb_weight: float = _limited(1.0, min=0)
    """Weight of the L1 colour loss of rendered against input pixels (docs/method.md 4.1)."""
    mvs_weight: float = _limited(1.0, min=0)
    """Weight of the MVS prior: the GCE loss between the rendering weights and the probability
    volume P' of the rays it supervises (docs/method.md 4.2)."""
    sparse_weight: float = _limited(1.0, min=0)
    """Weight of the sparsity loss on the rays P' does not supervise, during the warm-up
    (docs/method.md 4.3)."""
    smooth_weight: float = _limited(0.0, min=0)
    """grid field: weight of the grid smoothness regularizer (not in the paper)."""
    gce_q: float = _limited(0.5, min=0, max=1)
    """GCE exponent q (docs/method.md 4.2); 0 gives cross-entropy."""
    gce_form: Literal["paper", "released"] = "paper"
    """paper: P'(1 - w^q)/q | released: -P' sg(w)^q log w (same gradient; docs/method.md 9.2.4)."""
    sparse_norm: Literal["unsupervised", "all"] = "unsupervised"
    """unsupervised: divide by |Q| (paper) | all: by all rays (released; docs/method.md 9.2.5)."""
    sparse_decay: bool = False
    """Released code's linear decay of the sparsity weight over the warm-up (docs/method.md 4.3)."""
    anneal_rgb: int = _limited(200, min=0)
    """Warm-up steps: Gaussian-smoothed RGB target and sparsity loss (docs/method.md 4.4)."""
    warmup_mask_supervised: bool = False
    """Released code: no RGB loss on MVS-supervised rays in the warm-up (docs/method.md 9.2.6)."""
    # the names registered with svolsdf.render.sampler_registry.register_sampler
    sampler: str = _limited("mvs", choices=_sampler_names)
    """mvs: samples near P' and the current surface (fast) | error_bounded (docs/method.md 5.4)."""
    samples_uniform: int = _limited(32, min=1)
    """mvs sampler: stratified samples along the ray."""
    samples_fine: int = _limited(48, min=0)
    """mvs sampler: importance samples from P' and the current weights."""
    colour_min_weight: float = _limited(0.0, min=0, max=0.01)
    """> 0: during training the colour features and network are evaluated only at samples whose
    rendering weight exceeds this (the SDF and its gradient at every sample); the colour terms
    left out sum to less than samples x this per ray (`svolsdf.render.volume.render_rays`).
    0 = every sample, as the paper. Fields without a separate colour-feature lookup (mlp) use
    every sample."""
    prior_floor: float = _limited(0.0, min=0, max=0.01)
    """The labels P' (docs/method.md 3) read the source views only at samples whose own view's
    probability P_ref exceeds this; below it P' is left at 0 (less than this x (views - 1)).
    0: the sources are skipped only where P_ref = 0, which leaves P' exact
    (`svolsdf.prior.consistency.MVSPrior.label`)."""
    prior_sources: Literal["all", "selected"] = "all"
    """Whose P_src enter a ray's label P' (docs/method.md 3): all (every other input view, the
    paper) | selected (the view's MVS sources, at most ``mvs.max_sources`` by pair score,
    `svolsdf.mvs.backbone.select_sources`: with more views than that, each label reads fewer
    volumes). Three views: the same."""
    beta_min: float = _limited(0.0, min=0)
    """> 0: replaces the Laplace density's floor beta_min (docs/method.md 5.4: 1e-4); 0 keeps it."""
    beta_start: float = _limited(0.0, min=0)
    """> 0: beta is not learned but annealed log-linearly from beta_start to beta_end over the
    steps (unit-frame units; fast preset: a short run cannot wait for the learned beta to
    sharpen). 0: learnable beta (docs/method.md 5.4, the paper)."""
    beta_end: float = _limited(0.0025, gt=0)
    """Final beta of the anneal (unit frame; ~0.5 mm on DTU-scale scenes)."""
    snapshot_every: int = _limited(0, min=0)
    """Every this many field steps (and at the start), write the field's surface, its zero
    level at a coarse 96^3 grid in world units, to OUT/field/snapshots/step_NNNNNN.ply, and at
    the end OUT/field/snapshots/snapshots.png, the surface over the optimization from the first
    input view (`svolsdf.pipeline.snapshots`). Only while the field stage runs; 0 = none."""
    checkpoint_every: int = _limited(100, min=0)
    """Save a checkpoint every N steps (resume after a kill); 0 = never."""
    seed: int = _limited(0, min=0)
    """Random seed."""


@dataclass
class GuideConfig:
    mask_dilation: int | None = _limited(None, min=0)
    """Render the guide depth (docs/method.md 6.1) only inside the object masks dilated by this many
    pixels; the other pixels count as rendered with no surface (weight 0, so
    ``guide.low_weight_rule`` applies). None = every pixel (released). Scenes without masks render
    every pixel."""
    low_weight_rule: Literal["max", "mvs"] = "max"
    """Rendered-depth pixels with weight < 0.2: max (the map's maximum depth, released) |
    mvs (keep the stage-1 MVS depth)."""


@dataclass
class FusionConfig:
    dist: float = _limited(1.0, min=0)
    """Reprojection distance threshold in pixels (docs/method.md 6.3)."""
    rel: float = _limited(0.01, min=0)
    """Relative depth difference threshold (docs/method.md 6.3)."""
    min_views: int = _limited(1, min=0)
    """Minimum number of consistent source views (docs/method.md 6.3)."""
    conf: float = _limited(0.0, min=0, max=1)
    """Photometric confidence threshold (0 = off, as released; docs/method.md 9.2.9)."""
    surface: float = _limited(0.0, min=0)
    """A depth within this relative difference of the optimized surface's rendered depth (the
    guide) counts as one consistent source (`svolsdf.fusion.filter.FusionFilterConfig.surface`;
    0 = off, as released). Not used without a field (mvs-only)."""
    guided_dilation: int | None = _limited(None, min=0)
    """Object-mask dilation, in pixels, for the depth maps a field made: the field-guided stages
    2-3 (svolsdf mode) and the field's rendered depth (volsdf mode); None = the released 12 px
    (docs/method.md 6.3). The MVS cascade's own depth (mvs-only mode, the unguided set of
    ``fusion.unguided``) takes ``fusion.unguided_dilation``. Near the silhouette a field's
    depth carries its errors (a surface fattened into the background), and because those errors
    form one 3D surface the multi-view check passes them
    (`svolsdf.pipeline.options.mask_dilation`)."""
    unguided_dilation: int | None = _limited(None, min=0)
    """Object-mask dilation, in pixels, for the MVS cascade's own depth: mvs-only mode's and the
    unguided set of ``fusion.unguided``; None = the released 12 px
    (`svolsdf.fusion.filter.FusionFilterConfig.unguided_dilation`)."""
    unguided: bool = False
    """Also run MVS stages 2-3 centred on the stage-1 depth, as the backbone alone does, and
    give every view that unguided depth as a second hypothesis: each hypothesis is a reference
    in turn, and a source view is consistent when either of its hypotheses agrees
    (`fuse_depth_maps` ``alt_depths``). Where the field is wrong, its guide centres stages 2-3
    away from the surface and their narrow search cannot find it; the unguided pass still can.
    An extension: neither the paper nor the released code has it (svolsdf mode only).
    OUT/unguided/{depth,confidence}/<view>.npy."""
    network: str | None = _limited(None, choices=_backbone_names)
    """A learned backbone that can start from a depth map (patchmatchnet, with
    ``fusion.network_weights``), started from the field's guide depth in every input view; its
    depth joins fusion as a further hypothesis of each view, like ``fusion.unguided``'s (svolsdf
    mode only; OUT/network/{depth,confidence}/<view>.npy): a second matcher adds multi-view
    evidence where the main backbone fails. None = off (the paper; no weights ship with this
    package)."""
    network_weights: str | None = None
    """Weights file of ``fusion.network``."""


@dataclass
class PoissonConfig:
    depth: int = _limited(10, min=5, max=14)
    """Octree depth; the finest cell is the points' box / 2^depth."""
    trim: float = _limited(5.0, min=0, max=14)
    """Remove the surface whose sample density, in octree levels, is below this (0 = keep the
    closed surface)."""


@dataclass
class TSDFConfig:
    resolution: int = _limited(384, min=32, max=1024)
    """Voxels along the longest side of the fused points' box (the voxel is at most half the
    truncation)."""
    truncation_steps: float = _limited(4.0, gt=0)
    """Truncation distance in final-stage depth steps."""
    fill_holes: float = _limited(0.0, min=0)
    """Fill the TSDF mesh's holes up to this size (in point spacings, across) with the screened
    Poisson surface of the fused points (``mesh.poisson``'s options), leaving larger holes and
    the Poisson surface past the silhouettes out (`svolsdf.fusion.meshing.fill_small_holes`);
    0 = off."""


@dataclass
class MeshConfig:
    method: str = _limited("field", choices=_mesh_method_names)
    """Mesh source: field (the optimized field's zero level, the paper) | poisson (screened
    Poisson of OUT/points.ply, `svolsdf.fusion.poisson`) | tsdf (the final depth maps the fused
    points confirm, `svolsdf.fusion.tsdf`) | any method registered with
    `svolsdf.fusion.mesh_methods.register_mesh_method`. docs/meshing.md compares them."""
    resolution: int = _limited(256, min=8, max=2048)
    """Marching-cubes grid resolution in the unit frame (at most 2048: its 2048^3 samples
    already take tens of GB)."""
    format: Literal["ply", "obj"] = "ply"
    """ply | obj."""
    cull_unseen: bool = False
    """Also remove the faces no input view sees, i.e. whose centroid lies more than
    ``mesh.cull_tol`` behind the field's rendered depth in every view that contains it
    (`svolsdf.fusion.cull.cull_unseen`). Off as released (mask culling only, docs/method.md 8.3):
    the interior of a sparse-view reconstruction is unconstrained and may hold cavities."""
    cull_tol: float = _limited(0.01, min=0)
    """Relative depth slack of ``mesh.cull_unseen``."""
    watertight: bool = False
    """Keep the whole closed zero level (its largest connected part) instead of the parts the
    input views judge: no frustum, mask or visibility culling, so the mesh has no holes (for
    printing or simulation). Parts no view sees are the field's guess, so it scores worse
    against ground truth than the culled mesh."""
    fit_points: int = _limited(0, min=0)
    """Before marching cubes, refine the SDF grid for this many steps so that its zero level
    passes through the fused points (`svolsdf.field.fit`; svolsdf mode with the grid field and
    method field; 0 = off, the paper: the mesh is the optimized field's zero level). The finer
    MVS stages place depth more precisely than the surface that guided them, so the fused points
    are more accurate than the field; this brings the mesh to them. OUT/field/surface.pt."""
    free_space: bool = False
    """Remove faces that lie in space an input view saw as empty, i.e. more than
    ``mesh.free_space_steps`` final depth steps in front of the depth that view observed there
    (its final depth where the fused points confirm it; `svolsdf.fusion.observe`). Every mesh
    method; off in the paper's protocol (docs/method.md 8.3: mask culling only)."""
    free_space_steps: float = _limited(4.0, gt=0)
    """Tolerance of ``mesh.free_space`` in final-stage depth steps (docs/method.md 2.5: half
    the base interval, 1.3 mm on DTU)."""
    support: float = _limited(0.0, min=0)
    """Remove faces farther than this many point spacings (the median distance between
    neighbouring fused points) from every fused point; 0 = off. Surface that no point supports
    is a mesher's extrapolation over holes and past silhouettes."""
    poisson: PoissonConfig = dc_field(default_factory=PoissonConfig)
    """method poisson: the screened Poisson reconstruction."""
    tsdf: TSDFConfig = dc_field(default_factory=TSDFConfig)
    """method tsdf: the truncated signed distance of the observed depth."""


@dataclass
class Config:
    preset: Literal["fast", "draft", "paper", "released"] = "fast"
    """fast (default; minutes on a CPU) | draft (fast in about half the time: half the field
    steps, the plane sweep at 1.5x, other backbones at their own size; docs/presets.md) | paper
    (the paper's constants, docs/method.md; a GPU) | released (paper with the released code's
    settings and per-scan constants, docs/method.md 9)."""
    device: str = _limited("auto", pattern=r"auto|cpu|cuda(:\d+)?",
                           wanted="auto, cpu, cuda or cuda:N")
    """Where the work runs: auto (the GPU when there is one), cpu, cuda or cuda:N (GPU N)."""
    threads: int = _limited(0, min=0)
    """torch intra-op threads; 0 = the cores this process may run on (its CPU affinity), unless
    OMP_NUM_THREADS is set, which then decides (`svolsdf.pipeline.set_threads`)."""
    scene: SceneConfig = dc_field(default_factory=SceneConfig)
    """The scene: its folder, the input views and the working size."""
    mvs: MVSConfig = dc_field(default_factory=MVSConfig)
    """The MVS cascade: backbone, hypotheses, sources, scale."""
    field: FieldConfig = dc_field(default_factory=FieldConfig)
    """The neural surface (SDF and colour) and its initialisation."""
    train: TrainConfig = dc_field(default_factory=TrainConfig)
    """The optimization: mode, losses, sampler, schedule."""
    guide: GuideConfig = dc_field(default_factory=GuideConfig)
    """The guide: the optimized surface's rendered depth that centres MVS stages 2-3."""
    fusion: FusionConfig = dc_field(default_factory=FusionConfig)
    """Fusion of the final depth maps into points.ply."""
    mesh: MeshConfig = dc_field(default_factory=MeshConfig)
    """The mesh: its method, resolution and cleaning."""


def choices(option: str) -> tuple[str, ...]:
    """The strings an option allows, in their declared order: the one list of a choice
    (``choices("train.mode")``, ``choices("train.ablation")``; None, where the option takes it,
    is not among them). A ``Literal``'s values, or for an option whose ``choices`` limit names a
    registry (``choices("mvs.backbone")``) the names registered now.

    Raises:
        KeyError: ``option`` is no option, or takes no ``Literal`` and names no registry.
    """
    cls, *path = (Config, *option.split("."))
    tp: Any = None
    owner: Any = None
    for name in path:
        hints = get_type_hints(cls)
        if name not in hints:
            raise KeyError(f"{option}: no such option")
        owner, tp = cls, hints[name]
        cls = tp
    args = get_args(tp) if get_origin(tp) in (Union, types.UnionType) else (tp,)
    found = tuple(a for t in args if get_origin(t) is Literal for a in get_args(t))
    if not found and dataclasses.is_dataclass(owner):
        field = next(f for f in dataclasses.fields(owner) if f.name == path[-1])
        registry = field.metadata.get("limits", {}).get("choices")
        found = tuple(registry()) if registry is not None else ()
    if not found:
        raise KeyError(f"{option}: not a choice (no Literal or registry)")
    return found
