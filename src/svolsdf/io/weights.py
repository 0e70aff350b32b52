"""Published network weights: where each comes from, its SHA-256, and the torch cache.

A network whose weights are published at a fixed address (torchvision's LPIPS backbones, the
PatchmatchNet TorchScript module) is fetched the way torchvision fetches its own: once, into
the torch cache (``torch.hub.get_dir()/checkpoints``, under ``$TORCH_HOME``), with a message
naming the address and the size, and kept only when its SHA-256 is the published one. A
machine without internet passes a local copy instead (each network's option or environment
variable); docs/dependencies.md lists the sources.
"""

from __future__ import annotations

import hashlib
import logging
import os
from dataclasses import dataclass
from pathlib import Path

from svolsdf.errors import InputError

__all__ = ["PublishedWeights", "cached_weights", "is_published", "sha256"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PublishedWeights:
    """One published weights file."""

    what: str
    """The weights in words, for messages ("torchvision's vgg16")."""
    file: str
    """Its name in the torch cache."""
    url: str
    """Where it is published."""
    sha256: str
    """SHA-256 of the published file."""
    size: int
    """Bytes."""


def sha256(path: str | Path) -> str:
    """Hex SHA-256 of a file, read in 1 MiB blocks."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(1 << 20):
            h.update(block)
    return h.hexdigest()


def is_published(path: str | Path, spec: PublishedWeights) -> bool:
    """The file at ``path`` is the published one (same size and SHA-256)."""
    p = Path(path)
    return p.stat().st_size == spec.size and sha256(p) == spec.sha256


def cached_weights(spec: PublishedWeights, offline: str, progress: bool = True) -> Path:
    """The published file in the torch cache, downloaded there the first time.

    A cached file of another size is refused (a download cut short elsewhere); a download is
    kept only when its SHA-256 is the published one.

    Args:
        spec: the file.
        offline: how to give a local copy instead, for messages ("--weights FILE").
        progress: a progress bar while downloading.

    Raises:
        InputError: the cache cannot be written, the download failed (no network: the message
            names the address and ``offline``), or it is not the published file (removed).
    """
    import torch

    from svolsdf.io.runfolder import unique_temp

    folder = Path(torch.hub.get_dir()) / "checkpoints"
    dst = folder / spec.file
    if dst.is_file():
        size = dst.stat().st_size
        if size != spec.size:
            raise InputError(f"{dst}: {size} bytes, but {spec.what} ({spec.file}) has "
                             f"{spec.size}; remove it to download it again")
        return dst
    log.warning("%s: downloading %s (%.1f MB, once) into %s; without internet, %s", spec.what,
                spec.url, spec.size / 1e6, folder, offline)
    try:
        folder.mkdir(parents=True, exist_ok=True)
        tmp = unique_temp(dst)
    except OSError as e:
        raise InputError(f"{folder}: cannot write the torch cache ({e.strerror or e}); set "
                         "TORCH_HOME to a writable folder") from None
    try:
        try:
            torch.hub.download_url_to_file(spec.url, str(tmp), progress=progress)
        except OSError as e:  # no network, refused, a full disk
            raise InputError(f"{spec.what}: cannot download {spec.url} ({e}); download it "
                             f"elsewhere and {offline}") from None
        got = sha256(tmp)
        if got != spec.sha256:
            raise InputError(f"{spec.url}: the download's SHA-256 is {got}, not the published "
                             f"{spec.sha256}; nothing was kept")
        os.replace(tmp, dst)
    finally:
        tmp.unlink(missing_ok=True)
    return dst
