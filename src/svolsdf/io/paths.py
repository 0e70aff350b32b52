"""Paths a user types: one place that turns them into `Path`s and, when one cannot be used, says
why in one line before any work.

Every path a command takes (scene folders, OUT, ``--config``, weights, ground truth, lists of
scenes) passes through these functions. A path may hold spaces and non-ASCII characters, start
with ``~`` or ``~user`` (expanded here, for paths the shell did not expand: a quoted argument, an
``--option=~/x`` form, a config file), hold relative parts and symbolic links. Relative parts are
left to the operating system, which resolves them against the working folder and resolves a
``..`` after a symbolic link the way a shell's ``ls`` does; messages show the absolute location
beside the path as typed.

A refusal raises `InputError` (the command line prints its one line, exit status 2) naming the
path and the real cause:

- missing, and which part of the path is the first to be missing;
- a dangling symbolic link, and where it points (for the path itself or a folder on its way);
- a file where a folder is wanted, and the other way round;
- a folder that cannot be read or written, naming the folder and the system's reason.

An output folder that is a symbolic link to a folder that does not exist yet is created through
the link when the target's own folder exists and is writable (as ``mkdir`` of the target would);
when that folder is missing too (an unmounted disk, a moved project) it is refused, naming the
link, its target and the missing folder, rather than created somewhere the user did not mean.
"""

from __future__ import annotations

import errno
import logging
import os
import stat
import tempfile
from pathlib import Path

from svolsdf.errors import InputError

__all__ = [
    "input_dir",
    "input_file",
    "input_path",
    "output_dir",
    "output_file",
    "path_label",
    "user_path",
]

log = logging.getLogger(__name__)


def user_path(path: str | os.PathLike) -> Path:
    """``path`` as a `Path` with a leading ``~`` or ``~user`` expanded; nothing else changes
    (relative parts stay relative, links are not resolved)."""
    text = os.fspath(path)
    if isinstance(text, bytes):
        text = os.fsdecode(text)
    return Path(os.path.expanduser(text))


def _absolute(path: Path) -> Path:
    """Where ``path`` is, absolute, with links and ``..`` of its folders resolved but not the
    last part (so that a link is shown as itself, not as its target)."""
    if path.name in ("", ".", ".."):
        return Path(os.path.realpath(path))
    return Path(os.path.realpath(path.parent)) / path.name


def path_label(path: str | os.PathLike, option: str | None = None) -> str:
    """How messages name a path: the option that gave it, the path as typed, and where it is
    when that differs (``-o ~/runs/a (/home/me/runs/a)``)."""
    typed = os.fspath(path)
    if isinstance(typed, bytes):
        typed = os.fsdecode(typed)
    where = str(_absolute(user_path(typed)))
    text = typed if typed == where else f"{typed} ({where})"
    return f"{option} {text}" if option else text


def _link_target(link: Path) -> str:
    """A symbolic link's target as stored, with its absolute form when that differs."""
    try:
        raw = os.readlink(link)
    except OSError:
        raw = "?"
    full = os.path.realpath(link)
    return raw if raw == full else f"{raw} ({full})"


def _first_problem(path: Path) -> tuple[str, Path] | None:
    """The first part of ``path``, from its start, that stops the path from being reached:
    ("missing" | "dangling" | "file" | "denied" | "loop" | "error", that part), or None when
    every part can be reached."""
    parts = path.parts
    for k in range(1, len(parts) + 1):
        q = Path(*parts[:k])
        try:
            st = os.stat(q)
        except FileNotFoundError:
            return ("dangling" if os.path.islink(q) else "missing"), q
        except PermissionError:
            return "denied", q.parent if k > 1 else q
        except OSError as e:
            if e.errno == errno.ELOOP:
                return "loop", q
            if e.errno == errno.ENOTDIR:
                return "file", Path(*parts[:k - 1])
            return "error", q
        if k < len(parts) and not stat.S_ISDIR(st.st_mode):
            return "file", q
    return None


