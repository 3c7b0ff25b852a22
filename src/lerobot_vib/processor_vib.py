"""Pre/post-processing of VIBPolicy: LeRobot's default pipelines (rename, batch, device, normalize /
unnormalize, cpu), the same as ACT's, with the statistics floored (`normalization.py`)."""

from __future__ import annotations

from typing import Any

import torch
from lerobot.processor import PolicyAction, PolicyProcessorPipeline, make_default_pre_post_processors

from .configuration_vib import FLOORED_TYPES, VIBConfig
from .normalization import floor_stats, warn_near_constant


def vib_dataset_stats(config: VIBConfig, dataset_stats: dict | None, context: str | None = None) -> dict | None:
    """The statistics the policy normalizes with: the dataset's, floored per `config.normalization_floor`.
    With `context`, near-constant features are named in a warning."""
    if dataset_stats is None or config.normalization_floor is None:
        return dataset_stats
    features = {**(config.input_features or {}), **(config.output_features or {})}
    # ACT like VIB (baselines/) floors every feature, as the preset it copies
    floored_types = FLOORED_TYPES[getattr(config, "normalization_floor_features", "all")]
    features = {key: ft for key, ft in features.items() if ft.type in floored_types}
    stats, changed = floor_stats(dataset_stats, features, config.normalization_mapping, config.normalization_floor)
    if context:
        warn_near_constant(changed, context)
    return stats


def make_vib_pre_post_processors(
    config: VIBConfig,
    dataset_stats: dict[str, dict[str, torch.Tensor]] | None = None,
) -> tuple[
    PolicyProcessorPipeline[dict[str, Any], dict[str, Any]],
    PolicyProcessorPipeline[PolicyAction, PolicyAction],
]:
    """Normalizer (per `config.normalization_mapping`, floored scales) before the policy, unnormalizer after."""
    stats = vib_dataset_stats(config, dataset_stats, context="VIB normalization")
    return make_default_pre_post_processors(config, stats, normalizer_device=config.device)
