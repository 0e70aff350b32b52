"""The runner: every stage of `svolsdf.pipeline.stages` in order, each result kept on disk,
with resume (docs/architecture.md "Data flow"; docs/method.md 0 and 6).

`Pipeline.run` takes the stages that apply to the config (`Stage.applies`) in their order and,
for each, hands it the values of the stages it consumes; a stage is read back (`Stage.load`)
instead of run when its marker in OUT/stages.json carries the same config key
(`svolsdf.pipeline.keys`) and its inputs (images, masks, cameras) are those it finished with; a
changed config or input reruns that stage and everything after it that reads it, and OUT/log says
which input changed. Each stage also records the digest of the config.yaml it finished (or was
last reused) under, so evaluate and report can tell outputs of an earlier config, and the size
and digest of its files (`svolsdf.pipeline.records`). The runner holds the folder's lock, copies
the run's messages to OUT/log, times every stage in OUT/timing.json and turns Ctrl-C into
`RunInterrupted` naming the stage. With ``start`` (``svolsdf reconstruct --from STAGE``) the
stages before it must be finished and are only read back. The optimization resumes from its last
checkpoint after a kill. All files are written atomically (`svolsdf.pipeline.rundir`). The
algorithms live in their components; the stages gather their inputs; this module orders them.
"""

from __future__ import annotations

import logging
import os
import time
from pathlib import Path

import torch

from svolsdf.config import Config, save_config, validate_config
from svolsdf.errors import (
    InputError,
    RunInterrupted,
    interrupted,
    raise_if_interrupted,
    watch_interrupts,
)
from svolsdf.io.paths import user_path
from svolsdf.pipeline import builders, options
from svolsdf.pipeline.context import GuideRender
from svolsdf.pipeline.keys import STAGES, describe_changes, input_keys, input_manifest
from svolsdf.pipeline.loaded_run import Run
from svolsdf.pipeline.machine import set_threads
from svolsdf.pipeline.records import StageRecords, load_maps
from svolsdf.pipeline.rundir import one_line
from svolsdf.pipeline.stages import PIPELINE_STAGES, Stage

__all__ = ["Pipeline"]

# the run's messages in OUT/log keep the logger name they always had
log = logging.getLogger("svolsdf.pipeline")


