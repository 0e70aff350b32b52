"""The `MVSBackbone` protocol, the backbone registry, and helpers shared by all backbones.

A backbone turns a `Scene` into per-view `ProbabilityVolume`s, one cascade stage at a time
(docs/architecture.md "Interfaces"). Every view of the scene is the reference once; its sources are
the other views of the scene, ordered by ``scene.source_views`` (docs/method.md 1.4).

Stage k (1-based, of ``num_stages`` = 3) works at 1 / 2^(3 - k) of the backbone's MVS size
(stage 1 at 1/4, stage 2 at 1/2, stage 3 at full size), like CasMVSNet (docs/method.md 1.3, 2.5).
The MVS size is a multiple of the scene's working size (`mvs_size`): 2x for the plane sweep and for
CasMVSNet (x2_mvsres), as the released code runs (docs/method.md 9.2.2).

Backbones are created by name with :func:`get_backbone`. Each is a class decorated with
``@register_backbone("name")``; the modules of `svolsdf.mvs` that use the decorator are imported the
first time a name is asked for (no import work happens before), so adding a backbone is one
module with one decorator. Built in:

- ``planesweep``: `svolsdf.mvs.planesweep.PlaneSweepBackbone` (training-free, the default)
- ``casmvsnet``: `svolsdf.mvs.casmvsnet.CasMVSNetBackbone` (docs/method.md 2; needs ``weights``)
- ``patchmatchnet``: `svolsdf.mvs.adapters.PatchmatchNetBackbone` (TorchScript weights)

A backbone written elsewhere (a test, a plugin) is registered when its module is imported.
"""

from __future__ import annotations

import inspect
from abc import ABC, abstractmethod
from dataclasses import asdict, fields, is_dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from svolsdf.errors import InputError
from svolsdf.mvs.volume import ProbabilityVolume
from svolsdf.registry import Registry
from svolsdf.scene.cameras import Cameras
from svolsdf.scene.scene import Scene

__all__ = [
    "BACKBONES",
    "MAX_SOURCES",
    "select_sources",
    "MVSBackbone",
    "get_backbone",
    "takes_device",
    "backbone_signature",
    "starts_from_depth",
    "backbone_options",
    "backbone_scale_problem",
    "backbone_config_class",
    "register_backbone",
    "unregister_backbone",
    "available_backbones",
    "mvs_size",
    "stage_size",
    "stage_cameras",
    "expected_depth",
    "with_expected_depth",
    "mode_depth",
    "photometric_confidence",
    "volume_from_prob",
    "check_depth_ranges",
    "upsample_depth",
]

NUM_STAGES = 3


