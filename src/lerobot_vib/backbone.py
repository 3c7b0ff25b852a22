"""The image trunk: a torchvision ResNet up to layer2, 3 or 4, its normalization layers and its initial weights.

A ResNet's normalization layers decide whether it can be trained from scratch (`backbone_norm`):

    frozen_bn   y = (x - mu) / sqrt(var + eps) * w + b, with mu, var, w, b fixed      (ACT's)
                Right for pretrained weights, whose statistics it keeps. From scratch mu = 0, var = 1,
                w = 1, b = 0 forever: the identity, so the trunk trains with no normalization at all.
    batch_norm  mu, var of the batch while training, their running averages in eval mode.
    group_norm  mu, var over groups of 16 channels of each sample, the same in training and eval
                (LeRobot's Diffusion Policy, `use_group_norm`, for trunks trained from scratch).

Initial weights (`pretrained_backbone_weights`): None (random), a torchvision weights name such as
"ResNet18_Weights.IMAGENET1K_V1" (downloaded into the torch hub cache), or a local file holding a torchvision
ResNet state dict (`.pth`/`.pt` from `torch.save(resnet.state_dict())`, or `.safetensors`), for machines
without a network connection.
"""

from __future__ import annotations

import contextlib
import contextvars
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import torch
import torchvision
from torch import nn
from torchvision.models._utils import IntermediateLayerGetter
from torchvision.ops.misc import FrozenBatchNorm2d

BACKBONE_NORMS = ("frozen_bn", "batch_norm", "group_norm")
BACKBONE_LAYERS = ("layer2", "layer3", "layer4")
GROUP_NORM_CHANNELS = 16  # channels per group, as Diffusion Policy's trunk
WEIGHT_FILE_SUFFIXES = (".pth", ".pt", ".bin", ".safetensors")


