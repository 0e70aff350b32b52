"""Each choice is declared once, as a ``Literal`` in the schema: `svolsdf.config.choices` reads
it, and the trainer's ablations and the benchmark's modes come from it."""

from __future__ import annotations

from typing import Literal, get_args, get_type_hints

import pytest

from svolsdf.config import Config, TrainConfig, choices


def test_choices_read_the_schema_literal():
    hints = get_type_hints(TrainConfig)
    assert choices("train.mode") == get_args(hints["mode"])
    (lit, none) = get_args(hints["ablation"])  # Literal[...] | None
    assert none is type(None)
    assert choices("train.ablation") == get_args(lit)
    assert choices("preset") == get_args(get_type_hints(Config)["preset"])
    assert choices("scene.lighting") == ("max",)  # int | Literal["max"]
    assert get_args(Literal["svolsdf"]) == ("svolsdf",)


@pytest.mark.parametrize("option", ["train.steps", "train.nope", "nope", "scene"])
def test_choices_refuse_an_option_without_a_literal(option):
    with pytest.raises(KeyError):
        choices(option)


def test_the_trainer_and_the_benchmark_take_the_schema_choices():
    from svolsdf.commands.benchmark import MODES, BenchmarkConfig
    from svolsdf.optimize.modes import ABLATIONS

    assert ABLATIONS == (None, *choices("train.ablation"))
    assert MODES == choices("train.mode") == ("svolsdf", "mvs-only", "volsdf")
    assert BenchmarkConfig(scenes=[]).modes == list(choices("train.mode"))