def _part_cause(kind: str, q: Path) -> str:
    """What is wrong with the part ``q`` of a path (`_first_problem`'s answer), in words."""
    if kind == "missing":
        return f"{q} does not exist"
    if kind == "dangling":
        return f"{q} is a symbolic link to {_link_target(q)}, which does not exist"
    if kind == "file":
        return f"{q} is a file, not a folder"
    if kind == "denied":
        return f"permission denied in {q}"
    if kind == "loop":
        return f"{q} is a symbolic link that leads back to itself (a loop)"
    try:
        os.stat(q)
    except OSError as e:
        return f"{q}: {e.strerror or e}"
    return f"{q} cannot be reached"


def _unreachable(path: Path, label: str, what: str) -> str:
    """The message for a ``path`` that cannot be reached (os.stat failed)."""
    found = _first_problem(path)
    if found is None:  # it appeared meanwhile, or the system gave another reason
        try:
            os.stat(path)
        except OSError as e:
            return f"{label}: cannot reach the {what} ({e.strerror or e})"
        return f"{label}: cannot reach the {what}"
    kind, q = found
    if q == path and kind == "missing":
        return f"{label}: {what} does not exist"
    if q == path and kind == "dangling":
        return (f"{label}: {what} is a symbolic link to {_link_target(q)}, which does not "
                "exist")
    if kind in ("missing", "dangling", "file"):
        return f"{label}: {what} does not exist: {_part_cause(kind, q)}"
    return f"{label}: cannot reach the {what}: {_part_cause(kind, q)}"


def _existing(path: str | os.PathLike, what: str, option: str | None) -> tuple[Path, str,
                                                                              os.stat_result]:
    """``path`` expanded, its label and its stat; refused when it cannot be reached."""
    p = user_path(path)
    label = path_label(path, option)
    if not os.fspath(path):
        raise InputError(f"{option + ': ' if option else ''}an empty path; give the {what}")
    try:
        st = os.stat(p)
    except OSError:
        raise InputError(_unreachable(p, label, what)) from None
    return p, label, st


def input_dir(path: str | os.PathLike, what: str = "folder", option: str | None = None) -> Path:
    """An existing folder to read.

    Args:
        path: as the user gave it.
        what: what the folder is, for the message ("scene folder").
        option: the option that gave it ("--dtu-gt"), for the message; None for an argument.

    Returns:
        ``path`` with ``~`` expanded (`user_path`).

    Raises:
        InputError: missing (naming the first missing part), a dangling link (naming its
            target), a file, or not readable.
    """
    p, label, st = _existing(path, what, option)
    if not stat.S_ISDIR(st.st_mode):
        raise InputError(f"{label}: {what} is a file, not a folder")
    if not os.access(p, os.R_OK | os.X_OK):
        raise InputError(f"{label}: cannot read the {what} (permission denied)")
    return p


def input_file(path: str | os.PathLike, what: str = "file", option: str | None = None) -> Path:
    """An existing file to read (arguments and errors as `input_dir`; a folder is refused)."""
    p, label, st = _existing(path, what, option)
    if stat.S_ISDIR(st.st_mode):
        raise InputError(f"{label}: {what} is a folder, not a file")
    if not os.access(p, os.R_OK):
        raise InputError(f"{label}: cannot read the {what} (permission denied)")
    return p


def input_path(path: str | os.PathLike, what: str = "file or folder",
               option: str | None = None) -> Path:
    """An existing file or folder to read (arguments and errors as `input_dir`)."""
    p, label, st = _existing(path, what, option)
    mode = os.R_OK | (os.X_OK if stat.S_ISDIR(st.st_mode) else 0)
    if not os.access(p, mode):
        raise InputError(f"{label}: cannot read the {what} (permission denied)")
    return p


def _probe(folder: Path) -> str | None:
    """None when a file can be made in ``folder``, else the system's reason."""
    try:
        fd, probe = tempfile.mkstemp(prefix=".svolsdf-write-test-", dir=folder)
        os.close(fd)
        os.unlink(probe)
    except OSError as e:
        return e.strerror or e.__class__.__name__
    return None


def _make(folder: Path, label: str, what: str) -> None:
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise InputError(f"{label}: cannot write the {what} ({e.strerror or e}); choose a "
                         "writable folder") from None