class MVSBackbone(ABC):
    """A multi-view-stereo backbone producing probability volumes stage by stage.

    Subclasses implement :meth:`stage`. They are built by :meth:`create` (called by
    :func:`get_backbone`), which by default rejects a ``weights`` path and passes ``**cfg`` to the
    constructor; backbones with weights override it.
    """

    #: registry name
    name: str = "backbone"
    #: number of cascade stages
    num_stages: int = NUM_STAGES
    #: the dataclass its ``**cfg`` keywords fill (None: the keywords are the whole config)
    config_class: type | None = None
    #: it can start a stage from a given depth map (``fusion.network``; PatchmatchNet can)
    can_start_from_depth: bool = False
    #: config fields under the names the earlier stage-key formula hashed them (`signature`;
    #: `svolsdf.pipeline.legacy_keys`): a field renamed to its option's name keeps the name it
    #: had when run folders were written, so that formula still recognises their MVS stages
    signature_names: dict[str, str] = {}

    @classmethod
    def signature(cls, weights=None, **cfg) -> dict:
        """Everything that decides this backbone's output, for cache keys (`svolsdf.pipeline`).

        The full config with its defaults (so that a changed default invalidates cached volumes),
        its fields under `signature_names`, and, with weights, the file's resolved path, size
        and modification time.
        """
        try:
            conf = asdict(cls.config_class(**cfg)) if cls.config_class is not None else dict(cfg)
        except TypeError as e:
            raise InputError(f"{cls.name} backbone: {e}") from None
        conf = {cls.signature_names.get(k, k): v for k, v in conf.items()}
        sig: dict = {"backbone": cls.name, "config": conf}
        if weights is not None:
            from svolsdf.io.paths import user_path

            p = user_path(weights)
            st = p.stat() if p.is_file() else None
            sig["weights"] = [str(p.resolve()), st.st_size, st.st_mtime_ns] if st else str(p)
        return sig

    @classmethod
    def scale_problem(cls, scale: float | None) -> str | None:
        """Why this backbone cannot run at ``mvs.scale`` = ``scale`` (in words, for a message),
        or None when it can. Unset (None, the backbone's own size) always can; the base class
        takes 1 or 2 where the config class has ``x2_mvsres`` (CasMVSNet) and nothing else
        otherwise (the adapters run at the working size). A backbone that reads ``mvs.scale``
        itself (the plane sweep) overrides it with its own rule."""
        if scale is None:
            return None
        if not hasattr(cls.config_class, "x2_mvsres"):
            return f"the {cls.name} backbone runs at the working size only"
        if float(scale) not in (1.0, 2.0):
            return f"{cls.name} runs at 1 or 2 x the working size (x2_mvsres)"
        return None

    @classmethod
    def options(cls, mvs) -> dict:
        """This backbone's ``**cfg`` keywords from the run's MVS section ``mvs`` (a
        `svolsdf.config.MVSConfig`): every field of its config class that is an option of the
        section, under the same name (``ndepths``, ``width``, ``inverse_depth``,
        ``max_sources``, ``native_images``, ``guide_network``, ``crop_to_masks``, ...; a
        backbone without a config class takes the first four), but ``scale``, whose None
        means the backbone's own size: set, it gives ``x2_mvsres`` (``mvs.scale`` 1 or 2)
        where the config class has it. A backbone that reads ``mvs.scale`` otherwise
        overrides this.

        Raises:
            InputError: ``mvs.scale`` this backbone cannot run at.
        """
        why = cls.scale_problem(mvs.scale)
        if why is not None:
            raise InputError(f"mvs.scale = {mvs.scale}: {why}; leave mvs.scale unset for the "
                             "backbone's own size")
        conf = cls.config_class
        names = ([f.name for f in fields(conf)] if conf is not None and is_dataclass(conf)
                 else ["ndepths", "width", "inverse_depth", "max_sources"])
        kw = {n: getattr(mvs, n) for n in names if n != "scale" and hasattr(mvs, n)}
        if "ndepths" in kw:
            kw["ndepths"] = tuple(int(x) for x in kw["ndepths"])
        if mvs.scale is not None and "x2_mvsres" in names:
            kw["x2_mvsres"] = float(mvs.scale) == 2.0
        return kw

    @classmethod
    def create(cls, weights=None, **cfg) -> MVSBackbone:
        """Build the backbone from an optional weights path and config keywords."""
        if weights is not None:
            raise InputError(f"{weights}: the {cls.name!r} backbone takes no weights")
        return cls(**cfg)

    @abstractmethod
    def stage(
        self,
        k: int,
        scene: Scene,
        ref_ids: list[int] | None = None,
        guide_depth: dict[int, Tensor] | None = None,
        prev: dict[int, ProbabilityVolume] | None = None,
    ) -> list[ProbabilityVolume]:
        """Run cascade stage ``k`` for reference views ``ref_ids`` (default: every view).

        Args:
            k: stage, 1-based (1..num_stages).
            scene: the views (images (V,3,H,W), cameras, depth ranges) at the working size.
            ref_ids: view ids to use as reference, default all of ``scene.view_ids``.
            guide_depth: view id -> (H', W') z-depth (world units, any size) that centres this
                stage's hypotheses instead of the previous stage's depth (docs/method.md 6.1).
                Ignored at stage 1.
            prev: view id -> the previous stage's volume of that view; required at k > 1 for views
                without a guide depth.

        Returns:
            One `ProbabilityVolume` per reference view, in ``ref_ids`` order, at
            :func:`stage_size` (k).
        """

    def __call__(self, *args, **kwargs) -> list[ProbabilityVolume]:
        return self.stage(*args, **kwargs)


# --------------------------------------------------------------------------- registry
def _named(name: str, cls: type[MVSBackbone]) -> type[MVSBackbone]:
    cls.name = name
    return cls


#: name -> backbone class; the modules of `svolsdf.mvs` that use ``@register_backbone(...)`` are
#: imported the first time a name is asked for (`svolsdf.registry.Registry`)
BACKBONES: Registry[type[MVSBackbone]] = Registry("MVS backbone", "svolsdf.mvs",
                                                  "register_backbone", sort=True, entry=_named)

#: ``@register_backbone(name)``: a class decorator adding a backbone (its ``create`` builds
#: it); in a module of `svolsdf.mvs` it is found without any other edit
register_backbone = BACKBONES.register
#: withdraw the backbone registered as a name (a test's, say); unknown names are ignored
unregister_backbone = BACKBONES.remove
#: the names accepted by `get_backbone`, in alphabetical order
available_backbones = BACKBONES.names
_backbone_class = BACKBONES.get


def backbone_config_class(name: str) -> type | None:
    """The config dataclass of the backbone called ``name`` (None if it has none)."""
    return _backbone_class(name).config_class


