"""What the pipeline records of its stages in the run folder: a stage is finished when its
marker in OUT/stages.json has the current config key and inputs key and its output files are those
it finished with; a finished stage's files are read back, or the stage runs again with the reason
in OUT/log and timing.json (docs/run-folder.md). `StageRecords` is the part of
`svolsdf.pipeline.Pipeline` that keeps these records; the stages themselves are in
`svolsdf.pipeline.stages`.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

import numpy as np
import torch

from svolsdf.errors import InputError, raise_if_interrupted
from svolsdf.pipeline.keys import STAGES
from svolsdf.pipeline.machine import peak_rss_gb
from svolsdf.pipeline.rundir import is_unreadable_file, one_line

__all__ = ["StageRecords", "load_map", "load_maps"]

# the run's messages in OUT/log keep the logger name they always had
log = logging.getLogger("svolsdf.pipeline")

T = TypeVar("T")


def load_map(path: Path) -> torch.Tensor:
    """The (H, W) map of an .npy file."""
    return torch.from_numpy(np.load(path))


def load_maps(files: dict[int, Path]) -> dict[int, torch.Tensor]:
    """{view: (H, W) map} from .npy files."""
    return {v: load_map(f) for v, f in files.items()}


class StageRecords:
    """The stage bookkeeping of `svolsdf.pipeline.Pipeline`, which sets what it uses: ``dir``
    (the `RunDir`), ``out``, ``cfg``, ``views``, ``keys`` (stage keys), ``input_keys``,
    ``timing``, ``_config_digest``, ``_input_changes``, ``_logged`` (the stages whose reuse or
    rerun OUT/log explained) and ``_reruns`` (stage -> why it runs again)."""

    def reuse(self, stage: str, files: list[Path], read: Callable[[Path], T],
               discard: bool = False) -> list[T] | None:
        """``[read(f) for f in files]``, the files of a finished (or, for the field, started)
        ``stage``; None when one cannot be read: a warning in OUT/log names it and why, the
        stage and the later ones run again, the stage's entry in timing.json says so
        (``rerun``), and with ``discard`` the file is deleted.

        Only what a truncated, corrupt or older file raises counts as unreadable
        (`svolsdf.pipeline.rundir.is_unreadable_file`; and `InputError`, which `load_model`
        raises for such a file): any other exception is a bug of the loader and propagates.
        """
        out = []
        for f in files:
            try:
                out.append(read(f))
            except Exception as e:
                raise_if_interrupted()  # a read that Ctrl-C stopped: the file is kept
                if not (isinstance(e, InputError) or is_unreadable_file(e)):
                    raise
                if discard:
                    f.unlink(missing_ok=True)
                self._rerun(stage, f"{f} could not be read ({one_line(e)})", discard)
                return None
        return out

    def _rerun(self, stage: str, why: str, discarded: bool = False) -> None:
        """``stage`` and the later ones run again because of ``why`` (a finished file cannot
        be read or changed since): a warning in OUT/log, ``rerun`` in timing.json."""
        self._reruns[stage] = why
        log.warning("%s: %s; %srunning the stage %s again", self.out, why,
                    "discarding it and " if discarded else "", stage)
        self.dir.unmark(STAGES[STAGES.index(stage):])

    def reuse_maps(self, stage: str, files: dict[int, Path]) -> dict[int, torch.Tensor] | None:
        """{view: (H, W) map} of a finished ``stage``'s .npy files, None when one cannot be read
        (`reuse`)."""
        maps = self.reuse(stage, list(files.values()), load_map)
        return None if maps is None else dict(zip(files, maps, strict=True))

    def _mark(self, stage: str, outputs: list[Path] | None = None) -> None:
        """``stage`` finished: its key, provenance and the record of its output files
        (``outputs``, by default `RunFolder.stage_outputs`)."""
        raise_if_interrupted()  # one that something swallowed: the stage is not finished
        if outputs is None:
            outputs = self.dir.stage_outputs(stage, self.views)
        self.dir.mark(stage, self.keys[stage], **self.provenance(stage), outputs=outputs)

    def provenance(self, stage: str) -> dict:
        """The inputs key and config digest a finished ``stage`` records (none outside run)."""
        if self.input_keys is None:
            return {}
        base = "field" if stage == "field_partial" else stage
        return {"inputs": self.input_keys[base], "config": self._config_digest}

    def _done(self, stage: str) -> bool:
        """``stage`` finished under the current key and inputs, and its files are those it
        finished with (a truncated or replaced one reruns it, `RunFolder.changed_output`)."""
        if not self.inputs_unchanged(stage, stage):
            return False
        changed = self.dir.changed_output(stage)
        if changed is not None:
            self._rerun(stage, changed)
        return changed is None

    def inputs_unchanged(self, stage: str, marker: str) -> bool:
        """``marker`` (``stage`` or field_partial) is recorded under the stage's key, and its
        inputs are the current ones. A marker without an inputs record (a run folder made before
        they were recorded) is kept, with a line in OUT/log."""
        if not self.dir.done(marker, self.keys[stage]):
            return False
        if self.input_keys is None:
            return True
        rec = self.dir.provenance(marker).get("inputs")
        if rec is None:
            if "unknown" not in self._logged:
                self._logged.add("unknown")
                log.info("%s: stages finished before their inputs were recorded are kept as "
                         "finished (whether the scene's files changed since is unknown; delete "
                         "%s to compute them again)", self.out, self.dir.stages_file)
            return True
        if rec == self.input_keys[stage]:
            return True
        if stage not in self._logged:
            self._logged.add(stage)
            what = "; ".join(self._input_changes) or "the scene's files"
            log.info("stage %s: its inputs changed since it finished (%s); running it again",
                     stage, what)
        return False

    def _adopt(self, stage: str) -> None:
        """Record the current inputs and config.yaml for ``stage`` when it finished (or was
        reused) under them, so that its outputs name the config that stands for them."""
        if self.input_keys is None or not self.dir.done(stage, self.keys[stage]):
            return
        if self.dir.provenance(stage) != self.provenance(stage):
            self.dir.mark(stage, self.keys[stage], **self.provenance(stage))

    def recognise_old_markers(self, stages: list) -> None:
        """Mark with today's key each of ``stages`` (`Stage` objects that apply) whose marker
        holds the key the earlier stage-key formula gives the current config
        (`svolsdf.pipeline.legacy_keys`) and whose recorded output files are intact, with a line
        in OUT/log: a run folder made before the keys came from the declarations keeps its
        finished stages. The field's checkpoint marker (field_partial) follows the field's.
        Run once, before the stages; a marker with any other key is left as it is."""
        state = self.dir.state()
        marked = {s.name: state.get(s.name) for s in stages}
        if "field" in marked:
            marked["field_partial"] = state.get("field_partial")
        if all(k is None or k == self.keys[s.replace("_partial", "")]
               for s, k in marked.items()):
            return
        from svolsdf.pipeline.legacy_keys import legacy_stage_keys

        old = legacy_stage_keys(self.cfg, self.views)
        outputs = {s.name: s.outputs(self) for s in stages}
        renewed = []
        for name, key in marked.items():
            stage = name.replace("_partial", "")
            if key is None or key != old[stage] or key == self.keys[stage]:
                continue
            if name == stage and not (all(f.is_file() for f in outputs[stage])
                                      and self.dir.changed_output(stage) is None):
                continue  # not intact: the stage runs again as under any other key
            self.dir.mark(name, self.keys[stage])
            renewed.append(name)
        if renewed:
            log.info("%s: stage(s) %s finished under the stage keys of an earlier release's "
                     "formula; their markers now hold the current keys", self.out,
                     ", ".join(renewed))

    def _time(self, stage: str, t0: float, **extra) -> None:
        """Record ``stage``'s time, peak memory and ``extra`` in OUT/timing.json, with why it ran
        again (``rerun``) when its earlier file could not be read (`reuse`)."""
        rerun = {"rerun": self._reruns.pop(stage)} if stage in self._reruns else {}
        self.timing[stage] = {"seconds": round(time.perf_counter() - t0, 3),
                              "peak_memory_gb": round(peak_rss_gb(), 3), **extra, **rerun}
        self.dir.write_timing(self.timing)
