"""The command line offers exactly the schema's choices (`svolsdf.config.choices`): the help of
``reconstruct --mode`` and ``--ablation``, and ``benchmark --modes``."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import typer

from svolsdf.cli import app
from svolsdf.config import choices
from svolsdf.errors import InputError


def _option(command: str, flag: str):
    cmd = typer.main.get_command(app).commands[command]
    return next(p for p in cmd.params if flag in p.opts)


def _named(help_text: str) -> set[str]:
    """The choices a help text names: its words outside parentheses, but "or"."""
    return set(re.findall(r"[\w-]+", re.sub(r"\([^)]*\)", "", help_text))) - {"or"}


@pytest.mark.parametrize("flag, option", [("--mode", "train.mode"),
                                          ("--ablation", "train.ablation")])
def test_reconstruct_help_names_the_schema_choices(flag, option):
    assert _named(_option("reconstruct", flag).help) == set(choices(option))


def test_benchmark_modes_are_the_schema_choices(tmp_path):
    from svolsdf.commands.benchmark import BenchmarkConfig
    from svolsdf.commands.benchmark_checks import validate_benchmark as _validate

    opt = _option("benchmark", "--modes")
    assert list(opt.default) == list(choices("train.mode"))
    assert _named(opt.help.split(":", 1)[1].replace("--modes", "")) == set(choices("train.mode"))
    scene = Path(tmp_path)
    _validate(BenchmarkConfig(scenes=[scene], modes=list(choices("train.mode"))))
    with pytest.raises(InputError, match="unknown mode"):
        _validate(BenchmarkConfig(scenes=[scene], modes=["mvs"]))
