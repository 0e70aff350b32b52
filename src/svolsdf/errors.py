"""Errors that the command line reports as one clear line: exit status 2 for bad input, 130
for an interrupted run."""

from __future__ import annotations

__all__ = ["InputError", "RunInterrupted"]


class InputError(ValueError):
    """Bad user input (a file, a folder, an option). The message names the file and the problem."""


class RunInterrupted(KeyboardInterrupt):
    """Ctrl-C stopped a run. The message names the stage that stopped and says how to resume.

    A `KeyboardInterrupt`, so that code catching ``Exception`` (a benchmark's per-run
    ``try``) still stops.
    """