def norm_layer(norm: str) -> Callable[[int], nn.Module]:
    """The constructor torchvision's ResNet calls for each normalization layer, given its channel count."""
    if norm == "frozen_bn":
        return FrozenBatchNorm2d
    if norm == "batch_norm":
        return nn.BatchNorm2d
    if norm == "group_norm":
        return lambda channels: nn.GroupNorm(max(channels // GROUP_NORM_CHANNELS, 1), channels)
    raise ValueError(f"`backbone_norm` must be one of {BACKBONE_NORMS}, got {norm!r}.")


def is_weight_file(weights: str | None) -> bool:
    """Whether `pretrained_backbone_weights` names a local file rather than torchvision weights."""
    if weights is None:
        return False
    return Path(weights).suffix in WEIGHT_FILE_SUFFIXES or "/" in weights or Path(weights).exists()


def build_resnet_trunk(
    name: str, weights: str | None, norm: str, dilate_last_stage: bool = False, last_layer: str = "layer4"
) -> tuple[nn.Module, int]:
    """A torchvision ResNet up to `last_layer` (feature map under the key "feature_map").

    Returns (trunk, channels of the feature map). Stages after `last_layer` are dropped, weights included.
    """
    if last_layer not in BACKBONE_LAYERS:
        raise ValueError(f"The trunk's last layer must be one of {BACKBONE_LAYERS}, got {last_layer!r}.")
    if not hasattr(torchvision.models, name):
        raise ValueError(f"torchvision has no model {name!r}.")
    kwargs = dict(replace_stride_with_dilation=[False, False, dilate_last_stage], norm_layer=norm_layer(norm))
    if is_weight_file(weights):
        resnet = getattr(torchvision.models, name)(weights=None, **kwargs)
        load_weight_file(resnet, Path(weights), name)
    else:
        try:
            resnet = getattr(torchvision.models, name)(weights=weights, **kwargs)
        except OSError as e:  # URLError, connection errors: the weights are neither cached nor downloadable
            raise RuntimeError(
                f"Could not load the pretrained backbone weights {weights!r} for {name} ({type(e).__name__}: {e}). "
                "torchvision downloads them into the torch hub cache on first use. Offline, pass a local file "
                "(`--policy.pretrained_backbone_weights=/path/to/resnet18.pth`, a torchvision state dict) or "
                "train the trunk from scratch with `--policy.pretrained_backbone_weights=null`."
            ) from e
    trunk = IntermediateLayerGetter(resnet, return_layers={last_layer: "feature_map"})
    # Each stage doubles the channels of the one before; layer4's are the classifier's input.
    channels = resnet.fc.in_features // 2 ** (len(BACKBONE_LAYERS) - 1 - BACKBONE_LAYERS.index(last_layer))
    return trunk, channels


def load_weight_file(resnet: nn.Module, path: Path, name: str) -> None:
    """Load a torchvision ResNet state dict from `path` into `resnet`; the classifier (`fc.*`) may be absent."""
    if not path.is_file():
        raise FileNotFoundError(f"Backbone weights file {path} does not exist (`pretrained_backbone_weights`).")
    try:
        if path.suffix == ".safetensors":
            from safetensors.torch import load_file

            state = load_file(str(path))
        else:
            state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:
        raise ValueError(f"Could not read backbone weights from {path}: {type(e).__name__}: {e}") from e
    if isinstance(state, dict) and set(state) <= {"state_dict", "model"} and len(state) == 1:
        state = next(iter(state.values()))  # training checkpoints often wrap the state dict once
    if not isinstance(state, dict) or not all(isinstance(v, torch.Tensor) for v in state.values()):
        raise ValueError(f"{path} does not hold a state dict (a mapping of parameter names to tensors).")
    own = resnet.state_dict()
    missing = sorted(k for k in own if k not in state and not k.startswith("fc.") and "num_batches" not in k)
    unexpected = sorted(k for k in state if k not in own and "num_batches" not in k)
    wrong_shape = sorted(k for k in state if k in own and state[k].shape != own[k].shape)
    if missing or unexpected or wrong_shape:
        problems = [
            f"{label} {keys[:4]}{' ...' if len(keys) > 4 else ''} ({len(keys)})"
            for label, keys in (("missing", missing), ("unexpected", unexpected), ("of another shape", wrong_shape))
            if keys
        ]
        raise ValueError(
            f"{path} is not a torchvision {name} state dict: keys " + "; ".join(problems) + ". "
            f"Save one with `torch.save(torchvision.models.{name}(weights=...).state_dict(), path)`."
        )
    resnet.load_state_dict({k: v for k, v in state.items() if "num_batches" not in k}, strict=False)


def swap_norm_layers(module: nn.Module, norm: str) -> nn.Module:
    """Replace every batch-norm layer of `module` (frozen or not) by a fresh `norm` layer, in place.

    Gives a policy built elsewhere (LeRobot's ACT) the same trunk as VIB for like-for-like comparisons.
    """
    make = norm_layer(norm)
    for child_name, child in module.named_children():
        if isinstance(child, nn.BatchNorm2d | FrozenBatchNorm2d):
            channels = child.weight.shape[0]
            setattr(module, child_name, make(channels).to(child.weight.device))
        else:
            swap_norm_layers(child, norm)
    return module


# Set while `from_pretrained` builds the model: the checkpoint overwrites the backbone, so fetching
# ImageNet weights first would only fail offline for nothing.
_SKIP_PRETRAINED_BACKBONE: contextvars.ContextVar[bool] = contextvars.ContextVar(
    "vib_skip_pretrained_backbone", default=False
)


@contextlib.contextmanager
def skip_pretrained_backbone() -> Iterator[None]:
    token = _SKIP_PRETRAINED_BACKBONE.set(True)
    try:
        yield
    finally:
        _SKIP_PRETRAINED_BACKBONE.reset(token)


def build_encoder_trunk(config: Any) -> tuple[nn.Module, int]:
    """The trunk a VIB config asks for (its vision_backbone, weights, norm, dilation and layer). Returns
    (trunk, channels)."""
    weights = None if _SKIP_PRETRAINED_BACKBONE.get() else config.pretrained_backbone_weights
    return build_resnet_trunk(
        config.vision_backbone,
        weights,
        config.backbone_norm,
        config.replace_final_stride_with_dilation,
        config.backbone_layer,
    )
