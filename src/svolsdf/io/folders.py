"""Output folders: created and proven writable before any work goes into them."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from svolsdf.errors import InputError

__all__ = ["ensure_writable_folder"]


def ensure_writable_folder(path: str | Path, what: str = "output folder") -> Path:
    """Create ``path`` (with its parents) if needed and check that a file can be written in it.

    A read-only mount, a folder of another user or a path under /sys fails here, with one line,
    rather than as a traceback after minutes of work.

    Args:
        path: the folder.
        what: what the folder is, for the message.

    Returns:
        ``path`` as a `Path`.

    Raises:
        InputError: the path is a file, cannot be created, or is not writable.
    """
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise InputError(f"{path}: {what} path exists and is not a folder")
    try:
        path.mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(prefix=".svolsdf-write-test-", dir=path)
        os.close(fd)
        os.unlink(probe)
    except OSError as e:
        reason = e.strerror or e.__class__.__name__
        raise InputError(f"{path}: cannot write the {what} ({reason}); choose a writable "
                         "folder") from None
    return path
