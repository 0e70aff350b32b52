"""The field-kind registry (`svolsdf.field.kinds`): the built-in kinds keep their order and
models; a kind registered here, in the test file alone, is accepted by the config and built by
the pipeline's builder (with the background and beta floor the config asks for); an unregistered
name is refused naming the option."""

from __future__ import annotations

import pytest
import torch

from svolsdf.config import choices, preset, validate_config
from svolsdf.errors import InputError
from svolsdf.field.grid import GridSDFField
from svolsdf.field.kinds import (
    FieldInputs,
    get_field_kind,
    register_field_kind,
    registered_field_kinds,
)
from svolsdf.field.volsdf import VolSDFField, VolSDFFieldConfig
from svolsdf.pipeline.builders import build_model


class _TinyMLP(VolSDFField):
    """The VolSDF field, two hidden layers of 16."""


@register_field_kind("test-tiny-mlp")
def _tiny(i: FieldInputs):
    return _TinyMLP(VolSDFFieldConfig(n_layers=2, d_hidden=16, render_hidden=16, skip_in=()))


def _box():
    return torch.tensor([[-0.5] * 3, [0.5] * 3])


def test_builtin_kinds_are_registered_in_the_documented_order():
    assert registered_field_kinds()[:2] == ["grid", "mlp"]
    assert choices("field.kind") == tuple(registered_field_kinds())
    assert preset("fast").field.kind == "grid" and preset("paper").field.kind == "mlp"


def test_builtin_kinds_are_built_as_configured():
    cfg = preset("fast")
    assert isinstance(build_model(cfg, _box), GridSDFField)
    cfg = preset("paper")
    cfg.field.mlp_depth, cfg.field.mlp_width = 6, 48

    def no_box():
        raise AssertionError("the MLP needs no box")

    m = build_model(cfg, no_box)
    assert isinstance(m, VolSDFField)
    assert (m.config.n_layers, m.config.d_hidden) == (6, 48)


def test_a_registered_kind_is_a_valid_choice_and_is_built():
    cfg = preset("paper")
    cfg.field.kind = "test-tiny-mlp"
    cfg.field.background = True
    cfg.train.beta_min = 1e-3
    validate_config(cfg)
    m = build_model(cfg, _box)
    assert isinstance(m, _TinyMLP)
    assert hasattr(m, "background") and m.laplace.beta_min == pytest.approx(1e-3)


def test_an_unregistered_kind_is_refused_naming_the_option():
    cfg = preset("fast")
    cfg.field.kind = "no-such-kind"
    with pytest.raises(InputError, match=r"field\.kind = 'no-such-kind': expected one of "
                                         r"'grid', 'mlp'"):
        validate_config(cfg)
    with pytest.raises(InputError, match="unknown field kind 'no-such-kind'"):
        get_field_kind("no-such-kind")