class Pipeline(StageRecords, Run):
    """Runs a `Config` into an output folder: the context every stage gets (its config, run
    folder, scene, backbones) and the runner that drives them.

    Args:
        cfg: the run's configuration (``cfg.scene.path`` must be set).
        out: the output folder (created; must not be a file).
        progress: show progress bars.
        start: run this stage and the later ones again, reusing the earlier ones, which must be
            finished (``svolsdf reconstruct --from``); None: every stage that did not finish.
    """

    def __init__(self, cfg: Config, out: str | Path, progress: bool = True,
                 start: str | None = None):
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
        self.start = start
        self.values: dict = {}  # stage -> its value in this process (`run_stage`)
        self.trainer = None  # the field stage's Trainer while it runs (its step, ditto)
        self.input_keys: dict[str, str] | None = None  # set by run() (`keys.input_keys`)
        self._config_digest: str | None = None  # of OUT/config.yaml, set by run()
        self._input_changes: list[str] = []
        self._logged: set[str] = set()  # the stages whose reuse or rerun OUT/log explained
        self._reruns: dict[str, str] = {}  # stage -> the file that could not be read, and why

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
        t, resumes = self.trainer, ""
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
        stages = [s for s in PIPELINE_STAGES if s.applies(self.cfg)]
        self.recognise_old_markers(stages)  # a run folder marked by the earlier key formula
        if self.start is not None:
            stages = self._from_start(stages)
        save_config(self.cfg, self.dir.config_file)
        if self.cfg.preset in ("paper", "released"):
            from svolsdf.config.presets import backbone_provenance

            prov = backbone_provenance(self.cfg)
            (log.info if prov["papers"] else log.warning)("%s preset: %s", self.cfg.preset,
                                                          prov["note"])
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
        for stage in stages:
            self._stage = stage.name
            self.run_stage(stage.name)
            self._adopt(stage.name)
        self._stage = "finish"
        self._time("total", t_all)
        return {"out": str(self.out), "points": str(self.dir.points),
                "mesh": str(self.dir.mesh()) if self.has_field() else None,
                "timing": self.timing}

    def run_stage(self, name: str):
        """Drive the stage ``name`` alone (`_drive`) with the values the stages it consumes left
        in this process (None for one that has not run); returns its value. `run` calls it for
        each stage in order; scripts that time a part of the pipeline call it directly."""
        stage = PIPELINE_STAGES[STAGES.index(name)]
        value = self._drive(stage, {c: self.values.get(c) for c in stage.consumes})
        self.values[name] = value
        # what the helpers read of the run (`Run`): the stage-1 volumes and the field
        if name == "mvs1":
            self._volumes1 = value
        elif name == "field":
            self._model = value
        return value

    def set_model(self, model) -> None:
        """Use ``model`` as the field the later stages consume (one trained outside them)."""
        super().set_model(model)
        self.values["field"] = model

    def _drive(self, stage: Stage, inputs: dict):
        """``stage``'s value: read back when it finished under the current key and inputs and
        its files can be read (`Stage.load`), else computed (`Stage.run`), marked as finished
        with the record of its files, and timed."""
        if self._done(stage.name) and all(f.is_file() for f in stage.outputs(self)):
            value = stage.load(self)
            if value is not None:
                return value
        t0 = time.perf_counter()
        res = stage.run(self, inputs)
        self._mark(stage.name, stage.recorded(self))
        self._time(stage.name, t0, **res.timing)
        return res.value

    def _from_start(self, stages: list[Stage]) -> list[Stage]:
        """``start`` and the stages after it, which run again; those before it must have
        finished under the current config and inputs (they are reused, never run).

        Raises:
            InputError: ``start`` is no stage of this config, or one before it did not finish
                (the message names it and the way out); nothing has been written.
        """
        names = [s.name for s in stages]
        if self.start not in names:
            raise InputError(f"--from {self.start}: not a stage of this run (its stages: "
                             f"{', '.join(names)})")
        i = names.index(self.start)
        for s in stages[:i]:
            if not (self.dir.done(s.name, self.keys[s.name])
                    and self.inputs_unchanged(s.name, s.name)
                    and all(f.is_file() for f in s.outputs(self))
                    and self.dir.changed_output(s.name) is None):
                raise InputError(
                    f"--from {self.start}: stage {s.name} of {self.out} is not finished under "
                    f"this config (an option it reads changed, or the run never got there); run "
                    f"svolsdf reconstruct without --from")
        self.dir.unmark(names[i:])
        return stages

    # ------------------------------------------------------------------ what stages use
    def backbone(self):
        """The configured MVS backbone (`svolsdf.pipeline.builders.build_backbone`)."""
        return builders.build_backbone(self.cfg, self.device)

    def train_data(self):
        """The field stage's `TrainData` (`svolsdf.pipeline.builders.build_train_data`)."""
        scene = self.load()
        mvs_depth = None
        if options.fits_to_mvs_depth(self.cfg):  # the "mse" and "no-prob-volume" ablations
            from svolsdf.prior.depth_filter import filtered_depth_maps

            mvs_depth = filtered_depth_maps(self.regressed_volumes1(), scene.height,
                                            scene.width) / scene.normalization.scale
        return builders.build_train_data(self.cfg, scene, mvs_depth)

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

    def render_guide(self, model, previews: bool = False) -> GuideRender:
        """``model``'s rendered z-depth (world) of each input view, with docs/method.md 6.1's rule
        for pixels of accumulated weight < 0.2 (`svolsdf.render.views.guide_depths`); with
        ``previews`` also the preview images in OUT/field and the field's PSNR on the inputs."""
        from svolsdf.pipeline.previews import field_psnr, write_previews
        from svolsdf.render.views import guide_depths

        scene = self.load()
        pixels = self.guide_pixels()
        r = self.render_views(scene.cameras_unit, self.unit_near_far().to(self.device),
                              pixels=pixels, model=model,
                              desc="guide: render the input views")
        psnr = None
        if previews:
            psnr = field_psnr(scene, self.views, r["rgb"], pixels, self.cfg.scene.use_masks)
            for i, v in enumerate(self.views):
                write_previews(self.dir, v, r, i)
        volumes = self.regressed_volumes1() if self._volumes1 is not None else None
        depth = guide_depths(r["depth"], r["opacity"], self.views, scene.normalization.scale,
                             self.cfg.guide.low_weight_rule, volumes)
        return GuideRender(depth, psnr)

    def network_backbone(self):
        """The ``fusion.network`` backbone (its weights loaded and checked once per
        config; `run` asks for it first, the fusion stage reuses it)."""
        key = (self.cfg.fusion.network, self.cfg.fusion.network_weights, self.cfg.mvs.max_sources)
        if self._net is None or self._net[0] != key:
            self._net = (key, builders.build_network_backbone(self.cfg, self.device))
        return self._net[1]
