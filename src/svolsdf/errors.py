"""Errors that the command line reports as one clear line: exit status 2 for bad input, 130
for an interrupted run; and the record of a Ctrl-C that tells an interrupt from a failure.

A Ctrl-C raises `KeyboardInterrupt` wherever Python happens to be, and a library can turn it into
an error of its own: pycolmap's import, interrupted half-way, raises RuntimeError ("Cannot import
the C++ backend"), and a loader may raise its own error for a read that stopped. Code that
catches errors to recover (a fallback mesh method, a stage that reruns when its file cannot be
read) would then recover from the user's Ctrl-C. Within `watch_interrupts` (the command line and
`svolsdf.pipeline.Pipeline.run` enter it) the SIGINT handler first records the interrupt, so
such code asks `raise_if_interrupted` before it recovers, and the pipeline asks it before it
marks a stage finished (an interrupt that something swallowed still stops the run).
"""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Iterator

__all__ = ["InputError", "RunInterrupted", "interrupted", "note_interrupt",
           "raise_if_interrupted", "watch_interrupts"]


class InputError(ValueError):
    """Bad user input (a file, a folder, an option). The message names the file and the problem."""


class RunInterrupted(KeyboardInterrupt):
    """Ctrl-C stopped a run. The message names the stage that stopped and says how to resume.

    A `KeyboardInterrupt`, so that code catching ``Exception`` (a benchmark's per-run
    ``try``) still stops.
    """


#: whether a SIGINT (or the command line's SIGTERM) arrived within `watch_interrupts`: process
#: state, as a signal is the process's
_INTERRUPT = {"seen": False}


def note_interrupt() -> None:
    """Record that the process was asked to stop (a signal handler calls it)."""
    _INTERRUPT["seen"] = True


def interrupted() -> bool:
    """A Ctrl-C (or the command line's SIGTERM) arrived within the outermost
    `watch_interrupts`."""
    return _INTERRUPT["seen"]


def raise_if_interrupted() -> None:
    """Raise `KeyboardInterrupt` when the process was interrupted (`interrupted`): call it
    before recovering from an error, which may be an interrupt a library converted.

    Raises:
        KeyboardInterrupt: the process was interrupted.
    """
    if _INTERRUPT["seen"]:
        raise KeyboardInterrupt


def _on_sigint(signum, frame) -> None:
    """Python's own SIGINT behaviour (raise KeyboardInterrupt) after recording it."""
    note_interrupt()
    raise KeyboardInterrupt


@contextlib.contextmanager
def watch_interrupts() -> Iterator[None]:
    """Within, SIGINT is recorded (`interrupted`) before it raises `KeyboardInterrupt`.

    The outermost entry starts with no interrupt recorded and forgets it again on leaving. It
    installs the handler only in the main thread and over Python's default handler, so an ignored
    SIGINT (a shell's background job) and a caller's own handler are left alone. Nested entries
    change nothing.
    """
    previous = signal.getsignal(signal.SIGINT)
    if threading.current_thread() is not threading.main_thread() or previous is _on_sigint:
        yield
        return
    own = previous is signal.default_int_handler
    _INTERRUPT["seen"] = False
    if own:
        signal.signal(signal.SIGINT, _on_sigint)
    try:
        yield
    finally:
        if own:
            signal.signal(signal.SIGINT, previous)
        _INTERRUPT["seen"] = False
