"""The reconstruction pipeline: every stage in order, each result kept on disk, with resume.

Stages (docs/architecture.md "Data flow"; docs/method.md 0 and 6):

1. ``mvs1``: stage-1 probability volumes of the input views (OUT/mvs/stage1/<id>.npz).
2. ``field``: the S-VolSDF optimization (OUT/field/model.pt; checkpoints in OUT/field/).
3. ``guide``: rendered z-depth of the input views, which replaces the stage-1 depth
   (docs/method.md 6.1; OUT/field/render_depth/<id>.npy).
4. ``mvs23``: stages 2 and 3 centred on that depth (OUT/depth/<id>.npy; ``mvs.save_volumes``).
5. ``unguided`` (``fusion.unguided``, the fast preset's; not in the paper): stages 2 and 3
   centred on the stage-1 depth, as the backbone alone runs them (OUT/unguided/depth/<id>.npy);
   fusion takes them as every view's second depth hypothesis.
6. ``fusion``: geometric-consistency filtering and fusion (OUT/points.ply, docs/method.md 6.3).
7. ``mesh``: the mesh the config asks for (`svolsdf.pipeline.mesh.build_mesh`; OUT/mesh.ply).

A stage is skipped on a rerun when its marker in OUT/stages.json carries the same config hash
(`svolsdf.pipeline.keys`) and its inputs (images, masks, cameras) are those it finished with; a
changed config or input reruns that stage and everything after it that reads it, and OUT/log says
which input changed. Each stage also records the digest of the config.yaml it finished (or was
last reused) under, so evaluate and report can tell outputs of an earlier config. The
optimization resumes from its last checkpoint after a kill. All files are written atomically
(`svolsdf.pipeline.rundir`). The algorithms live in their components; this module orders them.
"""

from __future__ import annotations

import logging
import os
import time
from pathlib import Path

import numpy as np
import torch

from svolsdf.config import Config, save_config, validate_config
from svolsdf.errors import (
    InputError,
    RunInterrupted,
    interrupted,
    raise_if_interrupted,
    watch_interrupts,
)
from svolsdf.field.saved import save_field
from svolsdf.io.paths import user_path
from svolsdf.mvs.volume import ProbabilityVolume
from svolsdf.pipeline import builders, options
from svolsdf.pipeline.context import GuideRender
from svolsdf.pipeline.keys import describe_changes, input_keys, input_manifest
from svolsdf.pipeline.loaded_run import Run, load_model
from svolsdf.pipeline.machine import set_threads
from svolsdf.pipeline.records import StageRecords, load_maps
from svolsdf.pipeline.rundir import one_line, save_npy

__all__ = ["Pipeline"]

# the run's messages in OUT/log keep the logger name they always had
log = logging.getLogger("svolsdf.pipeline")

