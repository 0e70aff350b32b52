"""The sampler registry (`svolsdf.render.sampler_registry`): the built-in samplers keep their
order and settings; a sampler registered here, in the test file alone, is accepted by the config
and built by the pipeline's builder; an unregistered name is refused naming the option."""

from __future__ import annotations

import pytest

from svolsdf.config import choices, preset, validate_config
from svolsdf.errors import InputError
from svolsdf.pipeline.builders import build_sampler
from svolsdf.render.guided import MVSGuidedSampler
from svolsdf.render.sampler_registry import (
    SamplerInputs,
    get_sampler,
    register_sampler,
    registered_samplers,
)
from svolsdf.render.samplers import ErrorBoundSampler, UniformRaySampler


@register_sampler("test-uniform")
def _uniform(s: SamplerInputs):
    """Uniform samples, as many as the config's stratified ones."""
    return UniformRaySampler(s.train.samples_uniform)


def test_builtin_samplers_are_registered_in_the_documented_order():
    assert registered_samplers()[:2] == ["mvs", "error_bounded"]
    assert choices("train.sampler") == tuple(registered_samplers())
    assert preset("fast").train.sampler == "mvs"
    assert preset("paper").train.sampler == "error_bounded"


def test_builtin_samplers_are_built_as_configured():
    cfg = preset("fast")
    cfg.train.samples_uniform, cfg.train.samples_fine = 20, 30
    prior = object()
    s = build_sampler(cfg, prior)
    assert isinstance(s, MVSGuidedSampler)
    c = s.config
    assert (c.samples_uniform, c.samples_fine, c.samples_coarse) == (20, 30, 64)
    r = build_sampler(cfg, prior, training=False)  # rendering: fewer probes, no prior
    c = r.config
    assert (c.samples_coarse, c.samples_uniform, c.samples_fine) == (64, 16, 32)
    assert isinstance(build_sampler(preset("paper")), ErrorBoundSampler)


def test_a_registered_sampler_is_a_valid_choice_and_is_built():
    cfg = preset("fast")
    cfg.train.sampler = "test-uniform"
    cfg.train.samples_uniform = 7
    validate_config(cfg)
    s = build_sampler(cfg)
    assert isinstance(s, UniformRaySampler) and s.n_samples == 7


def test_an_unregistered_sampler_is_refused_naming_the_option():
    cfg = preset("fast")
    cfg.train.sampler = "no-such-sampler"
    with pytest.raises(InputError, match=r"train\.sampler = 'no-such-sampler': expected one of "
                                         r"'mvs', 'error_bounded'"):
        validate_config(cfg)
    with pytest.raises(InputError, match="unknown sampler 'no-such-sampler'"):
        get_sampler("no-such-sampler")
