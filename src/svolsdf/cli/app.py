"""The typer application, its root options, and the option parsing the commands share."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Annotated

import typer

from svolsdf.cli.flags import RECONSTRUCT_FLAGS, flag_labels
from svolsdf.errors import InputError, RunInterrupted

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    help="S-VolSDF: surfaces, point clouds and novel views from a few calibrated photos.",
    pretty_exceptions_enable=False,
)

_STATE = {"debug": False}


class _Stopped(Exception):
    """A run that Ctrl-C stopped, with its message (typer would turn the `RunInterrupted`, a
    KeyboardInterrupt, into a bare exit status 130)."""


def _run_pipeline(pipeline) -> dict:
    from svolsdf.io.progress import show_progress

    try:  # --no-progress turns off every stage's bars, not only the optimization's
        with show_progress(None if getattr(pipeline, "progress", True) else False):
            summary = pipeline.run()
    except RunInterrupted as e:
        raise _Stopped(str(e)) from None
    if summary.get("out"):  # the run folder it finished
        _record_run(Path(summary["out"]), getattr(pipeline, "device", None))
    return summary


def _record_run(out: Path, device) -> None:
    """OUT/run.json: the command line, version, device and date of the run that finished (the
    report shows them)."""
    import datetime
    import json
    import shlex

    import torch

    from svolsdf import __version__
    from svolsdf.io.runfolder import RunFolder, atomic_write

    argv = _STATE.get("argv")
    info = {"command": "svolsdf " + shlex.join(argv) if argv is not None else None,
            "version": __version__, "device": str(device), "torch": torch.__version__,
            "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")}
    text = json.dumps(info, indent=1) + "\n"
    atomic_write(RunFolder(out).run_file, lambda tmp: tmp.write_text(text))


def _print_version(given: bool) -> None:
    if given:
        from svolsdf import __version__

        typer.echo(f"svolsdf {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    debug: Annotated[bool, typer.Option("--debug", help="Show tracebacks on errors.")] = False,
    verbose: Annotated[bool, typer.Option("--verbose", "-v", help="More log output.")] = False,
    version: Annotated[bool, typer.Option(
        "--version", callback=_print_version, is_eager=True,
        help="Print the version and exit.")] = False,
) -> None:
    _STATE["debug"] = debug
    logging.basicConfig(
        level=logging.DEBUG if verbose else logging.INFO,
        format="%(levelname)s %(name)s: %(message)s",
    )




# --------------------------------------------------------------------------- info
#: the help of ``--views`` wherever it names the input views (reconstruct, mvs): one default
VIEWS_HELP = ("Input view ids, e.g. --views 25 22 28, or --views auto [N]: N (3) views with good "
              "overlap and baselines (default: DTU's 25 22 28, or a central view and its two "
              "best source views).")


def _parse_views(text: str | None) -> list[int] | None:
    """'25,22,28' or '25 22 28' -> [25, 22, 28]; None -> None."""
    if text is None:
        return None
    out = []
    for tok in text.replace(",", " ").split():
        try:
            v = int(tok)
        except ValueError:
            raise InputError(f"--views: '{tok}' is not a view id (give integers, e.g. "
                             f"--views 25,22,28)") from None
        if v in out:
            raise InputError(f"--views {text}: view {v} is given twice (give each view once)")
        out.append(v)
    if not out:
        raise InputError("--views: no view ids given (e.g. --views 25,22,28)")
    return out


def _parse_auto_views(text: str | None) -> int | None:
    """'auto' -> 3, 'auto 5' -> 5; anything else -> None (view ids)."""
    if text is None:
        return None
    tok = text.replace(",", " ").split()
    if not tok or tok[0].lower() != "auto":
        return None
    if len(tok) > 2 or (len(tok) == 2 and not tok[1].isdigit()):
        raise InputError(f"--views: '{text}' is neither view ids nor 'auto [N]' (e.g. --views "
                         f"auto 3)")
    n = int(tok[1]) if len(tok) == 2 else 3
    if n < 2:
        raise InputError(f"--views auto {n}: need at least 2 views")
    return n




# --------------------------------------------------------------------------- reconstruct / demo
def _parse_size(text: str | None) -> list[int] | None:
    """'768x576' -> [768, 576]; None stays None (`svolsdf.scene.size.parse_size`)."""
    from svolsdf.scene.size import parse_size

    return None if text is None else list(parse_size(text))


def base_config(config: Path | None, preset_name: str | None) -> object:
    """The config that `reconstruct` and `config` start from: ``--config FILE`` (its values
    over the preset it names) or the preset ``--preset`` names (default fast). Both given: the
    file's preset must be the one ``--preset`` names, else neither is silently dropped.

    Raises:
        InputError: an unreadable or invalid file (`svolsdf.config.load_config`), or a
            ``--preset`` that contradicts the file's.
    """
    from svolsdf.config import load_config, preset

    if config is not None:
        cfg = load_config(config)
        if preset_name is not None and preset_name != cfg.preset:
            raise InputError(f"--preset {preset_name} contradicts {config} (preset "
                             f"{cfg.preset}); drop one of them")
        return cfg
    return preset(preset_name or "fast")


def build_config(scene: Path | None, config: Path | None, preset_name: str | None,
                 overrides: dict, labels: dict[str, str] | None = None,
                 sets: list[str] | None = None) -> object:
    """Config from --config (or the preset), then the command-line overrides, then ``--set``
    items, validated (`svolsdf.config.validate_config`) before anything runs.

    Args:
        overrides: dotted config key -> value (None: not given).
        labels: dotted config key -> its option, for error messages.
        sets: ``--set section.option=value`` items (`svolsdf.config.parse_set`).
    """
    from svolsdf.config import apply_overrides, parse_set
    from svolsdf.config.presets import scene_overrides

    cfg = base_config(config, preset_name)
    apply_overrides(cfg, {"scene.path": None if scene is None else str(scene), **overrides},
                    labels={"scene.path": "SCENE", **(labels or {})})
    given = parse_set(sets)
    # the released preset's per-scan constants, unless an option or --set gives the value;
    # from a --config file they are already in it
    if config is None:
        scene_overrides(cfg, {k for k, v in overrides.items() if v is not None} | set(given))
    if given:
        apply_overrides(cfg, given, labels={k: f"--set {k}" for k in given}, skip_none=False)
    if not cfg.scene.path:
        raise InputError("no scene given (pass SCENE or a --config with scene.path)")
    return cfg




#: config key -> the `reconstruct` option that sets it (for error messages): the generated flags
#: (`svolsdf.cli.flags.RECONSTRUCT_FLAGS`) and the hand-written ones
_RECONSTRUCT_OPTIONS = {
    **flag_labels(RECONSTRUCT_FLAGS),
    "scene.views": "--views", "scene.image_size": "--size",
    "fusion.network": "--fusion-network",
    "fusion.network_weights": "--fusion-network",
}


