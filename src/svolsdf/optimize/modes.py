"""What the optimization's mode and ablation turn on: the rules the trainer reads, written once
(`svolsdf.pipeline.options` asks them for a whole run's config)."""

from __future__ import annotations

from svolsdf.config import TrainConfig, choices

__all__ = ["ABLATIONS", "supervised_by_mvs_depth", "uses_prior"]

ABLATIONS = (None, *choices("train.ablation"))
"""None (the method) and the paper's ablations (`TrainConfig.ablation`)."""


def uses_prior(t: TrainConfig) -> bool:
    """The field is fitted with the MVS prior's loss or an ablation's replacement of it
    (svolsdf mode)."""
    return t.mode == "svolsdf"


def supervised_by_mvs_depth(t: TrainConfig) -> bool:
    """An ablation ("mse", "no-prob-volume") replaces the probability volumes by the filtered
    stage-1 MVS depth: the field needs that depth, not the prior."""
    return t.ablation in ("mse", "no-prob-volume")
