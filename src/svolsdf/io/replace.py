"""Output folders that a command replaces as a whole (a scene of ``svolsdf synth`` or
``svolsdf calibrate``): checked before any work, written aside, swapped in at the end, and never
a file lost that the command did not write.

A command describes its output with an `OutputSpec`: the entries it writes at the folder's top
(``image/``, ``cameras.npz``, ...), which it replaces on a rerun, and those it only adds to (a
log folder). Writing goes through `replace_outputs`:

1. `check_replace` (nothing is written): the folder is new, empty, or the command's own earlier
   output; an input (a folder of photos, a scene whose cameras are borrowed) is neither the folder
   nor inside an entry the command replaces; and every file inside an entry it replaces is one
   the command wrote, as recorded in ``OUT/.svolsdf-files.json`` (the file list of its last
   write, with sizes: a file the user put there or changed since is the user's). A folder written
   before that record existed is read through the command's own summary file (``legacy``).
   Anything else is refused, naming the file, before any work.
2. The command writes its whole output into a new folder inside OUT (``.svolsdf-staging.*``)
   while it holds OUT's lock (`svolsdf.io.runfolder.folder_lock`); a failure or Ctrl-C removes
   that folder and leaves OUT as it was (a new OUT that stayed empty is removed again).
3. At the end each entry is swapped in by a rename: the earlier one moves aside and is removed
   only after the new one is in place. Files at OUT's top that are not the command's (a user's
   notes, the folder of the input photos) stay where they are.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import secrets
import shutil
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

from svolsdf.errors import InputError
from svolsdf.io.paths import output_dir, path_label, user_path
from svolsdf.io.runfolder import LOCK_NAME, atomic_write, folder_lock

__all__ = ["RECORD_NAME", "OutputSpec", "check_replace", "recorded_files", "replace_outputs"]

log = logging.getLogger(__name__)

RECORD_NAME = ".svolsdf-files.json"
"""The record of what a command wrote into its output folder: ``{"command": ..., "files":
{relative path: size in bytes}}``."""

_STAGING = ".svolsdf-staging."
_REPLACED = ".svolsdf-replaced."
#: never the user's data: the lock, the record, a desktop's index files
_OURS = frozenset({LOCK_NAME, RECORD_NAME, ".DS_Store", "Thumbs.db", "desktop.ini"})


@dataclass(frozen=True)
class OutputSpec:
    """What a command writes into its output folder."""

    command: str
    """The command, as messages and the record name it (``svolsdf synth``)."""
    names: frozenset[str]
    """The entries at the folder's top that the command writes and replaces on a rerun."""
    keeps: frozenset[str] = frozenset()
    """Entries the command adds to and never replaces (a log folder)."""
    what: str = "scene folder"
    """What the folder is, for messages."""
    earlier: str = "an earlier output of the command"
    """What the command's earlier output is, for messages ("a synthetic scene")."""
    legacy: Callable[[Path], dict[str, int | None] | None] | None = None
    """For a folder without a record: the files (relative path: size or None) an earlier
    version of the command wrote there, read from its own summary file; None when the folder is
    not such an output."""
    option: str | None = field(default="-o")
    """The option that names the folder, for messages; None for an argument."""


def _files(root: Path, top: Path | None = None) -> Iterator[tuple[str, int]]:
    """(relative path, size) of every file under ``root`` (itself when a file), symbolic links
    as files and not followed."""
    top = top or root.parent
    if not root.is_symlink() and root.is_dir():
        for p in sorted(root.iterdir()):
            yield from _files(p, top)
    else:
        yield root.relative_to(top).as_posix(), root.lstat().st_size


def recorded_files(out: str | Path, spec: OutputSpec) -> dict[str, int | None] | None:
    """The files ``spec.command`` recorded writing into ``out`` (`RECORD_NAME`, else
    ``spec.legacy``), or None when ``out`` holds no output of it.

    Raises:
        InputError: the record names another command.
    """
    out = Path(out)
    rec = out / RECORD_NAME
    if rec.is_file():
        try:
            data = json.loads(rec.read_text())
            command, files = data["command"], dict(data["files"])
        except (OSError, ValueError, KeyError, TypeError):
            raise InputError(f"{rec}: unreadable record of the folder's files; remove the "
                             f"folder's earlier output or write to a new folder") from None
        if command != spec.command:
            raise InputError(f"{path_label(out, spec.option)}: that folder holds the output of "
                             f"{command}, which {spec.command} does not replace; choose another "
                             "folder")
        return files
    return spec.legacy(out) if spec.legacy is not None and out.is_dir() else None


