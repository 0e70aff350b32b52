"""The field-kind registry (`svolsdf.field.kinds`): the built-in kinds keep their order, models
and capabilities; a kind registered here, in the test file alone, is accepted by the config and
built by the pipeline's builder (with the background and beta floor the config asks for), and
the capabilities it registers (its checks, schedule, background sizes, start from MVS, fit to
points) are what the validation and the pipeline use; an unregistered name is refused naming the
option."""

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
from svolsdf.pipeline import options
from svolsdf.pipeline.builders import build_model, grid_schedule


class _TinyMLP(VolSDFField):
    """The VolSDF field, two hidden layers of 16."""


@register_field_kind("test-tiny-mlp")
def _tiny(i: FieldInputs):
    return _TinyMLP(VolSDFFieldConfig(mlp_depth=2, mlp_width=16, render_hidden=16, skip_in=()))


#: what the toy kinds' hooks were called with
_CALLS: list[tuple] = []


def _toy_check(f, t, from_sphere):
    _CALLS.append(("check", from_sphere))
    if f.mlp_width == 77:
        return ("field.kind", f.kind, "field.mlp_width", f.mlp_width, "the toy refuses 77")
    return None


def _toy_schedule(f, t, from_sphere):
    _CALLS.append(("schedule", from_sphere))
    return [(t.steps // 2, 8)]


def _toy_from_mvs(model, volumes, normalization, masks, init_unverified_weight):
    _CALLS.append(("init_from_mvs",))


def _toy_build(i: FieldInputs):
    _CALLS.append(("build", i.from_sphere))
    return _TinyMLP(VolSDFFieldConfig(mlp_depth=2, mlp_width=16, render_hidden=16, skip_in=()))


register_field_kind("test-toy", check=_toy_check, schedule=_toy_schedule,
                    background={"n_layers": 2, "d_hidden": 8, "skip_in": ()})(_toy_build)
register_field_kind("test-toy-mvs", init_from_mvs=_toy_from_mvs, sphere_options=True,
                    fits_points=True)(_toy_build)


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
    assert (m.config.mlp_depth, m.config.mlp_width) == (6, 48)
    assert m.colour_net.layers[0].weight.shape[0] == 48  # the colour network as wide


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


def test_builtin_kinds_carry_their_capabilities():
    grid, mlp = get_field_kind("grid"), get_field_kind("mlp")
    assert grid.starts_from_mvs and grid.sphere_options and grid.fits_points
    assert grid.schedule is not None and grid.check is not None and grid.background
    assert not (mlp.starts_from_mvs or mlp.sphere_options or mlp.fits_points)
    assert mlp.schedule is None and mlp.check is not None and not mlp.background


def test_a_registered_kind_brings_its_own_capabilities():
    cfg = preset("paper")
    cfg.field.kind = "test-toy"
    cfg.field.background = True
    cfg.train.steps = 40
    _CALLS.clear()
    validate_config(cfg)
    assert _CALLS == [("check", True)]  # no start from MVS: from the sphere
    # its schedule, told it starts from the sphere
    assert grid_schedule(cfg) == [(20, 8)] and _CALLS[-1] == ("schedule", True)
    m = build_model(cfg, _box)
    assert _CALLS[-1] == ("build", True)
    c = m.background.config
    assert (c.n_layers, c.d_hidden, c.skip_in) == (2, 8, ())
    assert (c.feature_dim, c.colour_hidden) == (256, 128)  # the rest: the paper's sizes
    # its check's refusal, worded by the validation
    cfg.field.mlp_width = 77
    with pytest.raises(InputError, match=r"^field\.kind = test-toy with field\.mlp_width = 77: "
                                         r"the toy refuses 77$"):
        validate_config(cfg)
    # none of the grid's: no start from MVS, sphere options or fit to points
    cfg = preset("fast")
    cfg.field.kind = "test-toy"
    cfg.mesh.fit_points, cfg.mesh.method = 50, "field"
    assert not (options.field_from_mvs(cfg) or options.grid_from_sphere(cfg)
                or options.wants_mesh_fit(cfg))
    with pytest.raises(InputError, match=r"field\.kind = test-toy with field\.init = mvs: the "
                                         r"test-toy field starts from VolSDF's sphere, not from "
                                         r"the MVS surface \(only grid, test-toy-mvs can\): use "
                                         r"field\.init=sphere"):
        validate_config(cfg)


def test_a_registered_kind_that_starts_from_mvs():
    cfg = preset("fast")
    cfg.field.kind = "test-toy-mvs"
    cfg.mesh.fit_points, cfg.mesh.method = 50, "field"
    validate_config(cfg)
    assert options.field_from_mvs(cfg) and not options.grid_from_sphere(cfg)
    assert options.wants_mesh_fit(cfg)
    assert grid_schedule(cfg) == []  # no schedule of its own
    _CALLS.clear()
    build_model(cfg, _box)
    assert _CALLS == [("build", False)]  # built to start from the MVS surface
    cfg.field.init = "sphere"
    assert not options.field_from_mvs(cfg) and options.grid_from_sphere(cfg)


def test_the_mlp_keeps_its_refusals():
    cfg = preset("paper")
    cfg.field.mlp_depth = 3
    with pytest.raises(InputError, match=r"field\.kind = mlp with field\.mlp_depth = 3: the "
                                         r"MLP's skip connection"):
        validate_config(cfg)
    # 4 hidden layers put the skip (layer 4) on the last layer, where IDR's geometric init gives
    # no sphere (|grad| ~ 9 at the start, issue 50); 5 are the fewest
    cfg.field.mlp_depth = 4
    with pytest.raises(InputError, match=r"field\.mlp_depth = 4: .* must be a hidden layer "
                                         r"for the sphere start: give field\.mlp_depth >= 5"):
        validate_config(cfg)
    cfg.field.mlp_depth = 5
    validate_config(cfg)
    from svolsdf.field.volsdf import SDFNetwork

    with pytest.raises(ValueError, match="a hidden layer"):
        SDFNetwork(n_layers=4, d_hidden=64, skip_in=(4,))
    cfg = preset("paper")
    cfg.field.init = "mvs"
    with pytest.raises(InputError, match=r"field\.kind = mlp with field\.init = mvs: only the "
                                         r"grid field starts from the MVS surface; the MLP "):
        validate_config(cfg)


def test_the_memory_check_asks_the_field_kind():
    """`memory_needs` reports what a kind declares (`FieldKind.memory`), not a built-in
    name's allocation."""
    from svolsdf.config.validate import memory_needs

    cfg = preset("fast")
    grid = [n for keys, _, _ in memory_needs(cfg) for n in keys]
    assert "field.grid_resolution" in grid
    cfg.field.kind, cfg.field.init = "test-huge", "sphere"
    assert memory_needs(cfg)[0] == (("field.mlp_width",), 2.0**60, "the toy's table")
    cfg.field.kind = "test-tiny-mlp"
    assert all("field." not in k for keys, _, _ in memory_needs(cfg) for k in keys)


register_field_kind("test-huge", memory=lambda f: [(("field.mlp_width",), 2.0**60,
                                                    "the toy's table")])(_toy_build)
