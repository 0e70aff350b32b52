"""Errors that the command line reports as one clear line with exit status 2."""

from __future__ import annotations

__all__ = ["InputError"]


class InputError(ValueError):
    """Bad user input (a file, a folder, an option). The message names the file and the problem."""
