"""A run: its config, input views, scene, stage-1 volumes and field, read from its folder.

`Run.open` gives the commands that work on a finished run folder (render, evaluate, ...)
everything the reconstruction used, without running a stage; `svolsdf.pipeline.Pipeline` is
the `Run` that computes its stages.
"""

from __future__ import annotations

import logging
from pathlib import Path

import torch

from svolsdf.config import Config
from svolsdf.errors import InputError
from svolsdf.field.saved import load_field, read_field
from svolsdf.mvs.volume import ProbabilityVolume
from svolsdf.pipeline.keys import stage_keys
from svolsdf.pipeline.machine import resolve_device
from svolsdf.pipeline.options import has_field, is_baseline, runs_mvs1
from svolsdf.pipeline.rundir import RunDir, is_unreadable_file, one_line
from svolsdf.pipeline.views import auto_views, default_views, test_views
from svolsdf.scene.scene import Scene
from svolsdf.scene.size import working_size

__all__ = ["Run", "load_model"]

log = logging.getLogger(__name__)


def load_model(model, path: Path) -> None:
    """Load a saved field into ``model``.

    Raises:
        InputError: the file is unreadable (truncated, not a field file).
        RuntimeError: it holds another field than ``model`` (torch's message).
    """
    try:
        state = read_field(path)
    except Exception as e:
        if not is_unreadable_file(e):  # a bug, not a truncated or corrupt file
            raise
        raise InputError(f"{path}: not a readable field file ({one_line(e)})") from None
    # a grid field takes the stored box and grid shapes (GridSDFField._load_from_state_dict)
    load_field(model, state)