def starts_from_depth(name: str) -> bool:
    """The backbone called ``name`` can start from a depth map (``can_start_from_depth``: its
    guided stages read ``mvs.guide_network``)."""
    return bool(_backbone_class(name).can_start_from_depth)


def backbone_options(name: str, mvs) -> dict:
    """`MVSBackbone.options` of the backbone called ``name``: its keywords from the MVS section
    ``mvs`` of a run's config.

    Raises:
        InputError: unknown name, or an ``mvs.scale`` the backbone cannot run at.
    """
    return _backbone_class(name).options(mvs)


def backbone_scale_problem(name: str, scale: float | None) -> str | None:
    """`MVSBackbone.scale_problem` of the backbone called ``name``: why it cannot run at
    ``mvs.scale`` = ``scale``, None when it can (`svolsdf.config.validate_config` asks before any
    work)."""
    return _backbone_class(name).scale_problem(scale)


def backbone_signature(name: str, weights=None, **cfg) -> dict:
    """`MVSBackbone.signature` of the backbone called ``name`` (no weights are loaded)."""
    return _backbone_class(name).signature(weights=weights, **cfg)


def takes_device(name: str) -> bool:
    """Whether the backbone called ``name`` runs on a chosen torch device (its config has a
    ``device`` field, or its constructor a ``device`` argument)."""
    cls = _backbone_class(name)
    conf = cls.config_class
    if conf is not None and is_dataclass(conf) and "device" in {f.name for f in fields(conf)}:
        return True
    return "device" in inspect.signature(cls.__init__).parameters


def get_backbone(name: str, weights=None, device: torch.device | str | None = None,
                 **cfg) -> MVSBackbone:
    """Create the backbone called ``name``.

    Args:
        name: one of :func:`available_backbones` ("planesweep", "casmvsnet", "patchmatchnet").
        weights: path to the weights file, for backbones that need one.
        device: torch device the backbone runs on (None: its config's, the CPU by default);
            ignored by backbones that cannot choose (`takes_device`). Where the work runs, not
            what it computes: the pipeline passes it here and not to `backbone_signature`, so
            cached volumes stay valid on another device.
        **cfg: fields of the backbone's config.

    Raises:
        InputError: unknown name, or a weights problem reported by the backbone.
    """
    if device is not None and takes_device(name):
        cfg["device"] = str(device)
    return _backbone_class(name).create(weights=weights, **cfg)


# --------------------------------------------------------------------------- helpers
def mvs_size(width: int, height: int, scale: float = 1.0) -> tuple[int, int]:
    """(W, H) of a backbone's finest stage: ``scale`` x the working size, rounded."""
    return max(1, round(width * scale)), max(1, round(height * scale))


def stage_size(k: int, width: int, height: int, num_stages: int = NUM_STAGES) -> tuple[int, int]:
    """(W_k, H_k) of stage ``k``: the working size divided by 2^(num_stages - k), rounded."""
    if not 1 <= k <= num_stages:
        raise ValueError(f"stage must be in 1..{num_stages}, got {k}")
    s = 2 ** (num_stages - k)
    return max(1, round(width / s)), max(1, round(height / s))


def stage_cameras(cameras: Cameras, k: int, num_stages: int = NUM_STAGES) -> Cameras:
    """Cameras resized to stage ``k``'s size (docs/method.md 1.3; c' = s (c + 0.5) - 0.5)."""
    W, H = stage_size(k, cameras.width, cameras.height, num_stages)
    return cameras.resize(W, H)


def expected_depth(prob: Tensor, depths: Tensor) -> Tensor:
    """Soft depth regression sum_k P_k d_k (docs/method.md 2.4).

    Args:
        prob: (..., D, H, W) probabilities over D.
        depths: (..., D, H, W) hypothesis depths (broadcastable).

    Returns:
        (..., H, W) expected depth.
    """
    return (prob * depths).sum(-3)


def with_expected_depth(volumes: list[ProbabilityVolume]) -> list[ProbabilityVolume]:
    """Copies of ``volumes`` whose depth (H, W) is the regression sum_k P_k d_k
    (docs/method.md 2.4), whatever estimate the backbone stored.

    The field stage (box, SDF initialisation, the ablations' MVS depth) uses this depth: the
    plane sweep stores the main-mode depth (`PlaneSweepConfig.depth_radius`), which centres its
    own next stage better, while the smoother full expectation initialises the SDF grid better
    (synthetic benchmark scene, points Chamfer 2.12 vs 2.34 mm; benchmarks/results/history/
    fast_preset.md).
    """
    from dataclasses import replace

    return [replace(v, depth=expected_depth(v.prob.float(), v.depths.float()).to(v.depth.dtype))
            for v in volumes]


