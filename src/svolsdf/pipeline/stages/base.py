"""`Stage`: one step of the reconstruction, declared (docs/architecture.md "Data flow").

A stage says what it is and what it needs; `svolsdf.pipeline.runner.Pipeline` decides when it
runs. It never calls another stage: the runner hands it what it consumes, either as the earlier
stage left it in memory or as that stage's `Stage.load` read it back from the run folder.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, ClassVar

from svolsdf.config import Config

__all__ = ["SCENE_OPTIONS", "Stage", "StageResult"]

#: The options the run's scene is loaded with (`svolsdf.pipeline.loaded_run.Run.load`): every
#: stage reads them through the scene. The options that pick the input views (``scene.views``,
#: ``scene.num_views``, ``scene.view_selection``) act through the views they pick, which enter
#: every stage key themselves.
SCENE_OPTIONS = ("scene.path", "scene.image_size", "scene.lighting")


class StageResult:
    """What `Stage.run` returns: the stage's ``value`` (handed to the stages that consume it)
    and ``timing`` extras for OUT/timing.json (``{"points": 1234}``)."""

    def __init__(self, value: Any, **timing):
        self.value = value
        self.timing = timing


class Stage:
    """One declared stage.

    Attributes:
        name: the stage's name in OUT/stages.json and OUT/timing.json.
        consumes: the earlier stages whose values `run` receives (``inputs[name]``; None for one
            that does not apply to the config).
        scene_inputs: what it reads of the scene, directly: "images", "masks", "cameras".
    """

    name: ClassVar[str] = ""
    consumes: ClassVar[tuple[str, ...]] = ()
    scene_inputs: ClassVar[tuple[str, ...]] = ()

    def applies(self, cfg: Config) -> bool:
        """The stage runs for ``cfg`` (when it does not, its value is None)."""
        return True

    def reads(self, cfg: Config) -> tuple[str, ...]:
        """The options the stage reads for ``cfg``: ``section.option``, or ``section.*`` for
        every option of a section (a component that takes its whole section, as the `Trainer`
        takes ``train``). Their values enter the stage's key (`svolsdf.pipeline.keys`), but for
        `key_ignores`. `tests/pipeline/test_stage_reads.py` checks that they cover what the
        stage is seen reading."""
        return ()

    def uses(self, cfg: Config) -> tuple[str, ...]:
        """The stages of `consumes` whose values the stage reads for ``cfg`` (all of them by
        default): only their keys enter its key, so a stage that reads the fused points only for
        some methods (the mesh) is not run again for a fusion option otherwise."""
        return self.consumes

    def key_ignores(self, cfg: Config) -> tuple[str, ...]:
        """Options among `reads` (same notation) that cannot change what the stage computes for
        ``cfg``: which side files it keeps or draws (``mvs.save_volumes``,
        ``train.snapshot_every``), or a setting of a part that does not act in this config.
        They stay out of its key, so changing them reuses the finished stage; an ``mvs`` option
        among them is also taken at its default in the backbone's signature (`backbones`)."""
        return ()

    def backbones(self, cfg: Config) -> tuple[str, ...]:
        """The networks the stage runs for ``cfg``: "mvs" (``mvs.backbone``) and/or "fusion"
        (``fusion.network``). Their signatures (the backbone's whole config with its defaults,
        the weights file's path, size and time: `svolsdf.mvs.backbone.backbone_signature`) enter
        the stage's key, so a changed default or a replaced weights file runs it again."""
        return ()

    def declares(self, cfg: Config, option: str) -> bool:
        """``option`` (``section.option``) is among `reads` for ``cfg``."""
        return _among(option, self.reads(cfg))

    def keyed(self, cfg: Config, option: str) -> bool:
        """``option`` enters the stage's key for ``cfg``: declared in `reads`, not in
        `key_ignores`."""
        return self.declares(cfg, option) and not _among(option, self.key_ignores(cfg))

    def outputs(self, ctx) -> list[Path]:
        """The files whose presence (with the stage's marker) means it finished."""
        raise NotImplementedError

    def recorded(self, ctx) -> list[Path] | None:
        """The files whose size and digest OUT/stages.json records (None: the run folder's
        default for the stage, `svolsdf.io.runfolder.RunFolder.stage_outputs`)."""
        return None

    def load(self, ctx) -> Any:
        """The value of the finished stage read back from the run folder, or None when a file
        cannot be read (the runner then runs the stage again; `Pipeline.reuse` says why)."""
        raise NotImplementedError

    def run(self, ctx, inputs: dict[str, Any]) -> StageResult:
        """Compute the stage and write its files; ``inputs`` holds the value of each stage of
        `consumes`."""
        raise NotImplementedError


def _among(option: str, declared: tuple[str, ...]) -> bool:
    """``option`` is one of ``declared`` (``section.option``, or ``section.*``: every option of
    the section and of its subsections)."""
    return any(option == r or (r.endswith(".*") and option.startswith(r[:-1]))
               for r in declared)
