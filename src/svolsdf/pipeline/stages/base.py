"""`Stage`: one step of the reconstruction, declared (docs/architecture.md "Data flow").

A stage says what it is and what it needs; `svolsdf.pipeline.runner.Pipeline` decides when it
runs. It never calls another stage: the runner hands it what it consumes, either as the earlier
stage left it in memory or as that stage's `Stage.load` read it back from the run folder.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, ClassVar

from svolsdf.config import Config

__all__ = ["Stage", "StageResult"]


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
        takes ``train``). `tests/pipeline/test_stage_key_reads.py` checks that they cover what
        the stage is seen reading."""
        return ()

    def declares(self, cfg: Config, option: str) -> bool:
        """``option`` (``section.option``) is among `reads` for ``cfg``."""
        return any(option == r or (r.endswith(".*") and option.startswith(r[:-1]))
                   for r in self.reads(cfg))

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
