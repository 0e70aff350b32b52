"""The memory check of `validate_config`: options whose allocations cannot fit the memory the
machine has available are refused naming the option; the presets pass; no answer from the
system means no check."""

from __future__ import annotations

import pytest

import svolsdf.config.validate as validate
from svolsdf.config import preset, validate_config
from svolsdf.config.validate import available_memory, check_memory, memory_needs
from svolsdf.errors import InputError

GB = 2**30


def test_the_machine_answers_how_much_memory_it_has():
    have = available_memory()
    assert have is not None and have > 0


@pytest.mark.parametrize(("option", "value", "key"), [
    ("field", {"grid_resolution": 4096}, "field.grid_resolution"),
    ("mvs", {"ndepths": [40_000_000, 32, 8]}, "mvs.ndepths"),
])
def test_an_option_beyond_the_memory_available_is_refused_by_name(option, value, key,
                                                                  monkeypatch):
    cfg = preset("fast")
    for k, v in value.items():
        setattr(getattr(cfg, option), k, v)
    monkeypatch.setattr(validate, "available_memory", lambda: 1 * GB)
    with pytest.raises(InputError, match=f"^{key} = .*at least .* GB of memory, but 1 GB is "
                                         "available"):
        validate_config(cfg)
    monkeypatch.setattr(validate, "available_memory", lambda: None)  # cannot tell: no check
    validate_config(cfg)


def test_the_estimates_are_the_allocations_they_bound():
    cfg = preset("fast")
    cfg.field.grid_resolution, cfg.mvs.ndepths, cfg.mvs.scale = 100, [64, 32, 8], 2.0
    needs = {keys[0]: b for keys, b, _ in memory_needs(cfg, size=(80, 64), views=3)}
    # SDF grid: values and gradients, 100 x 20 x 20 nodes at least, float32
    assert needs["field.grid_resolution"] == 2 * 100 * 20 * 20 * 4
    # stage 1 at 2 x 80x64 / 4 = 40x32 for three views, against stage 3 at 160x128 for one
    assert needs["mvs.ndepths"] == max(2 * 64 * 40 * 32 * 4 * 3, 2 * 8 * 160 * 128 * 4)


def test_the_presets_fit_a_small_machine(monkeypatch):
    monkeypatch.setattr(validate, "available_memory", lambda: 2 * GB)
    for name in ("fast", "paper"):
        cfg = preset(name)
        check_memory(cfg, size=(768, 576), views=3)
