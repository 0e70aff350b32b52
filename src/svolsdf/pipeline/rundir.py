"""The run folder's writing side: `RunDir` is a `svolsdf.io.runfolder.RunFolder` (every path of
a run, what its files hold; the layout is in its docstring) that also writes the stage state
(OUT/stages.json), views.json, OUT/timing.json and OUT/log, holds the folder lock, and saves
atomically.

Every file is written to a unique temporary name and renamed, so a killed run never leaves a
half file under the final name.
"""

from __future__ import annotations

import contextlib
import json
import logging
import pickle
import sys
import zipfile
import zlib
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from svolsdf.io.runfolder import RunFolder, atomic_write, file_record, folder_lock

__all__ = ["UNREADABLE_FILE_ERRORS", "RunDir", "is_unreadable_file", "save_json", "save_npy",
           "save_torch"]

log = logging.getLogger(__name__)


UNREADABLE_FILE_ERRORS: tuple[type[BaseException], ...] = (
    OSError, EOFError, ValueError, KeyError, zipfile.BadZipFile, zlib.error,
    pickle.UnpicklingError, RuntimeError)
"""What reading a truncated, corrupt or older run file raises: numpy (ValueError: a bad header or
too few bytes; EOFError), an .npz's zip (BadZipFile, zlib.error), torch.load (RuntimeError: "failed
finding central directory"; UnpicklingError, EOFError), a key an older file lacks (KeyError), a
field of another shape (load_state_dict's RuntimeError) and the disk (OSError). A stage whose file
raises one of these is run again; anything else (TypeError, AttributeError, NameError, ...) is a
bug of the loader and propagates (`is_unreadable_file`)."""


def is_unreadable_file(e: BaseException) -> bool:
    """``e``, raised while reading a run file, says the file is unreadable (truncated, corrupt, of
    an older layout: `UNREADABLE_FILE_ERRORS`) rather than that the loader has a bug. RuntimeError's
    subclasses NotImplementedError and RecursionError are bugs."""
    return isinstance(e, UNREADABLE_FILE_ERRORS) and not isinstance(
        e, (NotImplementedError, RecursionError))


def save_npy(path: Path, arr: np.ndarray) -> None:
    """Write ``arr`` to ``path`` (.npy) atomically, creating its folder
    (`svolsdf.io.runfolder.atomic_write`: a full disk names the file and leaves no temporary)."""
    atomic_write(path, lambda tmp: np.save(tmp, arr), suffix=".npy")


def save_json(path: Path, obj, indent: int = 1) -> None:
    """Write ``obj`` as JSON to ``path`` atomically."""
    text = json.dumps(obj, indent=indent)
    atomic_write(path, lambda tmp: tmp.write_text(text))


def save_torch(path: Path, obj) -> None:
    """``torch.save`` ``obj`` to ``path`` atomically."""
    atomic_write(path, lambda tmp: torch.save(obj, tmp))


def one_line(e: BaseException) -> str:
    """An exception's message on one line, at most 200 characters."""
    text = " ".join(str(e).split()) or e.__class__.__name__
    return text if len(text) <= 200 else text[:197] + "..."