class Run:
    """The config, views, scene, stage-1 volumes and field of one run folder.

    Args:
        cfg: the run's configuration (``cfg.scene.path`` set).
        out: the run folder.
        progress: show progress bars.

    Attributes:
        cfg, dir (`RunDir`), out (its path), device, progress; after `load`: views (input ids),
        test_view_ids, all_view_ids (the scene's); ``keys`` the stage keys once computed.
    """

    def __init__(self, cfg: Config, out: str | Path, progress: bool = False):
        self.cfg = cfg
        self.dir = RunDir(out)
        self.out = self.dir.root
        self.progress = progress
        self.device = resolve_device(cfg.device)
        self.keys: dict[str, str] | None = None
        self._scene: Scene | None = None
        self._volumes1: list[ProbabilityVolume] | None = None
        self._reg1: tuple | None = None  # (volumes1, their regressed copies)
        self._model = None

    # ------------------------------------------------------------------ opening
    @classmethod
    def open(cls, out: str | Path, progress: bool = False, field: bool = True) -> Run:
        """A finished run with its trained field loaded (``field``); never runs a stage.

        Args:
            out: a run folder written by ``svolsdf reconstruct`` (config.yaml, views.json,
                field/model.pt; field/stage2/model.pt instead when the finer-stage optimization
                made one).
            progress: progress bars.
            field: load the field (the run must have one).

        Raises:
            InputError: OUT is not a run folder, its mode has no field, field/model.pt is
                missing or does not match the config (the message names the folder).
        """
        from svolsdf.config import load_config, validate_config
        from svolsdf.io.paths import input_dir

        out = input_dir(out, "run folder")
        rd = RunDir(out)
        missing = rd.missing_run_files()
        if missing:
            raise InputError(f"{out}: not a run folder ({missing} missing); run "
                             f"svolsdf reconstruct SCENE -o {out} first")
        run = cls(validate_config(load_config(rd.config_file)), out, progress=progress)
        if field:
            run._open_field()
        return run

    def _open_field(self) -> None:
        out, cfg = self.out, self.cfg
        if not self.has_field():
            raise InputError(f"{out}: the run (mode {cfg.train.mode!r}, ablation "
                             f"{cfg.train.ablation!r}) has no neural field to render")
        model_path = self.dir.model
        if not model_path.is_file():
            raise InputError(f"{out}: the field is not finished ({model_path} is missing); let "
                             f"svolsdf reconstruct finish first")
        self.load()
        self.keys = self.stage_keys()
        # the grid field's box comes from stage-1 MVS when the run had it: load it the same way
        stage1 = [self.dir.stage1_file(v) for v in self.views]
        if runs_mvs1(cfg) and all(f.is_file() for f in stage1):
            try:
                self._volumes1 = [ProbabilityVolume.load(f) for f in stage1]
            except Exception as e:  # a truncated or corrupt .npz
                raise InputError(f"{out}: a stage-1 volume in {stage1[0].parent} is unreadable "
                                 f"({' '.join(str(e).split())[:200]}); rerun svolsdf "
                                 f"reconstruct -o {out}: it computes it again") from None
        from svolsdf.pipeline.legacy_keys import legacy_stage_keys

        if not (self.dir.done("field", self.keys["field"]) or self.dir.done(
                "field", legacy_stage_keys(cfg, self.views)["field"])):  # an earlier formula's
            # a config or package change alters the stage hash; rendering never retrains
            log.warning("%s: the stored field was trained under another config hash (edited "
                        "config or newer package); rendering the stored field/model.pt as it "
                        "is", out)
        if cfg.mvs.finer_stage_optimization and self.dir.refined_model.is_file():
            # the field after the finer-stage optimization (as the mesh uses)
            model_path = self.dir.refined_model
        model = self.build_model()
        try:
            load_model(model, model_path)
        except InputError as e:  # truncated or corrupt: only a rerun can make it again
            raise InputError(f"{e}; rerun svolsdf reconstruct -o {out}: it trains the field "
                             "again") from None
        except RuntimeError as e:
            raise InputError(f"{model_path}: does not match the field of {self.dir.config_file} "
                             f"({e})") from None
        self._model = model.to(self.device)

    # ------------------------------------------------------------------ scene
    def load(self) -> Scene:
        """The input views at the working size (images, masks, cameras)."""
        if self._scene is not None:
            return self._scene
        from svolsdf.scene.loaders import load_scene

        sc = self.cfg.scene
        head = load_scene(sc.path, load_images=False, lighting=sc.lighting)
        self.all_view_ids = list(head.view_ids)
        if sc.views:
            views = list(sc.views)
        elif sc.view_selection == "auto":
            views = auto_views(head, sc.num_views)
            log.info("views auto: picked %s of %d (reference %d)", views, len(head),
                     views[0])
        elif sc.view_selection == "default":
            views = default_views(head, sc.num_views)
        else:
            raise InputError(f"scene.view_selection: unknown {sc.view_selection!r} (default "
                             f"or auto)")
        for v in views:
            head.index(v)  # raises a clear error for unknown ids
        if len(views) < 2:
            raise InputError(f"need at least 2 input views, got {views}")
        if sc.image_size:
            size = tuple(int(x) for x in sc.image_size)
        else:
            size = working_size(head.width, head.height)
        self.views = views
        self.test_view_ids = test_views(head, views)
        self._scene = load_scene(sc.path, views=views, image_size=size, lighting=sc.lighting)
        return self._scene

    @property
    def scene(self) -> Scene:
        return self.load()

    def stage_keys(self) -> dict[str, str]:
        """{stage: key} of this run's config and input views (`svolsdf.pipeline.keys`)."""
        self.load()
        return stage_keys(self.cfg, self.views)

    def has_field(self) -> bool:
        """The run fits a neural field."""
        return has_field(self.cfg)

    # ------------------------------------------------------------------ stage 1, field
    @property
    def volumes1(self) -> list[ProbabilityVolume] | None:
        """The stage-1 volumes of the input views (None: not computed or not loaded)."""
        return self._volumes1

    @volumes1.setter
    def volumes1(self, volumes: list[ProbabilityVolume] | None) -> None:
        self._volumes1 = volumes

    def regressed_volumes1(self) -> list[ProbabilityVolume] | None:
        """The stage-1 volumes with depth = sum_k P_k d_k, the regression of docs/method.md 2.4
        (`svolsdf.mvs.backbone.with_expected_depth`), computed once."""
        if self._volumes1 is None:
            return None
        if self._reg1 is None or self._reg1[0] is not self._volumes1:
            from svolsdf.mvs.backbone import with_expected_depth

            self._reg1 = (self._volumes1, with_expected_depth(self._volumes1))
        return self._reg1[1]

    def field_bounds(self) -> torch.Tensor:
        """(2, 3) unit-frame box of the object (`svolsdf.field.bounds.field_bounds`): from the
        stage-1 MVS depth where the run has it, else from the views' frusta."""
        from svolsdf.field.bounds import field_bounds

        use = self._volumes1 is not None and not is_baseline(self.cfg)
        return field_bounds(self.load(), self.regressed_volumes1() if use else None)

    def build_model(self):
        """A fresh `SurfaceModel` of the config (`svolsdf.pipeline.builders.build_model`)."""
        from svolsdf.pipeline.builders import build_model

        return build_model(self.cfg, self.field_bounds)

    def model(self):
        """The run's field (loaded by `open`)."""
        if self._model is None:
            raise InputError(f"{self.out}: no field loaded (Run.open(..., field=True))")
        return self._model

    def set_model(self, model) -> None:
        """Use ``model`` as the run's field (e.g. one trained outside the stages)."""
        self._model = model

    def unit_near_far(self) -> torch.Tensor:
        """(V, 2) unit-frame z-depth range of the input views, padded by 10 %."""
        from svolsdf.pipeline.builders import unit_near_far

        return unit_near_far(self.load())

    def render_views(self, cameras_unit, near_far=None, chunk: int = 4096,
                     keys=("depth", "opacity", "rgb", "normals"),
                     pixels: torch.Tensor | None = None, model=None,
                     desc: str = "render the field") -> dict[str, torch.Tensor]:
        """Render every camera of ``cameras_unit`` with the field (``model``, by default the
        run's) and the eval-mode sampler (`svolsdf.render.views.render_field_views`).

        Args:
            pixels: optional (V, H, W) bool; only these pixels are rendered.
            desc: the name of the progress bar over the cameras.

        Returns:
            dict of (V, H, W, ...) tensors: depth (unit-frame z-depth), opacity, rgb, normals.
        """
        from svolsdf.pipeline.builders import build_sampler
        from svolsdf.render.views import render_field_views

        model = self.model() if model is None else model
        return render_field_views(model, build_sampler(self.cfg, None, training=False),
                                  cameras_unit, near_far, chunk=chunk, keys=keys,
                                  pixels=pixels, device=self.device, desc=desc)

    def guide_pixels(self) -> torch.Tensor | None:
        """(V, H, W) bool: the pixels whose guide depth is rendered
        (`svolsdf.render.views.guide_pixels` of ``guide.mask_dilation``), or None."""
        from svolsdf.render.views import guide_pixels

        scene = self.load()
        masks = scene.masks if self.cfg.scene.use_masks else None
        return guide_pixels(masks, self.cfg.guide.mask_dilation)
