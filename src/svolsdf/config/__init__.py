"""Dataclass configs for a reconstruction run, the named presets, validation and YAML round trips.

One `Config` describes a whole run. `svolsdf reconstruct` maps its options onto it (and
``--set section.option=value`` reaches every option) and writes it as OUT/config.yaml, which can
be passed back with ``--config`` to rerun. Presets (docs/architecture.md "Presets"): ``paper``
reproduces docs/method.md's constants; ``fast`` (the default) keeps the prior and the losses and
changes the field, the sampling and the schedule (docs/presets.md says why).
"""

from svolsdf.config.io import (
    apply_overrides,
    config_from_dict,
    config_yaml,
    load_config,
    option_docs,
    parse_set,
    save_config,
)
from svolsdf.config.presets import PRESETS, preset
from svolsdf.config.schema import (
    DTU_EXCLUDED_IDS,
    DTU_TRAIN_IDS,
    Config,
    FieldConfig,
    FusionConfig,
    GuideConfig,
    MeshConfig,
    MVSConfig,
    PoissonConfig,
    SceneConfig,
    TrainConfig,
    TSDFConfig,
    choices,
)
from svolsdf.config.validate import check_memory, validate_config

__all__ = [
    "Config",
    "SceneConfig",
    "MVSConfig",
    "FieldConfig",
    "TrainConfig",
    "GuideConfig",
    "FusionConfig",
    "MeshConfig",
    "PoissonConfig",
    "TSDFConfig",
    "DTU_TRAIN_IDS",
    "DTU_EXCLUDED_IDS",
    "preset",
    "PRESETS",
    "load_config",
    "save_config",
    "config_from_dict",
    "apply_overrides",
    "parse_set",
    "option_docs",
    "config_yaml",
    "check_memory",
    "validate_config",
    "choices",
]
