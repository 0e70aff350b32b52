"""The ray samplers, by name: what `TrainConfig.sampler` may say and what each name builds.

A sampler kind is a function of one `SamplerInputs` returning a sampler, a callable
``sampler(model, rays, training=None) -> SamplerOutput`` (`svolsdf.render.samplers`), registered
with ``@register_sampler("name")``. Adding one is one module of `svolsdf.render` with one
decorator: `train.sampler` accepts the name and `svolsdf.pipeline.builders.build_sampler` builds
it for training, the finer stage and rendering.

Built in (in this order): "mvs" (`svolsdf.render.guided.MVSGuidedSampler`, the fast preset's)
and "error_bounded" (VolSDF's, `svolsdf.render.samplers.ErrorBoundSampler`, docs/method.md 5.4).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from svolsdf.registry import DeclaresOptions, Registry

__all__ = ["SAMPLERS", "SamplerInputs", "SamplerKind", "get_sampler", "register_sampler",
           "registered_samplers"]


@dataclass
class SamplerInputs:
    """What a sampler kind may read.

    Attributes:
        train: the run's `TrainConfig` (the sampler's options are read from it).
        prior: the `svolsdf.prior.consistency.MVSPrior` of the input views, or None (no MVS:
            rendering, the volsdf mode).
        training: the sampler serves the optimization (False: rendering a converged field).
    """

    train: Any
    prior: Any = None
    training: bool = True


SamplerFactory = Callable[[SamplerInputs], Any]


@dataclass(frozen=True)
class SamplerKind(DeclaresOptions):
    """A registered sampler kind: called with a `SamplerInputs`, it builds the sampler.

    Attributes:
        name: the name `TrainConfig.sampler` accepts.
        build: `SamplerInputs` -> the sampler.
        options: the dotted config keys of the options it reads in training (or a function
            of the config returning them); ``reads(cfg)``: {key: value} of them.
    """

    name: str
    build: SamplerFactory
    options: tuple[str, ...] | Callable[[Any], tuple[str, ...]] = ()

    def __call__(self, inputs: SamplerInputs) -> Any:
        return self.build(inputs)

#: name -> sampler kind; the modules of `svolsdf.render` that use ``@register_sampler(...)`` are
#: imported the first time a name is asked for (`svolsdf.registry.Registry`)
SAMPLERS: Registry[SamplerKind] = Registry("sampler", "svolsdf.render", "register_sampler",
                                           entry=SamplerKind)

#: ``@register_sampler(name, options=...)``: a function decorator adding a sampler kind, whose
#: ``fn(SamplerInputs)`` returns the sampler (`SamplerKind`)
register_sampler = SAMPLERS.register
#: the names `TrainConfig.sampler` accepts, in registration order (the built-in ones first)
registered_samplers = SAMPLERS.names
#: the sampler kind registered as a name (InputError when none is)
get_sampler = SAMPLERS.get


# --------------------------------------------------------------------------- built in
@register_sampler("mvs", options=("train.samples_uniform", "train.samples_fine"))
def _mvs(s: SamplerInputs):
    """Samples near P' and the current surface (`MVSGuidedSampler`; with the prior in
    training, a lighter one without it for rendering)."""
    from svolsdf.render.guided import GuidedSamplerConfig, MVSGuidedSampler

    if s.training:
        gc = GuidedSamplerConfig.from_config(s.train)
    else:
        # rendering: a converged field needs fewer probes
        # (benchmarks/results/history/render_speed.md)
        gc = GuidedSamplerConfig(samples_coarse=64, samples_uniform=16, samples_fine=32)
    return MVSGuidedSampler(s.prior if s.training else None, gc)


@register_sampler("error_bounded")
def _error_bounded(s: SamplerInputs):
    """VolSDF's error-bounded sampler (docs/method.md 5.4)."""
    from svolsdf.render.samplers import ErrorBoundSampler

    return ErrorBoundSampler()
