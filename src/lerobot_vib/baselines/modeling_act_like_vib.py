"""ACTLikeVIBPolicy: LeRobot's ACTPolicy with VIB's trunk, weight average and normalization floor
(`configuration_act_like_vib.py` says why). Everything else is ACT's own code."""

from __future__ import annotations

import torch
from lerobot.policies.act.modeling_act import ACTPolicy
from lerobot.utils.constants import OBS_IMAGES
from torch import Tensor, nn

from ..backbone import build_resnet_trunk
from ..ema import make_ema
from .configuration_act_like_vib import ACTLikeVIBConfig


class ACTLikeVIBPolicy(ACTPolicy):
    config_class = ACTLikeVIBConfig
    name = "act_like_vib"

    def __init__(self, config: ACTLikeVIBConfig, **kwargs):
        super().__init__(config, **kwargs)
        if config.image_features:
            # ACT builds a frozen-batch-norm ResNet up to layer4; replace it, and the 1x1 projection that reads
            # its channels, by VIB's trunk. ACT's forward only calls `backbone(img)["feature_map"]`.
            trunk, channels = build_resnet_trunk(
                config.vision_backbone,
                config.pretrained_backbone_weights,
                config.backbone_norm,
                config.replace_final_stride_with_dilation,
                config.backbone_layer,
            )
            self.model.backbone = trunk
            self.model.encoder_img_feat_input_proj = nn.Conv2d(channels, config.dim_model, kernel_size=1)
        # Made after the swap so that the average holds the new trunk; frozen, so ACT's optimizer groups skip it.
        self.ema = make_ema(self.model, config.ema_decay) if config.ema_decay is not None else None

    def update(self) -> None:
        """After each optimizer step (LeRobot's training loop calls it): fold the new weights into the average."""
        if self.ema is not None:
            self.ema.update_parameters(self.model)

    @torch.no_grad()
    def predict_action_chunk(self, batch: dict[str, Tensor]) -> Tensor:
        """ACT's chunk, from the averaged weights when there are any (the queue and ACT's ensembling call this)."""
        if self.ema is None:
            return super().predict_action_chunk(batch)
        self.eval()
        if self.config.image_features:
            batch = dict(batch)
            batch[OBS_IMAGES] = [batch[key] for key in self.config.image_features]
        return self.ema.module(batch)[0]