def mode_depth(prob: Tensor, depths: Tensor, radius: int = 2) -> Tensor:
    """Soft depth regression restricted to the main mode: sum_{|k-k*|<=r} P_k d_k / sum P_k.

    k* = argmax_k P_k. Equal to `expected_depth` for a unimodal distribution inside the window;
    for a bimodal one (a training-free cost with a second, wrong match) it stays on the stronger
    mode instead of landing between the two, on no surface.

    Args:
        prob: (..., D, H, W) probabilities over D.
        depths: (..., D, H, W) hypothesis depths (broadcastable to prob).
        radius: r, hypotheses on each side of the argmax.

    Returns:
        (..., H, W) depth.
    """
    D = prob.shape[-3]
    k = torch.arange(D, device=prob.device).view(D, 1, 1)
    kstar = prob.argmax(-3, keepdim=True)
    win = ((k - kstar).abs() <= radius).to(prob.dtype)
    pw = prob * win
    return (pw * depths).sum(-3) / pw.sum(-3).clamp_min(1e-12)


def photometric_confidence(prob: Tensor) -> Tensor:
    """CasMVSNet's 4-bin photometric confidence (docs/method.md 2.4).

    s4_k = sum_{j=k-1}^{k+2} P_j (zero padded), k* = floor(sum_k P_k k) clamped to [0, D-1],
    conf = s4_{k*}.

    Args:
        prob: (..., D, H, W) probabilities over D.

    Returns:
        (..., H, W) confidence in [0, 1].
    """
    D = prob.shape[-3]
    lead = prob.shape[:-3]
    p = prob.reshape(-1, 1, D, *prob.shape[-2:])
    s4 = 4 * F.avg_pool3d(F.pad(p, (0, 0, 0, 0, 1, 2)), (4, 1, 1), stride=1)[:, 0]
    idx = torch.arange(D, device=prob.device, dtype=prob.dtype).view(D, 1, 1)
    kstar = (p[:, 0] * idx).sum(1).floor().clamp(0, D - 1).long()
    conf = torch.gather(s4, 1, kstar[:, None])[:, 0]
    return conf.reshape(*lead, *prob.shape[-2:])


def volume_from_prob(
    prob: Tensor,
    depths: Tensor,
    cameras: Cameras,
    view_id: int,
    stage: int,
    inverse_depth: bool = False,
    depth_radius: int | None = None,
) -> ProbabilityVolume:
    """Assemble a `ProbabilityVolume` from (D, H, W) probabilities and hypotheses.

    depth = expectation (docs/method.md 2.4), or with ``depth_radius`` r the expectation over the
    2r+1 hypotheses around the argmax (`mode_depth`); confidence = 4-bin sum (docs/method.md 2.4).
    """
    depth = (expected_depth(prob, depths) if depth_radius is None
             else mode_depth(prob, depths, depth_radius))
    return ProbabilityVolume(
        depths=depths,
        prob=prob,
        depth=depth,
        confidence=photometric_confidence(prob),
        cameras=cameras,
        view_id=int(view_id),
        stage=int(stage),
        inverse_depth=inverse_depth,
    )


#: Source views per reference (docs/method.md 1.4: the released code feeds at most 5 views).
MAX_SOURCES = 4


def select_sources(scene: Scene, ref_id: int, max_sources: int = MAX_SOURCES) -> list[int]:
    """Source view ids of reference ``ref_id`` among the loaded views: `Scene.source_views`
    order (pair score first, docs/method.md 1.4), at most ``max_sources`` of them (<= 0: all).

    The released code builds each reference's MVS input from at most 5 views (the reference and
    4 sources), so with 3 input views every other view is a source, as here; with more inputs the
    cap keeps the cost volume's work linear in the number of views instead of quadratic.
    """
    src = scene.source_views(ref_id)
    return src if max_sources <= 0 else src[:max_sources]


def check_depth_ranges(scene: Scene, ref_ids: list[int] | None = None) -> None:
    """Raise InputError naming the view when its depth range is empty, negative or not finite."""
    for vid in ref_ids if ref_ids is not None else scene.view_ids:
        near, far = (float(x) for x in scene.depth_range[scene.index(vid)])
        if not (torch.isfinite(torch.tensor([near, far])).all() and 0 < near < far):
            raise InputError(
                f"{scene.path}: view {vid} has depth range [{near:g}, {far:g}]; it must satisfy "
                "0 < near < far (fix the scene's depth range or cameras)"
            )


def upsample_depth(depth: Tensor, width: int, height: int) -> Tensor:
    """Bilinearly resize (H, W) depth to (height, width), align_corners=False
    (docs/method.md 2.5)."""
    if depth.shape == (height, width):
        return depth
    return F.interpolate(
        depth[None, None].float(), size=(height, width), mode="bilinear", align_corners=False
    )[0, 0]