class Pipeline(StageRecords, Run):
    """Runs a `Config` into an output folder.

    Args:
        cfg: the run's configuration (``cfg.scene.path`` must be set).
        out: the output folder (created; must not be a file).
        progress: show progress bars.
    """

    def __init__(self, cfg: Config, out: str | Path, progress: bool = True):
        cfg = validate_config(cfg)  # a bad value fails here, before any stage
        out = user_path(out)
        if out.exists() and not out.is_dir():
            raise InputError(f"{out}: output path exists and is not a folder")
        if not cfg.scene.path:
            raise InputError("no scene given (scene.path is empty)")
        super().__init__(cfg, out, progress=progress)
        self.timing: dict[str, dict] = {}
        self._net: tuple | None = None  # (its config, the fusion network's backbone)
        self._stage = "setup"  # the stage run() is in, for the message of an interrupt
        self._trainer = None  # the field stage's Trainer while it runs (its step, ditto)
        self.input_keys: dict[str, str] | None = None  # set by run() (`keys.input_keys`)
        self._config_digest: str | None = None  # of OUT/config.yaml, set by run()
        self._input_changes: list[str] = []
        self._logged: set[str] = set()  # the stages whose reuse or rerun OUT/log explained
        self._reruns: dict[str, str] = {}  # stage -> the file that could not be read, and why

    def model(self):
        """The fitted field (runs the field stage when it has not run in this process)."""
        if self._model is None:
            self.stage_field()
        return self._model

    # ------------------------------------------------------------------ run
    def run(self) -> dict:
        """Run (or resume) every stage; returns a summary dict.

        Raises:
            InputError: bad input (also written to OUT/log).
            RunInterrupted: Ctrl-C; its message, also in OUT/log, names the stage that stopped
                and says that a rerun resumes.
        """
        from svolsdf.io.paths import output_dir

        t_all = time.perf_counter()
        self._check_options()
        new = not self.out.exists()
        output_dir(self.out)
        with self.dir.lock(), watch_interrupts():
            handler = self.dir.attach_log()
            finished = False
            try:
                res = self._run(t_all)
                raise_if_interrupted()  # one that something swallowed: still status 130
                finished = True
                return res
            except BaseException as e:
                # an error a library made of the Ctrl-C counts as the Ctrl-C (svolsdf.errors)
                if isinstance(e, KeyboardInterrupt) or interrupted():
                    msg = self._interrupt_message()
                    self.dir.log_to_file(log, logging.WARNING, msg)
                    raise RunInterrupted(msg) from None
                if isinstance(e, Exception):  # the command line prints an InputError
                    self.dir.log_to_file(log, logging.ERROR, f"error: {e}" if isinstance(
                        e, InputError) else f"failed in stage {self._stage}: {one_line(e)}",
                        exc_info=not isinstance(e, InputError))
                raise
            finally:
                if handler is not None:  # this run's OUT/log only gets this run's messages
                    logging.getLogger("svolsdf").removeHandler(handler)
                    handler.close()
                if not finished and new and self._stage == "setup":
                    self._discard_new_folder()

    def _discard_new_folder(self) -> None:
        """Remove the folder this run created when it stopped before any stage (a scene that
        fails its checks leaves no OUT behind); only the run's own bookkeeping is removed."""
        import shutil

        own = {".svolsdf.lock", "log", "config.yaml", "views.json", "stages.json"}
        try:
            if {p.name for p in self.out.iterdir()} <= own:
                # a link to a folder this run made: the folder goes, the link stays as it was
                shutil.rmtree(os.path.realpath(self.out))
        except OSError:
            pass

    def _check_options(self) -> None:
        """Fail on a missing scene folder, one that no scene format recognises, or on backbone
        options (weights, scale) that cannot run before the output folder is touched."""
        from svolsdf.scene.checks import check_output_folder
        from svolsdf.scene.loaders import scene_folder

        # missing, a dangling link, a file, or a folder no format reads: refused before OUT/log
        # exists
        path = scene_folder(self.cfg.scene.path)
        if str(path) != str(self.cfg.scene.path):  # "~/scans/a" from a config file
            self.cfg.scene.path = str(path)
        check_output_folder(self.out, path, "svolsdf reconstruct")
        if options.runs_mvs1(self.cfg):
            self.backbone()  # built once and dropped: its weights load again in stage 1
        if options.wants_network(self.cfg):
            self.network_backbone()  # kept: the fusion stage reuses it

    def _interrupt_message(self) -> str:
        msg = f"interrupted: stage {self._stage} stopped"
        keys = self.keys or {}
        if self._stage in keys and self.dir.done(self._stage, keys[self._stage]):
            msg = f"interrupted after stage {self._stage} finished"  # between two stages
        t, resumes = self._trainer, ""
        if self._stage == "field" and t is not None:
            msg += f" at step {t.step} of {self.cfg.train.steps}"
            if self.cfg.train.checkpoint_every > 0:
                resumes = "; the optimization continues from its last checkpoint"
        return (f"{msg}; rerun the same command to resume (finished stages in {self.out} are "
                f"kept{resumes})")

    def _run(self, t_all: float) -> dict:
        from svolsdf.io.runfolder import config_digest
        from svolsdf.scene.checks import check_scene

        scene = self.load()
        # degenerate input (empty masks, tiny images, cameras that see nothing in common) ends
        # here, before a stage, in one line
        check_scene(scene, use_masks=self.cfg.scene.use_masks)
        self.keys = self.stage_keys()
        before = self.dir.state().get("manifest")
        manifest = input_manifest(scene, before)
        self.input_keys = input_keys(self.cfg, manifest)
        self._input_changes = describe_changes(before, manifest)
        save_config(self.cfg, self.dir.config_file)
        self._config_digest = config_digest(self.dir.config_file)
        self.dir.write_views(self.views, self.test_view_ids, (scene.width, scene.height),
                             str(self.cfg.scene.path))
        self.dir.write_manifest(manifest)
        if self._input_changes:
            log.info("inputs changed since the last run: %s; the stages that read them run "
                     "again", "; ".join(self._input_changes))
        threads = set_threads(self.cfg.threads)
        log.info("scene %s: inputs %s at %dx%d, mode %s, preset %s, %d torch thread(s)",
                 scene.path, self.views, scene.width, scene.height, self.cfg.train.mode,
                 self.cfg.preset, threads)
        # the mode's value and the options it allows: validate_config. Stage keys chain their
        # inputs: a changed config reruns that stage and the later ones
        stages = []
        if options.runs_mvs1(self.cfg):
            stages.append(("mvs1", self.stage_mvs1))
        if self.has_field():
            stages.append(("field", self.stage_field))
        stages += [("guide", self.stage_guide), ("mvs23", self.stage_mvs23),
                   ("unguided", self.stage_unguided), ("fusion", self.stage_fusion)]
        if self.has_field():
            stages.append(("mesh", self.stage_mesh))
        for name, stage in stages:
            self._stage = name
            stage()
            self._adopt(name)
        self._stage = "finish"
        self._time("total", t_all)
        return {"out": str(self.out), "points": str(self.dir.points),
                "mesh": str(self.dir.mesh()) if self.has_field() else None,
                "timing": self.timing}

    # ------------------------------------------------------------------ stage 1
    def backbone(self):
        """The configured MVS backbone (`svolsdf.pipeline.builders.build_backbone`)."""
        return builders.build_backbone(self.cfg, self.device)

    def stage_mvs1(self) -> list[ProbabilityVolume]:
        files = [self.dir.stage1_file(v) for v in self.views]
        if self._done("mvs1") and all(f.is_file() for f in files):
            vols = self._reuse("mvs1", files, ProbabilityVolume.load)
            if vols is not None:
                self._volumes1 = vols
                return vols
        t0 = time.perf_counter()
        from svolsdf.mvs.cascade import run_cascade

        res = run_cascade(self.backbone(), self.load(), stages=(1,))
        files[0].parent.mkdir(parents=True, exist_ok=True)
        for v in res[1]:
            v.save(self.dir.stage1_file(v.view_id))
        self._volumes1 = [v.to("cpu") for v in res[1]]  # as when read back from the files
        self._mark("mvs1")
        self._time("mvs1", t0)
        return self._volumes1

    # ------------------------------------------------------------------ field
    def train_data(self):
        """The field stage's `TrainData` (`svolsdf.pipeline.builders.build_train_data`)."""
        scene = self.load()
        mvs_depth = None
        if options.fits_to_mvs_depth(self.cfg):  # the "mse" and "no-prob-volume" ablations
            from svolsdf.prior.depth_filter import filtered_depth_maps

            mvs_depth = filtered_depth_maps(self.regressed_volumes1(), scene.height,
                                            scene.width) / scene.normalization.scale
        return builders.build_train_data(self.cfg, scene, mvs_depth)

    def stage_field(self):
        """The S-VolSDF optimization (OUT/field/model.pt), resumed from OUT/field/checkpoint.pt
        after an interrupt; an unreadable model or checkpoint is discarded (with a warning) and
        the stage runs again."""
        final = self.dir.model
        torch.manual_seed(self.cfg.train.seed)  # the box (quantiles of a random subset) too
        model = self.build_model()
        if self._done("field") and final.is_file():
            if self._reuse("field", [final], lambda f: load_model(model, f), discard=True):
                self._model = model.to(self.device)
                return self._model
            torch.manual_seed(self.cfg.train.seed)  # a fresh model: the load may have filled
            model = self.build_model()  # part of it
        t0 = time.perf_counter()
        tcfg = self.cfg.train
        trainer = self._field_trainer(model)
        if self._inputs_unchanged("field", "field_partial"):
            ckpt = trainer.checkpoint_path()
            if not self._reuse("field", [ckpt], trainer.load_checkpoint, discard=True):
                torch.manual_seed(tcfg.seed)  # start again, exactly as a fresh run
                model = self.build_model()
                trainer = self._field_trainer(model)
        else:
            self.dir.mark("field_partial", self.keys["field"], **self._provenance("field"))
        self._trainer = trainer  # its step, for the message of an interrupt
        trainer.fit(progress=self.progress)
        self._trainer = None
        final.parent.mkdir(parents=True, exist_ok=True)
        save_field(final, model)
        self._model = model
        self._mark("field")
        hist = trainer.history
        self._time("field", t0, steps=tcfg.steps,
                   steps_per_s=round(hist[-1]["steps_per_s"], 3) if hist else None)
        return model

    def _field_trainer(self, model):
        """The `Trainer` of the field stage for a freshly built ``model`` (its grid initialised
        from the stage-1 MVS depth where configured)."""
        from svolsdf.optimize.trainer import Trainer
        from svolsdf.prior.consistency import MVSPrior

        tcfg = self.cfg.train
        torch.manual_seed(tcfg.seed)
        prior = None
        if options.uses_prior(self.cfg) and self._volumes1 is not None:
            prior = MVSPrior(self._volumes1, self.load().normalization, device=self.device,
                             sources=builders.prior_sources(self.cfg, self.load(),
                                                            self._volumes1))
            if options.field_from_mvs(self.cfg):  # the kind's start from the MVS surface
                scene = self.load()
                options.field_kind(self.cfg).init_from_mvs(
                    model, self.regressed_volumes1(), scene.normalization,
                    scene.masks if self.cfg.scene.use_masks else None,
                    self.cfg.field.init_unverified_weight)
        return Trainer(model, self.train_data(), tcfg, prior=prior,
                       sampler=builders.build_sampler(self.cfg, prior),
                       out_dir=self.dir.field_dir, device=self.device,
                       grid_schedule=builders.grid_schedule(self.cfg))

    # ------------------------------------------------------------------ guide depth
    def stage_guide(self) -> dict[int, torch.Tensor] | None:
        """World z-depth maps that replace the stage-1 depth (docs/method.md 6.1), or None."""
        if not options.has_guide(self.cfg):
            return None
        files = self.dir.view_files(self.dir.render_depth_dir(), self.views)
        if self._done("guide") and all(f.is_file() for f in files.values()):
            maps = self._reuse_maps("guide", files)
            if maps is not None:
                return maps
        t0 = time.perf_counter()
        if options.guide_from_consistency(self.cfg):
            from svolsdf.prior.consistency import consistency_depth

            guide, psnr = consistency_depth(self._volumes1, self.load().normalization), None
        else:
            rendered = self.render_guide(previews=True)
            guide, psnr = rendered.depth, rendered.field_psnr
        for v, d in guide.items():
            save_npy(files[v], d.numpy().astype(np.float32))
        self._mark("guide")
        self._time("guide", t0, **({"field_psnr": psnr} if psnr is not None else {}))
        return guide

    def guide_depth(self) -> dict[int, torch.Tensor] | None:
        """The guide stage's depth maps as it left them in OUT/field/render_depth ({view: (H, W)
        world z-depth}), or None when the run has no guide (mvs-only).

        Raises:
            RuntimeError: the guide stage has not written them (it runs before every reader).
        """
        if not options.has_guide(self.cfg):
            return None
        files = self.dir.view_files(self.dir.render_depth_dir(), self.views)
        missing = [str(f) for f in files.values() if not f.is_file()]
        if missing:
            raise RuntimeError(f"the guide stage has not run: {missing[0]} is missing")
        return load_maps(files)

    def render_guide(self, previews: bool = False) -> GuideRender:
        """The field's rendered z-depth (world) of each input view, with docs/method.md 6.1's rule
        for pixels of accumulated weight < 0.2 (`svolsdf.render.views.guide_depths`); with
        ``previews`` also the preview images in OUT/field and the field's PSNR on the inputs."""
        from svolsdf.pipeline.previews import field_psnr, write_previews
        from svolsdf.render.views import guide_depths

        scene = self.load()
        pixels = self.guide_pixels()
        r = self.render_views(scene.cameras_unit, self.unit_near_far().to(self.device),
                              pixels=pixels)
        psnr = None
        if previews:
            psnr = field_psnr(scene, self.views, r["rgb"], pixels, self.cfg.scene.use_masks)
            for i, v in enumerate(self.views):
                write_previews(self.dir, v, r, i)
        volumes = self.regressed_volumes1() if self._volumes1 is not None else None
        depth = guide_depths(r["depth"], r["opacity"], self.views, scene.normalization.scale,
                             self.cfg.guide.low_weight_rule, volumes)
        return GuideRender(depth, psnr)

    # ------------------------------------------------------------------ stages 2-3
    def stage_mvs23(self) -> dict[int, torch.Tensor]:
        """Final per-view depth: MVS stage 3 (guided by the field when there is one); for the
        ``volsdf`` mode, the field's rendered depth itself."""
        ddir = self.dir.depth_dir
        files = self.dir.view_files(ddir, self.views)
        if self._done("mvs23") and all(f.is_file() for f in files.values()):
            maps = self._reuse_maps("mvs23", files)
            if maps is not None:
                return maps
        t0 = time.perf_counter()
        from svolsdf.io.images import write_depth_preview

        guide = self.guide_depth()  # the guide stage ran before
        if options.is_baseline(self.cfg):
            depths = guide
            for v, d in depths.items():
                save_npy(files[v], d.numpy().astype(np.float32))
                write_depth_preview(ddir / f"{v}.png", d)
        else:
            from svolsdf.mvs.cascade import run_and_save_cascade, save_cascade

            def picture(d, p):
                write_depth_preview(p, torch.from_numpy(d))

            prev = {v.view_id: v for v in self._volumes1} if guide is None else None
            stages = (2, 3)
            if guide is None and self._volumes1 is None:
                stages = (1, 2, 3)
            earlier = {1: self._volumes1} if self._volumes1 is not None else None
            # stages 2-3's volumes only on request (mvs.save_volumes): nothing reads them again;
            # stage 1's only when run here (the mvs1 stage's files are its own, with its record)
            keep = tuple(k for k in stages if k == 1 or self.cfg.mvs.save_volumes)
            if self.cfg.mvs.finer_stage_optimization and guide is not None:
                from svolsdf.pipeline.finer import finer_stage_cascade

                res = finer_stage_cascade(self, guide)
                save_cascade({**res, **(earlier or {})}, self.out, picture=picture,
                             volumes=keep)
                depths = {v.view_id: v.depth.float() for v in res[max(res)]}
            else:  # one view at a time: only its finer volumes are in memory
                depths = run_and_save_cascade(self.backbone(), self.load(), self.out,
                                              stages=stages, guide_depth=guide, prev=prev,
                                              earlier=earlier, picture=picture,
                                              volumes=keep)
        self._mark("mvs23")
        self._time("mvs23", t0)
        return depths

    def network_backbone(self):
        """The ``fusion.network`` backbone (its weights loaded and checked once per
        config; `run` asks for it first, the fusion stage reuses it)."""
        key = (self.cfg.fusion.network, self.cfg.fusion.network_weights, self.cfg.mvs.max_sources)
        if self._net is None or self._net[0] != key:
            self._net = (key, builders.build_network_backbone(self.cfg, self.device))
        return self._net[1]

    def stage_unguided(self) -> dict[int, torch.Tensor] | None:
        """MVS stages 2-3 centred on the stage-1 depth, the backbone alone's cascade
        (``fusion.unguided``): OUT/unguided/{depth,confidence}/<view>.npy, confidence
        the product over stages 1-3 (docs/method.md 6.2). None when the option does not apply."""
        if not options.wants_unguided(self.cfg):
            return None
        udir = self.dir.unguided_dir
        files = self.dir.view_files(udir / "depth", self.views)
        if self._done("unguided") and all(f.is_file() for f in files.values()):
            maps = self._reuse_maps("unguided", files)
            if maps is not None:
                return maps
        t0 = time.perf_counter()
        from svolsdf.mvs.cascade import run_and_save_cascade

        vols1 = self._volumes1 if self._volumes1 is not None else self.stage_mvs1()
        # depth, confidence over stages 1-3, one view at a time
        depths = run_and_save_cascade(self.backbone(), self.load(), udir, stages=(2, 3),
                                      prev={v.view_id: v for v in vols1}, earlier={1: vols1},
                                      volumes=False)
        self._mark("unguided")
        self._time("unguided", t0)
        return depths

    # ------------------------------------------------------------------ fusion, mesh
    def stage_fusion(self) -> Path:
        """Geometric-consistency filtering and fusion of the depth sets (OUT/points.ply)."""
        path = self.dir.points
        if self._done("fusion") and path.is_file():
            return path
        t0 = time.perf_counter()
        from svolsdf.pipeline.fusion_stage import fuse

        n, extra = fuse(self, path)
        if n == 0:  # never a finished run: nothing downstream can use it
            path.unlink(missing_ok=True)
            raise InputError(self._no_points_message())
        self._mark("fusion")
        self._time("fusion", t0, points=n, **extra)
        log.info("fused %d points -> %s %s", n, path, extra.get("points_per_set", ""))
        return path

    def _no_points_message(self) -> str:
        """Why fusion kept no point, as far as the run can tell, and what to try."""
        why = []
        if self.load().masks is not None and self.cfg.scene.use_masks:
            why.append("the object masks")
        f = self.cfg.fusion
        return (f"{self.out}: fusion kept no point: no pixel's depth agrees in "
                f"{f.min_views} other input view(s) within {f.dist} px / "
                f"{f.rel:g} relative depth"
                + (f" inside {why[0]}" if why else "")
                + f" (views {self.views}). Check that the cameras look at the object and "
                  "overlap (svolsdf info SCENE --sheet sheet.png), or pick views with more "
                  "overlap (--views auto)")

    def stage_mesh(self) -> Path:
        """The mesh (OUT/mesh.ply or .obj; `svolsdf.pipeline.mesh.build_mesh`): the field's
        zero level, the Poisson surface of the fused points or the TSDF of the observed final
        depth, culled by the input views, then by free space and support. ``mesh_source`` in
        OUT/timing.json says which surface it is, and why when it is not the one asked for."""
        path = self.dir.mesh(self.cfg.mesh.format)
        if self._done("mesh") and path.is_file():
            return path
        t0 = time.perf_counter()
        from svolsdf.fusion.mesh_ops import save_mesh
        from svolsdf.pipeline.mesh import build_mesh

        vw, f, cols, info = build_mesh(self)
        save_mesh(path, vw, f, cols, fmt=self.cfg.mesh.format)
        self._mark("mesh", [path])
        self._time("mesh", t0, vertices=int(len(vw)), faces=int(len(f)), **info)
        return path
