"""ACT like VIB (`--policy.type=act_like_vib`): LeRobot's ACT with VIB's trunk, weight average and normalization
floor, and nothing else changed."""

from __future__ import annotations

import pytest
import torch
from lerobot.configs.policies import PreTrainedConfig
from lerobot.configs.types import FeatureType, NormalizationMode, PolicyFeature
from lerobot.policies.act.configuration_act import ACTConfig
from lerobot.policies.act.modeling_act import ACTPolicy
from lerobot.policies.factory import get_policy_class, make_pre_post_processors
from torch import nn
from torchvision.ops.misc import FrozenBatchNorm2d

from helpers import make_batch, make_config
from lerobot_vib.baselines.configuration_act_like_vib import ACTLikeVIBConfig
from lerobot_vib.baselines.modeling_act_like_vib import ACTLikeVIBPolicy
from lerobot_vib.configuration_vib import VIBConfigError
from lerobot_vib.variants import act_with

FEATURES = dict(
    input_features={
        "observation.images.top": PolicyFeature(FeatureType.VISUAL, (3, 32, 32)),
        "observation.state": PolicyFeature(FeatureType.STATE, (5,)),
    },
    output_features={"action": PolicyFeature(FeatureType.ACTION, (3,))},
)
SMALL = dict(
    device="cpu", chunk_size=4, n_action_steps=4, dim_model=32, n_heads=4, dim_feedforward=64, n_vae_encoder_layers=1
)


def batch() -> dict:
    return make_batch(make_config(cameras={"top": (3, 32, 32)}, chunk_size=4, n_action_steps=4), batch_size=2)


def norm_types(module: nn.Module) -> set[type]:
    return {type(m) for m in module.modules() if isinstance(m, nn.BatchNorm2d | FrozenBatchNorm2d | nn.GroupNorm)}


def test_act_like_vib_has_vibs_trunk_and_acts_own_everything_else():
    act = ACTPolicy(ACTConfig(pretrained_backbone_weights=None, **FEATURES, **SMALL))
    like = ACTLikeVIBPolicy(ACTLikeVIBConfig(**FEATURES, **SMALL))
    assert norm_types(act.model.backbone) == {FrozenBatchNorm2d}
    assert norm_types(like.model.backbone) == {nn.GroupNorm}
    names = {n.split(".")[0] for n, _ in like.model.backbone.named_children()}
    assert "layer2" in names and "layer3" not in names and "layer4" not in names  # cut after layer2
    assert like.model.encoder_img_feat_input_proj.in_channels == 128
    # everything but the trunk and its projection has ACT's shapes
    own = {k: v.shape for k, v in act.model.state_dict().items() if not k.startswith(("backbone", "encoder_img"))}
    theirs = {k: v.shape for k, v in like.model.state_dict().items() if not k.startswith(("backbone", "encoder_img"))}
    assert own == theirs
    loss, _ = like.train().forward(batch())
    loss.backward()
    assert torch.isfinite(loss) and like.model.backbone.layer1[0].conv1.weight.grad is not None
    # the average is frozen: ACT's optimizer groups hold only the trained weights
    grouped = sum(p.numel() for g in like.get_optim_params() for p in g["params"])
    assert grouped == sum(p.numel() for p in like.model.parameters())


def test_act_like_vib_acts_with_the_average_of_its_weights():
    torch.manual_seed(0)
    policy = ACTLikeVIBPolicy(ACTLikeVIBConfig(**FEATURES, **SMALL, ema_decay=0.5))
    optimizer = torch.optim.AdamW(policy.model.parameters(), lr=1e-2)
    data = batch()
    for _ in range(5):
        policy.train()
        loss, _ = policy.forward(data)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        policy.update()
    obs = {k: v for k, v in data.items() if k.startswith("observation")}
    chunk = policy.predict_action_chunk(obs)
    with torch.no_grad():
        averaged = policy.ema.module({**obs, "observation.images": [obs["observation.images.top"]]})[0]
        last = policy.model({**obs, "observation.images": [obs["observation.images.top"]]})[0]
    assert torch.equal(chunk, averaged) and not torch.allclose(chunk, last)
    # ACT's queue and ensembling run on the average too, and keep the class through the benchmark's copy
    ensembling = act_with(policy, "act", 0.3)
    assert isinstance(ensembling, ACTLikeVIBPolicy) and torch.allclose(ensembling.select_action(obs), chunk[:, 0])


def test_lerobot_finds_act_like_vib_and_it_saves_and_loads(tmp_path):
    assert "act_like_vib" in PreTrainedConfig.get_known_choices()
    assert get_policy_class("act_like_vib") is ACTLikeVIBPolicy
    policy = ACTLikeVIBPolicy(ACTLikeVIBConfig(**FEATURES, **SMALL))
    policy.update()
    policy.save_pretrained(tmp_path)
    loaded = get_policy_class("act_like_vib").from_pretrained(tmp_path)
    obs = {k: v for k, v in batch().items() if k.startswith("observation")}
    assert torch.equal(loaded.predict_action_chunk(obs), policy.predict_action_chunk(obs))


def test_its_processors_floor_a_feature_the_demonstrations_never_move():
    config = ACTLikeVIBConfig(**FEATURES, **SMALL)
    config.normalization_mapping = {**config.normalization_mapping, "STATE": NormalizationMode.MEAN_STD}
    stats = {
        "observation.state": {
            "mean": torch.zeros(5), "std": torch.tensor([1.0, 1.0, 1.0, 1.0, 1e-4]),
            "min": -torch.ones(5), "max": torch.ones(5),
        },
        "action": {"mean": torch.zeros(3), "std": torch.ones(3), "min": -torch.ones(3), "max": torch.ones(3)},
    }  # fmt: skip
    pre, _ = make_pre_post_processors(config, dataset_stats=stats)
    out = pre({"observation.state": torch.tensor([[0.0, 0, 0, 0, 1e-3]]), "action": torch.zeros(1, 3)})
    assert out["observation.state"][0, 4].abs() < 1.0  # a z-score of 10 without the floor
    config.normalization_floor = None
    pre, _ = make_pre_post_processors(config, dataset_stats=stats)
    out = pre({"observation.state": torch.tensor([[0.0, 0, 0, 0, 1e-3]]), "action": torch.zeros(1, 3)})
    assert out["observation.state"][0, 4] == pytest.approx(10.0, rel=1e-3)


@pytest.mark.parametrize(
    "field, value, match",
    [
        ("backbone_norm", "layer_norm", "backbone_norm"),
        ("backbone_layer", "layer5", "backbone_layer"),
        ("ema_decay", 1.0, "ema_decay"),
        ("normalization_floor", 0.0, "normalization_floor"),
        ("pretrained_backbone_weights", "ResNet18_Weights.IMAGENET1K_V1", "group_norm"),
    ],
)
def test_act_like_vib_refuses_bad_fields_by_name(field, value, match):
    with pytest.raises(VIBConfigError, match=match):
        ACTLikeVIBConfig(**FEATURES, **SMALL, **{field: value})
