"""Pre/post-processing of ACTLikeVIBPolicy: ACT's pipelines, with the statistics floored as VIB's are."""

from __future__ import annotations

from typing import Any

import torch
from lerobot.policies.act.processor_act import make_act_pre_post_processors
from lerobot.processor import PolicyAction, PolicyProcessorPipeline

from ..processor_vib import vib_dataset_stats
from .configuration_act_like_vib import ACTLikeVIBConfig


def make_act_like_vib_pre_post_processors(
    config: ACTLikeVIBConfig,
    dataset_stats: dict[str, dict[str, torch.Tensor]] | None = None,
) -> tuple[
    PolicyProcessorPipeline[dict[str, Any], dict[str, Any]],
    PolicyProcessorPipeline[PolicyAction, PolicyAction],
]:
    stats = vib_dataset_stats(config, dataset_stats, context="ACT (like VIB) normalization")
    return make_act_pre_post_processors(config, stats)