class RunDir(RunFolder):
    """The output folder of one run, for the pipeline that writes it: a `RunFolder` (paths and
    reading) with the stage state, views.json, timing.json, the lock and OUT/log.

    Args:
        root: the folder (need not exist yet).
    """

    def __init__(self, root: str | Path):
        super().__init__(root)
        self._warned_state = False

    @staticmethod
    def save_npy(path: Path, arr: np.ndarray) -> None:
        """Write ``arr`` to ``path`` (.npy) atomically (`save_npy`)."""
        save_npy(path, arr)

    # ------------------------------------------------------------------ views.json
    def write_views(self, inputs: list[int], test: list[int], size: tuple[int, int],
                    scene: str) -> None:
        save_json(self.views_file, {"inputs": inputs, "test": test, "size": list(size),
                                    "scene": scene})

    # ------------------------------------------------------------------ stage state
    def state(self) -> dict:
        """OUT/stages.json: {stage: key, "provenance": {...}, "manifest": {...}, "outputs":
        {...}}; {} (with one warning) when it is unreadable."""
        p = self.stages_file
        if not p.is_file():
            return {}
        try:
            st = json.loads(p.read_text())
            if isinstance(st, dict):
                return st
        except (ValueError, UnicodeDecodeError):
            pass
        if not self._warned_state:  # mark replaces it
            log.warning("%s is unreadable; no stage counts as finished", p)
            self._warned_state = True
        return {}

    def mark(self, stage: str, key: str, inputs: str | None = None,
             config: str | None = None, outputs: Sequence[Path] | None = None) -> None:
        """Record ``stage`` as finished under ``key``, with the key of its ``inputs``, the
        digest of the ``config`` (config.yaml) that made it and the size and digest of each of
        its ``outputs`` files (`svolsdf.io.runfolder.file_record`; `RunFolder.changed_output`
        compares them), when given."""
        st = self.state()
        st[stage] = key
        if inputs is not None or config is not None:
            prov = st.get("provenance") if isinstance(st.get("provenance"), dict) else {}
            prov[stage] = {"inputs": inputs, "config": config}
            st["provenance"] = prov
        if outputs is not None:
            rec = st.get("outputs") if isinstance(st.get("outputs"), dict) else {}
            rec[stage] = {Path(f).relative_to(self.root).as_posix(): file_record(f)
                          for f in outputs}
            st["outputs"] = rec
        save_json(self.stages_file, st)

    def record(self, output: str, config: str | None, **extra) -> None:
        """Record that ``output`` (e.g. "render": renders/) was made under the config.yaml of
        digest ``config`` (`svolsdf.io.runfolder.output_provenance` reads it), with ``extra``
        facts (the renders: the field file they were made from). An unreadable stages.json is
        left for the next reconstruct to replace (and to say so)."""
        st = self.state()
        if not st and self.stages_file.is_file():
            return
        prov = st.get("provenance") if isinstance(st.get("provenance"), dict) else {}
        prov[output] = {"config": config, **extra}
        st["provenance"] = prov
        save_json(self.stages_file, st)

    def provenance(self, stage: str) -> dict:
        """{"inputs": key, "config": digest} recorded for ``stage`` ({} when none is)."""
        prov = self.state().get("provenance")
        rec = prov.get(stage) if isinstance(prov, dict) else None
        return rec if isinstance(rec, dict) else {}

    def write_manifest(self, manifest: dict) -> None:
        """Keep the input manifest (`svolsdf.pipeline.keys.input_manifest`) in stages.json."""
        st = self.state()
        st["manifest"] = manifest
        save_json(self.stages_file, st)

    def unmark(self, stages: Sequence[str]) -> None:
        """Forget ``stages`` (their files no longer follow from earlier ones)."""
        st = {k: v for k, v in self.state().items() if k not in stages}
        for part in ("provenance", "outputs"):
            if isinstance(st.get(part), dict):
                st[part] = {k: v for k, v in st[part].items() if k not in stages}
        save_json(self.stages_file, st)

    def done(self, stage: str, key: str) -> bool:
        """``stage`` finished under ``key``."""
        return self.state().get(stage) == key

    # ------------------------------------------------------------------ timing
    def write_timing(self, timing: dict) -> None:
        """Merge ``timing`` ({stage: {...}}) into OUT/timing.json (rewritten when unreadable)."""
        prev = {}
        tp = self.timing_file
        if tp.is_file():
            try:
                prev = json.loads(tp.read_text())
            except (ValueError, UnicodeDecodeError):
                prev = None
            if not isinstance(prev, dict):
                log.warning("%s is unreadable; rewriting it", tp)
                prev = {}
        prev.update(timing)
        save_json(tp, prev)

    # ------------------------------------------------------------------ lock
    def lock(self, command: str = "svolsdf reconstruct"):
        """Hold the folder's lock while ``command`` writes it (`svolsdf.io.runfolder.folder_lock`;
        the folder must exist).

        Raises:
            InputError: another process holds the folder; the message names the folder, the
                command and its pid.
        """
        return folder_lock(self.root, command)

    # ------------------------------------------------------------------ log
    def attach_log(self) -> logging.Handler | None:
        """Append the package's messages to OUT/log; returns the handler to remove afterwards
        (None when one already writes there)."""
        root = logging.getLogger("svolsdf")
        if root.level == logging.NOTSET or root.level > logging.INFO:
            root.setLevel(logging.INFO)
        path = str(self.log_file.resolve())
        if any(isinstance(h, logging.FileHandler) and h.baseFilename == path
               for h in root.handlers):
            return None
        h = logging.FileHandler(path)
        h.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
        root.addHandler(h)
        return h

    def log_to_file(self, logger: logging.Logger, level: int, msg: str,
                    exc_info: bool = False) -> None:
        """Write ``msg`` to OUT/log alone, as ``logger``'s record (the console gets it from the
        command line)."""
        path = str(self.log_file.resolve())
        for h in logging.getLogger("svolsdf").handlers:
            if isinstance(h, logging.FileHandler) and h.baseFilename == path:
                rec = logger.makeRecord(logger.name, level, __file__, 0, msg, (),
                                        sys.exc_info() if exc_info else None)
                with contextlib.suppress(Exception):
                    h.handle(rec)
