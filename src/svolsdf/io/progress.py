"""Progress bars of the slow loops: one tqdm bar per loop, named after its stage, with the count
done and the time left (ETA).

A loop that can take more than a few seconds (the MVS stages per view, the guide's rendering,
fusion per view, the TSDF and marching-cubes grids, novel views) iterates through
`progress_bar`. Whether bars show is the command's choice, made once around its work with
`show_progress` (``--no-progress``: none); left to itself a bar shows when stderr is a terminal,
as tqdm decides (``disable=None``), so logs and pipes stay clean.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from contextvars import ContextVar

__all__ = ["BAR_FORMAT", "progress_bar", "show_progress"]

BAR_FORMAT = "{desc}: {percentage:3.0f}%|{bar}| {n_fmt}/{total_fmt} [{elapsed}, ETA {remaining}]"
"""The bar's layout: the stage's name, the share done, the time spent and the time left."""

_SHOW: ContextVar[bool | None] = ContextVar("svolsdf_show_progress", default=None)


@contextmanager
def show_progress(show: bool | None) -> Iterator[None]:
    """Bars opened inside the block show (True), never show (False), or show on a terminal
    (None, the default outside any block). The command line wraps a command's work in it."""
    token = _SHOW.set(show)
    try:
        yield
    finally:
        _SHOW.reset(token)


def progress_bar(iterable: Iterable | None = None, desc: str = "", total: int | None = None,
                 unit: str = "view", show: bool | None = None, leave: bool = False):
    """A tqdm bar over ``iterable`` (or a manual one of ``total`` steps: ``bar.update(n)``).

    Args:
        iterable: what the loop iterates over; None for a bar updated by hand.
        desc: the stage's name, e.g. "MVS stage 1".
        total: the number of steps (default: ``len(iterable)``).
        unit: what one step is ("view", "chunk", ...).
        show: True / False force the bar on / off; None follows `show_progress`, else the
            terminal.
        leave: keep the finished bar on the screen.

    Returns:
        a ``tqdm`` object: iterate over it, or call ``update`` and ``close``.
    """
    from tqdm.auto import tqdm

    on = _SHOW.get() if show is None else show
    return tqdm(iterable, desc=desc, total=total, unit=unit, leave=leave,
                disable=None if on is None else not on, bar_format=BAR_FORMAT,
                dynamic_ncols=True)