def check_replace(out: str | Path, spec: OutputSpec, inputs: Iterable[str | Path | None] = ()
                  ) -> Path:
    """Refuse, before any work, an output folder that ``spec.command`` cannot write without
    losing a file it did not write (module docstring); nothing is written.

    Args:
        out: the output folder as the user gave it (need not exist).
        spec: what the command writes.
        inputs: the files and folders the command reads (None entries are skipped).

    Returns:
        ``out`` with ``~`` expanded.

    Raises:
        InputError: one line naming the folder or the file and the way out.
    """
    label = path_label(out, spec.option)
    out = output_dir(out, spec.what, spec.option, create=False)
    if not out.is_dir():
        return out
    o = out.resolve()
    holders = set()  # top entries that hold an input: the user's, left alone
    for i in inputs:
        if i is None:
            continue
        s = user_path(i).resolve()
        if s == o:
            raise InputError(f"{label}: the {spec.what} is the input {i}; write to another "
                             "folder")
        if o in s.parents:
            top = s.relative_to(o).parts[0]
            if top in spec.names:
                where = "" if s == o / top else "inside "
                raise InputError(f"{label}: the input {i} is {where}{out / top}, which "
                                 f"{spec.command} replaces; move the input to another folder "
                                 f"(e.g. {out / 'photos'}) or write to another folder")
            holders.add(top)
    try:
        entries = sorted(p.name for p in out.iterdir())
    except OSError as e:
        raise InputError(f"{label}: cannot list the {spec.what} ({e.strerror or e})") from None
    entries = [n for n in entries if n not in _OURS and not n.startswith((_STAGING, _REPLACED))]
    files = recorded_files(out, spec)
    if files is None:
        foreign = [n for n in entries if n not in spec.keeps and n not in holders]
        if foreign:
            shown = ", ".join(foreign[:3]) + (" ..." if len(foreign) > 3 else "")
            raise InputError(f"{label}: the {spec.what} is not empty and is not {spec.earlier} "
                             f"({shown}); write to a new or empty folder")
        return out
    for name in entries:
        if name not in spec.names:
            continue  # the user's, or added to (keeps): left where it is
        for rel, size in _files(out / name):
            known = files.get(rel, -1)
            if known == -1 or (known is not None and known != size):
                why = "is not a file" if known == -1 else "changed since"
                raise InputError(f"{label}: {out / rel} {why} {spec.command} wrote, and "
                                 f"{spec.command} replaces {out / name}; move that file "
                                 "elsewhere or write to a new folder")
    return out


def _write_record(out: Path, command: str, files: dict) -> None:
    text = json.dumps({"command": command, "files": files}, indent=1, sort_keys=True) + "\n"
    atomic_write(out / RECORD_NAME, lambda p: p.write_text(text))


def _remove(p: Path) -> None:
    if p.is_dir() and not p.is_symlink():
        shutil.rmtree(p)
    else:
        p.unlink(missing_ok=True)


@contextlib.contextmanager
def replace_outputs(out: str | Path, spec: OutputSpec,
                    inputs: Iterable[str | Path | None] = ()) -> Iterator[Path]:
    """Write a command's output into ``out`` without losing a file it did not write (module
    docstring): checks (`check_replace`), yields a new empty folder inside ``out`` to write the
    whole output into, and swaps its entries in when the block ends without an error.

    Args:
        out: the output folder as the user gave it.
        spec: what the command writes; the yielded folder may hold only ``spec.names``.
        inputs: what the command reads (an input inside an entry it replaces is refused).

    Yields:
        the folder to write into; ``out``'s ``spec.keeps`` entries are written in place.

    Raises:
        InputError: as `check_replace`, or another process writes ``out``.
    """
    inputs = list(inputs)
    out = check_replace(out, spec, inputs)
    new = not os.path.lexists(out)
    output_dir(out, spec.what, spec.option)
    with folder_lock(out, spec.command):
        check_replace(out, spec, inputs)  # again under the lock: nobody changes it now
        for p in out.iterdir():  # what a killed earlier write left: no process owns it
            if p.name.startswith((_STAGING, _REPLACED)):
                _remove(p)
        stage = out / f"{_STAGING}{os.getpid()}.{secrets.token_hex(4)}"
        stage.mkdir()
        try:
            yield stage
        except BaseException:
            shutil.rmtree(stage, ignore_errors=True)
            if new and {p.name for p in out.iterdir()} <= {LOCK_NAME}:
                # OUT, or the folder a link OUT points to (the link stays as it was)
                shutil.rmtree(os.path.realpath(out), ignore_errors=True)
            raise
        _swap(out, stage, spec)


def _swap(out: Path, stage: Path, spec: OutputSpec) -> None:
    """Move the entries of ``stage`` into ``out``, the earlier ones aside and then away."""
    made = sorted(p.name for p in stage.iterdir())
    extra = [n for n in made if n not in spec.names]
    if extra:
        raise RuntimeError(f"{spec.command} wrote {extra}, which its OutputSpec does not name")
    new_files = {rel: size for n in made for rel, size in _files(stage / n, stage)}
    old_files = recorded_files(out, spec) or {}
    # first a record of both: a write killed while swapping leaves only recorded files
    _write_record(out, spec.command, {**old_files, **new_files})
    aside = out / f"{_REPLACED}{os.getpid()}.{secrets.token_hex(4)}"
    aside.mkdir()
    for name in sorted(spec.names):
        if os.path.lexists(out / name):
            os.replace(out / name, aside / name)
        if name in made:
            os.replace(stage / name, out / name)
    _write_record(out, spec.command, new_files)
    shutil.rmtree(aside)
    stage.rmdir()
    log.debug("%s: wrote %d files into %s", spec.command, len(new_files), out)
