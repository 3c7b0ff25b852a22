"""`--policy.type=act_like_vib`: LeRobot's ACT trained the way VIB is, so that a comparison isolates the bottleneck.

VIB trains its trunk from scratch with group norm, cuts it after layer2, acts with an exponential moving average
of its weights and floors the normalization scales; LeRobot's ACT has frozen batch norm (from scratch: no
normalization at all), a full ResNet up to layer4, its last weights and the raw dataset statistics. This config
is ACT's, with those four choices added as fields, so that only the architecture (ACT's CVAE and
encoder-decoder transformer over the feature map's cells against VIB's state tokens and bottleneck) differs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from lerobot.configs import PreTrainedConfig
from lerobot.policies.act.configuration_act import ACTConfig

from ..backbone import BACKBONE_LAYERS, BACKBONE_NORMS
from ..configuration_vib import VIBConfigError


@PreTrainedConfig.register_subclass("act_like_vib")
@dataclass
class ACTLikeVIBConfig(ACTConfig):
    """ACT's fields (LeRobot's `ACTConfig`), and:

    Args:
        backbone_norm: The trunk's normalization layers (`backbone.py`): "group_norm" (VIB's from scratch),
            "batch_norm" or "frozen_bn" (ACT's own).
        backbone_layer: The ResNet stage whose feature map becomes ACT's image tokens: "layer2" (VIB's arm
            preset; 8x downsampling, so 16 times as many tokens as layer4), "layer3" or "layer4" (ACT's).
        ema_decay: Act with an exponential moving average of the weights (`ema.py`, as VIB's `ema_decay`);
            None acts with the last weights, as ACT does.
        normalization_floor: The floor under every MEAN_STD scale, relative to the feature's range
            (`normalization.py`, as VIB's); None normalizes with the dataset's statistics as they are.
    """

    backbone_norm: str = "group_norm"
    backbone_layer: str = "layer2"
    ema_decay: float | None = 0.999
    normalization_floor: float | None = 0.1
    pretrained_backbone_weights: str | None = None

    def __post_init__(self):
        super().__post_init__()
        if self.backbone_norm not in BACKBONE_NORMS:
            raise VIBConfigError(f"`backbone_norm` must be one of {BACKBONE_NORMS}, got {self.backbone_norm!r}.")
        if self.backbone_layer not in BACKBONE_LAYERS:
            raise VIBConfigError(f"`backbone_layer` must be one of {BACKBONE_LAYERS}, got {self.backbone_layer!r}.")
        if self.backbone_norm == "group_norm" and self.pretrained_backbone_weights:
            raise VIBConfigError(
                "`backbone_norm=group_norm` cannot use `pretrained_backbone_weights`: they were trained with batch "
                "norm. Use `--policy.pretrained_backbone_weights=null` or another `backbone_norm`."
            )
        if self.replace_final_stride_with_dilation and self.backbone_layer != "layer4":
            raise VIBConfigError("`replace_final_stride_with_dilation=true` dilates layer4, the trunk drops.")
        if self.ema_decay is not None and not 0.0 < self.ema_decay < 1.0:
            raise VIBConfigError(f"`ema_decay` must be in (0, 1) or null, got {self.ema_decay}.")
        if self.normalization_floor is not None and not (
            math.isfinite(self.normalization_floor) and 0 < self.normalization_floor <= 1
        ):
            raise VIBConfigError(f"`normalization_floor` must be in (0, 1] or null, got {self.normalization_floor}.")
