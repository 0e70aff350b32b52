"""The ``svolsdf`` command: argument parsing only; the work happens in the package.

Each sub-command maps its options onto the package's functions / dataclass configs. Bad input
(`svolsdf.errors.InputError` and its subclasses, missing files) ends with exit status 2 and one
line naming the file and the problem; ``--debug`` shows the traceback instead.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import sys
from typing import NoReturn

from svolsdf.runtime import set_cpu_env

set_cpu_env()  # before the commands' imports load torch (`svolsdf.runtime.CPU_ENV`: why)

try:
    # the console script imports this module before `main` runs, and the commands' imports load
    # torch (seconds): a Ctrl-C meanwhile ends as a stopped run does, in one line
    import typer

    from svolsdf.cli import results, runs  # noqa: F401  (registers the commands on the app)
    from svolsdf.cli.app import _STATE, _Stopped, app, build_config
    from svolsdf.errors import InputError, interrupted, note_interrupt, watch_interrupts
except KeyboardInterrupt:
    print("interrupted", file=sys.stderr)
    raise SystemExit(130) from None

__all__ = ["REPEATED_OPTIONS", "app", "build_config", "expand_list_options", "main"]

#: options that take several values, each one argument as typed (a path with spaces stays one
#: path): ``--scenes A B`` is read as ``--scenes A --scenes B``
REPEATED_OPTIONS = ("--scenes", "--modes")
#: options whose values the command parses itself from one string of view ids:
#: ``--views 25 22 28`` is read as ``--views "25 22 28"`` (also ``25,22,28`` and ``auto 3``)
_JOINED_OPTIONS = ("--views",)


def expand_list_options(argv: list[str]) -> list[str]:
    """The argument list with the list options in the form typer takes.

    ``--scenes A B`` -> ``--scenes A --scenes B`` (also from ``--scenes=A B``): each value stays
    the one argument the shell gave, never split on spaces. ``--views 25 22 28`` -> ``--views
    "25 22 28"``: view ids, which the command splits on spaces and commas. The values of a list
    option run until the next token that starts with ``-`` (a negative number still counts as a
    value) or, for ``--views``, is not a number.
    """
    out: list[str] = []
    i = 0
    while i < len(argv):
        tok = argv[i]
        i += 1
        name, eq, first = tok.partition("=")
        if name not in REPEATED_OPTIONS + _JOINED_OPTIONS or not tok.startswith("--"):
            out.append(tok)
            continue
        vals = [first] if eq else []
        while i < len(argv):
            t = argv[i]
            is_num = t.lstrip("-").replace(",", "").isdigit()
            if (t.startswith("-") and not is_num) or (name == "--views" and vals and not is_num):
                break
            vals.append(t)
            i += 1
        if not vals:
            out.append(tok)  # typer says that the option needs a value
        elif name in REPEATED_OPTIONS:
            for v in vals:
                out += [name, v]
        else:
            out += [name, " ".join(vals)]
    return out


def main(argv: list[str] | None = None) -> None:
    """Console entry point (``svolsdf``).

    Exit status: 0 done; 1 a benchmark job failed (the other jobs' rows are written, the last
    line names the failed ones); 2 bad input, a bad option, or a file or folder that cannot be
    read or written (one line, ``--debug`` for the traceback); 130 Ctrl-C, 143 SIGTERM (one
    line; a stopped reconstruction names its stage, and a rerun resumes it). As the process's
    command (``argv`` None: ``python -m svolsdf``, the ``svolsdf`` script) it ends the process
    itself (`_end_process`).
    """
    if argv is not None:
        _guarded(argv)
        return
    try:
        _guarded(None)
    except SystemExit as e:
        _end_process(e.code)
    _end_process(0)


def _guarded(argv: list[str] | None) -> None:
    """`_main` with its last guard against Ctrl-C."""
    try:
        with watch_interrupts():
            _main(argv)
    except KeyboardInterrupt:
        # a Ctrl-C that lands outside the command's own handling, as it ends (the run's outputs
        # are written by then): the same one line, not a traceback
        print("interrupted", file=sys.stderr)
        raise SystemExit(130) from None


def _end_process(code) -> NoReturn:
    """End the process with the status of SystemExit's ``code``, without Python's shutdown.

    The command is done and its files are written, but Python's shutdown (torch's and OpenMP's
    teardown) takes a moment in which a Ctrl-C ends the process killed by SIGINT (status -2) or
    prints a traceback of whatever it interrupted. Output and log handlers are flushed first; a
    Ctrl-C meanwhile exits 130 with the one line.
    """
    def interrupted_now(signum, frame) -> None:
        print("interrupted", file=sys.stderr, flush=True)
        os._exit(130)

    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
        signal.signal(signal.SIGINT, interrupted_now)
    if code is not None and not isinstance(code, int):  # SystemExit("message"), as Python does
        print(code, file=sys.stderr)
        code = 1
    with contextlib.suppress(Exception):
        sys.stdout.flush()
        sys.stderr.flush()
        logging.shutdown()
    os._exit(code or 0)


def _main(argv: list[str] | None) -> None:
    """`main` without its last guard against Ctrl-C."""
    argv = expand_list_options(list(sys.argv[1:] if argv is None else argv))
    _STATE["argv"] = list(argv)  # the command line, for the records that name it (OUT/run.json)
    debug = "--debug" in argv
    got = []  # SIGTERM (a scheduler's or `kill`'s stop) is answered as Ctrl-C is, status 143

    def terminate(signum, frame):
        got.append(signum)
        note_interrupt()
        raise KeyboardInterrupt

    try:
        previous = signal.signal(signal.SIGTERM, terminate)
    except ValueError:  # not the main thread: leave signals alone
        previous = None
    try:
        # without standalone mode typer returns the status of typer.Exit, and of Ctrl-C (130)
        code = app(args=argv, standalone_mode=False)
    except _Stopped as e:
        print(e, file=sys.stderr)
        raise SystemExit(128 + got[0] if got else 130) from None
    except (InputError, OSError) as e:  # OSError: a missing, unreadable or unwritable path
        if interrupted():  # an error a library made of the Ctrl-C (errors.py)
            raise KeyboardInterrupt from None
        if debug:
            raise
        msg = str(e) if not isinstance(e, OSError) or not e.filename else (
            f"{e.filename}: {e.strerror or e}"
        )
        # one line, also when the message quotes a library's several lines (torch.load's)
        msg = " ".join(part.strip() for part in msg.splitlines() if part.strip())
        print(f"error: {msg}", file=sys.stderr)
        raise SystemExit(2) from None
    except typer.Exit as e:
        raise SystemExit(e.exit_code) from None
    except typer.Abort:
        print("aborted", file=sys.stderr)
        raise SystemExit(130) from None
    except Exception as e:
        if interrupted():
            raise KeyboardInterrupt from None
        # click's usage errors (an unknown option, a bad value): the message, not a traceback.
        # Recognised by their interface: typer >= 0.2x raises its vendored copy of click's
        # classes, older typer the click package's own
        if callable(getattr(e, "show", None)) and isinstance(getattr(e, "exit_code", None), int):
            e.show()
            raise SystemExit(e.exit_code) from None
        raise
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
    if interrupted() and not code:  # an interrupt that something caught and printed
        code = 130
    if code == 130:
        print("terminated" if got else "interrupted", file=sys.stderr)
        code = 128 + got[0] if got else 130
    if isinstance(code, int) and code != 0:
        raise SystemExit(code)


if __name__ == "__main__":
    main()
