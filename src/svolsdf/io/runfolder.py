"""What every command that writes into a run folder shares: its lock, atomic writes with unique
temporary names, and the record of which config made each output (its provenance).

The pipeline (`svolsdf.pipeline.RunDir`) and the commands over finished runs (evaluate, report,
render, mvs) all go through these, so two commands never write one folder at once, a full disk
never leaves a half file under a final name, and scores are never given to outputs that another
config made. docs/run-folder.md explains the choices.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import json
import os
import secrets
from collections.abc import Callable, Iterator
from pathlib import Path

from svolsdf.errors import InputError

__all__ = ["LOCK_NAME", "OUTPUT_STAGES", "atomic_write", "config_digest", "folder_lock",
           "output_provenance", "read_stage_state", "unique_temp"]

LOCK_NAME = ".svolsdf.lock"
"""The lock file of a run folder."""

OUTPUT_STAGES = {"points.ply": "fusion", "mesh.ply": "mesh", "mesh.obj": "mesh",
                 "renders": "render"}
"""The outputs that evaluate and report read, and the record (a stage of OUT/stages.json, or
``render``) that names the config which made each."""


# --------------------------------------------------------------------------- lock
@contextlib.contextmanager
def folder_lock(folder: str | Path, command: str) -> Iterator[None]:
    """Hold an exclusive lock on FOLDER/.svolsdf.lock while ``command`` writes the folder.

    The lock is an advisory ``flock`` that the operating system drops when the process ends, so a
    killed command never leaves a stale lock behind. Where ``fcntl`` does not exist (Windows)
    folders are not locked. One process taking the lock twice (through two open files) is
    refused too, so callers take it once, at their entry point.

    Args:
        folder: an existing folder.
        command: what writes (``svolsdf evaluate``), named to whoever finds the folder locked.

    Raises:
        InputError: another process holds the folder; the message names the folder, the command
            and its pid.
    """
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not POSIX
        yield
        return
    folder = Path(folder)
    f = open(folder / LOCK_NAME, "a+")  # noqa: SIM115 - held for the whole command
    try:
        try:
            fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            f.seek(0)
            holder = " ".join(f.read().split()) or "pid ?"
            raise InputError(f"{folder}: another svolsdf run ({holder}) is writing this "
                             "folder; wait for it or choose another output folder") from None
        f.seek(0)
        f.truncate()
        f.write(f"{command}, pid {os.getpid()}")
        f.flush()
        yield
    finally:
        f.close()


# --------------------------------------------------------------------------- atomic writes
def unique_temp(path: str | Path, suffix: str = "") -> Path:
    """Create an empty file with a name no other writer uses, beside ``path``
    (``.NAME.<pid>.<random>.tmp<suffix>``), with the permissions a new file gets (the umask's,
    not mkstemp's owner-only)."""
    path = Path(path)
    while True:
        tmp = path.with_name(f".{path.name}.{os.getpid()}.{secrets.token_hex(4)}.tmp{suffix}")
        try:
            os.close(os.open(tmp, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o666))
            return tmp
        except FileExistsError:  # pragma: no cover - 32 random bits
            continue


def atomic_write(path: str | Path, write: Callable[[Path], None], suffix: str = "") -> Path:
    """Write ``path`` through a uniquely named temporary file beside it, then rename it.

    A failure (a full disk, a killed process aside) removes the temporary file and leaves the
    previous ``path`` as it was; two writers of one file never share a temporary name.

    Args:
        path: the target; its folder is created.
        write: called with the temporary path; writes the whole file there.
        suffix: the temporary file's suffix, for writers that add or need one (np.save: .npy).

    Raises:
        InputError: the file cannot be written (no space left, read-only, ...); the message
            names ``path``.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        tmp = unique_temp(path, suffix)
    except OSError as e:
        raise InputError(f"{path}: cannot write it ({e.strerror or e})") from None
    try:
        write(tmp)
        os.replace(tmp, path)
    except OSError as e:
        tmp.unlink(missing_ok=True)
        if e.errno == errno.ENOSPC:
            raise InputError(f"{path}: cannot write it, the disk is full; free some space and "
                             "rerun (finished files are kept)") from None
        raise InputError(f"{path}: cannot write it ({e.strerror or e})") from None
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


# --------------------------------------------------------------------------- provenance
def config_digest(path: str | Path) -> str | None:
    """12-hex digest of a config.yaml's values (comments and layout do not count); None when the
    file is missing or is not YAML."""
    import yaml

    try:
        data = yaml.safe_load(Path(path).read_text())
    except (OSError, ValueError, yaml.YAMLError):
        return None
    text = json.dumps(data, sort_keys=True, default=str)
    return hashlib.sha1(text.encode()).hexdigest()[:12]


def read_stage_state(folder: str | Path) -> dict:
    """FOLDER/stages.json as a dict ({} when missing or unreadable)."""
    try:
        st = json.loads((Path(folder) / "stages.json").read_text())
    except (OSError, ValueError, UnicodeDecodeError):
        return {}
    return st if isinstance(st, dict) else {}


def output_provenance(folder: str | Path, outputs: list[str]) -> dict[str, str]:
    """Whether each of ``outputs`` (names of `OUTPUT_STAGES`, or stages such as "field") was
    made under FOLDER/config.yaml.

    Returns:
        {output: "config.yaml" (made under it) | "unknown" (no record: a folder from before the
        record, or of svolsdf mvs) | "another config" (made by an earlier config: a rerun with
        new options stopped before it made this output again)}.
    """
    folder = Path(folder)
    prov = read_stage_state(folder).get("provenance")
    digest = config_digest(folder / "config.yaml")
    res = {}
    for name in outputs:
        rec = prov.get(OUTPUT_STAGES.get(name, name)) if isinstance(prov, dict) else None
        made = rec.get("config") if isinstance(rec, dict) else None
        if made is None or digest is None:
            res[name] = "unknown"
        else:
            res[name] = "config.yaml" if made == digest else "another config"
    return res
