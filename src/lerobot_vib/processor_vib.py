"""Pre/post-processing of VIBPolicy: LeRobot's default pipelines (rename, batch, device, normalize /
unnormalize, cpu), the same as ACT's."""

from __future__ import annotations

from typing import Any

import torch
from lerobot.processor import PolicyAction, PolicyProcessorPipeline, make_default_pre_post_processors

from .configuration_vib import VIBConfig


def make_vib_pre_post_processors(
    config: VIBConfig,
    dataset_stats: dict[str, dict[str, torch.Tensor]] | None = None,
) -> tuple[
    PolicyProcessorPipeline[dict[str, Any], dict[str, Any]],
    PolicyProcessorPipeline[PolicyAction, PolicyAction],
]:
    """Normalizer (mean/std per `config.normalization_mapping`) before the policy, unnormalizer after."""
    return make_default_pre_post_processors(config, dataset_stats, normalizer_device=config.device)
