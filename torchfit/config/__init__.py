"""The tools' configuration: the schema (:mod:`torchfit.config.schema`), YAML loading with
``--set`` overrides (:mod:`torchfit.config.loader`) and the command-line plumbing
(:mod:`torchfit.config.cli`). Only the pipeline and the tools import this package."""

from torchfit.config.loader import (
    apply_overrides,
    config_from_dict,
    config_to_dict,
    config_to_yaml,
    load_config,
    parse_yaml,
    replace_keys,
    save_config,
)
from torchfit.config.schema import (
    Config,
    DataConfig,
    FitConfig,
    ModelConfig,
    OutputConfig,
    PartsConfig,
    RunConfig,
    SegmentationConfig,
    SilhouetteSource,
    SolverConfig,
    StageConfig,
)

__all__ = [
    "RunConfig",
    "DataConfig",
    "ModelConfig",
    "SegmentationConfig",
    "SilhouetteSource",
    "SolverConfig",
    "StageConfig",
    "FitConfig",
    "OutputConfig",
    "PartsConfig",
    "Config",
    "load_config",
    "config_from_dict",
    "config_to_dict",
    "config_to_yaml",
    "apply_overrides",
    "save_config",
    "parse_yaml",
    "replace_keys",
]