def output_dir(path: str | os.PathLike, what: str = "output folder", option: str | None = None,
               create: bool = True) -> Path:
    """A folder to write into: an existing writable folder, or one that can be made.

    Args:
        path: as the user gave it.
        what: what the folder is, for the message ("run folder").
        option: the option that gave it ("-o"), for the message; None for an argument.
        create: make the folder (with its missing parents, or the target of a symbolic link
            whose own folder exists: module docstring); False only checks that it could be
            made (nothing is created: the check before a command's other checks).

    Returns:
        ``path`` with ``~`` expanded (`user_path`).

    Raises:
        InputError: a file, a dangling link whose target cannot be made (naming link and
            target), a part of the path that is a file or a dangling link, or a folder that
            cannot be written (naming it and the system's reason).
    """
    if not os.fspath(path):
        raise InputError(f"{option + ': ' if option else ''}an empty path; give the {what}")
    p = user_path(path)
    _output_dir(p, path_label(path, option), what, create)
    return p


def _output_dir(p: Path, label: str, what: str, create: bool) -> None:
    """`output_dir` of the expanded path ``p``, named ``label`` in messages."""
    try:
        st = os.stat(p)
    except OSError:
        st = None
    if st is not None:
        if not stat.S_ISDIR(st.st_mode):
            raise InputError(f"{label}: {what} is a file, not a folder; give a folder")
        reason = _probe(p)
        if reason is not None:
            raise InputError(f"{label}: cannot write the {what} ({reason}); choose a writable "
                             "folder")
        return
    found = _first_problem(p)
    if found is not None and found[0] == "dangling" and found[1] == p:
        # a link to a folder that does not exist yet: made through the link when the target's
        # own folder is there
        target = Path(os.path.realpath(p))
        link = f"is a symbolic link to {_link_target(p)}, which does not exist"
        where = _first_problem(target.parent)
        if where is None and not os.path.isdir(target.parent):
            where = ("file", target.parent)
        if where is not None:
            raise InputError(f"{label}: {what} {link}, and it cannot be made there: "
                             f"{_part_cause(*where)}; create that folder or point the link "
                             "elsewhere")
        reason = _probe(target.parent)
        if reason is not None:
            raise InputError(f"{label}: cannot write the {what}: it {link}, and "
                             f"{target.parent} is not writable ({reason})")
        if create:
            _make(target, label, what)
            log.info("%s: created %s, where the link points", p, target)
        return
    if found is None:
        raise InputError(_unreachable(p, label, what))
    if found[0] != "missing":
        raise InputError(f"{label}: cannot make the {what}: {_part_cause(*found)}")
    base = found[1].parent  # the deepest folder that exists: the new folders go there
    reason = _probe(base)
    if reason is not None:
        raise InputError(f"{label}: cannot write the {what}: {base} is not writable ({reason});"
                         " choose a writable folder")
    if create:
        _make(p, label, what)
        reason = _probe(p)
        if reason is not None:
            raise InputError(f"{label}: cannot write the {what} ({reason}); choose a writable "
                             "folder")


def output_file(path: str | os.PathLike, what: str = "output file", option: str | None = None,
                create: bool = True) -> Path:
    """A file to write: not a folder, in a folder that exists or can be made and is writable
    (``create``: the folder is made, as `output_dir`).

    Returns:
        ``path`` with ``~`` expanded (`user_path`).

    Raises:
        InputError: a folder, or a folder for it that cannot be made or written (the message
            names the file as given and the folder).
    """
    p = user_path(path)
    label = path_label(path, option)
    if not os.fspath(path):
        raise InputError(f"{option + ': ' if option else ''}an empty path; give the {what}")
    if p.is_dir():
        raise InputError(f"{label}: {what} is a folder, not a file; give a file name")
    if p.is_symlink():
        target = Path(os.path.realpath(p))
        found = _first_problem(target.parent)
        if found is not None:  # a link whose target's folder is missing too: not made
            raise InputError(f"{label}: {what} is a symbolic link to {_link_target(p)}, "
                             f"which cannot be written: {_part_cause(*found)}; point the link "
                             "elsewhere")
        folder = target.parent
    else:
        folder = p.parent
    _output_dir(folder, label, f"folder {folder} of the {what}", create)
    return p
