"""The image trunk: normalization layers that can train from scratch, local weight files, checkpoints."""

import json

import pytest
import torch
import torchvision
from safetensors.torch import save_file
from torch import nn
from torchvision.ops.misc import FrozenBatchNorm2d

from helpers import make_batch, make_config
from lerobot_vib.backbone import build_resnet_trunk, swap_norm_layers
from lerobot_vib.configuration_vib import SCRATCH_BACKBONE_NORM, VIBConfigError
from lerobot_vib.modeling_vib import VIBPolicy

NORM_TYPES = {"frozen_bn": FrozenBatchNorm2d, "batch_norm": nn.BatchNorm2d, "group_norm": nn.GroupNorm}


def norm_types(module: nn.Module) -> set[type]:
    return {type(m) for m in module.modules() if isinstance(m, nn.BatchNorm2d | FrozenBatchNorm2d | nn.GroupNorm)}


def test_frozen_batch_norm_from_scratch_is_the_identity():
    """Why `frozen_bn` cannot be the default without pretrained weights: it normalizes nothing."""
    trunk, _ = build_resnet_trunk("resnet18", None, "frozen_bn")
    x = torch.randn(3, 64, 8, 8) * 5 + 2
    torch.testing.assert_close(trunk.bn1(x), x, atol=1e-4, rtol=1e-4)


def test_group_norm_normalizes_each_sample_alike_in_training_and_eval():
    trunk, _ = build_resnet_trunk("resnet18", None, "group_norm")
    x = torch.randn(3, 64, 8, 8) * 5 + 2
    y_train = trunk.bn1.train()(x)
    torch.testing.assert_close(trunk.bn1.eval()(x), y_train)
    assert y_train.mean().abs() < 1e-3 and (y_train.std() - 1).abs() < 1e-2


def test_default_norm_follows_the_weights():
    assert make_config(pretrained_backbone_weights=None).backbone_norm == SCRATCH_BACKBONE_NORM
    assert make_config(pretrained_backbone_weights="ResNet18_Weights.IMAGENET1K_V1").backbone_norm == "frozen_bn"


def test_group_norm_refuses_batch_norm_weights():
    with pytest.raises(VIBConfigError, match=r"group_norm.*pretrained_backbone_weights"):
        make_config(backbone_norm="group_norm", pretrained_backbone_weights="ResNet18_Weights.IMAGENET1K_V1")


def test_dilation_is_refused_for_basic_block_resnets():
    with pytest.raises(VIBConfigError, match=r"replace_final_stride_with_dilation.*resnet18"):
        make_config(replace_final_stride_with_dilation=True)
    trunk, _ = build_resnet_trunk("resnet50", None, "group_norm", dilate_last_stage=True)
    assert trunk(torch.rand(1, 3, 64, 64))["feature_map"].shape[-2:] == (4, 4)  # stride 16, not 32


@pytest.mark.parametrize(("name", "channels"), [("resnet18", 256), ("resnet50", 1024)])
def test_a_layer3_trunk_keeps_a_grid_twice_as_fine_and_drops_layer4(name, channels):
    trunk, reported = build_resnet_trunk(name, None, "group_norm", last_layer="layer3")
    feature_map = trunk(torch.rand(1, 3, 96, 128))["feature_map"]
    assert feature_map.shape[1:] == (channels, 6, 8) and reported == channels  # stride 16: 6x8 at 96x128
    assert not any(key.startswith("layer4") for key in trunk.state_dict())


@pytest.mark.parametrize(("name", "channels"), [("resnet18", 128), ("resnet50", 512)])
def test_a_layer2_trunk_keeps_a_grid_four_times_as_fine_and_drops_layer3(name, channels):
    trunk, reported = build_resnet_trunk(name, None, "group_norm", last_layer="layer2")
    feature_map = trunk(torch.rand(1, 3, 96, 128))["feature_map"]
    assert feature_map.shape[1:] == (channels, 12, 16) and reported == channels  # stride 8
    assert not any(key.startswith(("layer3", "layer4")) for key in trunk.state_dict())


def test_a_layer3_policy_saves_and_loads_its_trunk(tmp_path):
    policy = VIBPolicy(make_config(cameras={"top": (3, 96, 128)}, backbone_layer="layer3"))
    assert (policy.model.encoder.pool._in_h, policy.model.encoder.pool._in_w) == (6, 8)
    policy.eval().save_pretrained(tmp_path)
    loaded = VIBPolicy.from_pretrained(tmp_path)
    assert loaded.config.backbone_layer == "layer3"
    obs = make_batch(policy.config, with_action=False, seed=9)
    torch.testing.assert_close(loaded.predict_action_chunk(obs), policy.predict_action_chunk(obs))


def test_unknown_or_contradicting_trunk_layers_are_refused():
    with pytest.raises(VIBConfigError, match="backbone_layer"):
        make_config(backbone_layer="layer5")
    with pytest.raises(VIBConfigError, match=r"dilates layer4.*backbone_layer=layer3"):
        make_config(vision_backbone="resnet50", replace_final_stride_with_dilation=True, backbone_layer="layer3")
    with pytest.raises(ValueError, match="last layer"):
        build_resnet_trunk("resnet18", None, "group_norm", last_layer="layer1")


def test_unknown_norm():
    with pytest.raises(VIBConfigError, match="backbone_norm"):
        make_config(backbone_norm="layer_norm")


@pytest.mark.parametrize("norm", ["frozen_bn", "batch_norm", "group_norm"])
def test_checkpoint_round_trip_restores_the_same_layers(norm, tmp_path):
    policy = VIBPolicy(make_config(backbone_norm=norm))
    assert norm_types(policy.model.encoder.backbone) == {NORM_TYPES[norm]}
    # A few training steps move batch-norm statistics; the checkpoint must carry them.
    optimizer = torch.optim.AdamW(policy.parameters(), lr=1e-3)
    for step in range(3):
        loss, _ = policy.train().forward(make_batch(policy.config, batch_size=4, seed=step))
        loss.backward()
        optimizer.step()
        optimizer.zero_grad()
    policy.eval().save_pretrained(tmp_path)
    assert json.loads((tmp_path / "config.json").read_text())["backbone_norm"] == norm

    loaded = VIBPolicy.from_pretrained(tmp_path)
    assert norm_types(loaded.model.encoder.backbone) == {NORM_TYPES[norm]}
    obs = make_batch(policy.config, with_action=False, seed=9)
    torch.testing.assert_close(loaded.predict_action_chunk(obs), policy.predict_action_chunk(obs))
    if norm == "batch_norm":
        assert not torch.equal(loaded.model.encoder.backbone.bn1.running_mean, torch.zeros(64))


@pytest.mark.parametrize("suffix", [".pth", ".safetensors"])
@pytest.mark.parametrize("norm", ["frozen_bn", "batch_norm"])
def test_local_weight_file_initializes_the_trunk(tmp_path, suffix, norm):
    torch.manual_seed(0)
    reference = torchvision.models.resnet18(weights=None)
    with torch.no_grad():  # statistics that differ from the identity, so that loading them is visible
        reference.bn1.running_mean.uniform_(-1, 1)
        reference.bn1.running_var.uniform_(0.5, 2)
    path = tmp_path / f"resnet18{suffix}"
    state = reference.state_dict()
    if suffix == ".safetensors":
        save_file({k: v.contiguous() for k, v in state.items()}, str(path))
    else:
        torch.save({"state_dict": state}, path)  # wrapped once, as training checkpoints often are

    policy = VIBPolicy(make_config(pretrained_backbone_weights=str(path), backbone_norm=norm))
    trunk = policy.model.encoder.backbone
    torch.testing.assert_close(trunk.conv1.weight, reference.conv1.weight)
    torch.testing.assert_close(trunk.layer4[1].conv2.weight, reference.layer4[1].conv2.weight)
    torch.testing.assert_close(trunk.bn1.running_mean, reference.bn1.running_mean)


def test_missing_weight_file_is_refused(tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        VIBPolicy(make_config(pretrained_backbone_weights=str(tmp_path / "resnet18.pth"), backbone_norm="frozen_bn"))


def test_weights_of_another_resnet_are_refused(tmp_path):
    path = tmp_path / "resnet34.pth"
    torch.save(torchvision.models.resnet34(weights=None).state_dict(), path)
    with pytest.raises(ValueError, match=r"not a torchvision resnet18 state dict.*unexpected"):
        VIBPolicy(make_config(pretrained_backbone_weights=str(path), backbone_norm="frozen_bn"))


def test_a_file_that_is_no_state_dict_is_refused(tmp_path):
    path = tmp_path / "weights.pt"
    path.write_text("not a tensor file")
    with pytest.raises(ValueError, match="Could not read backbone weights"):
        VIBPolicy(make_config(pretrained_backbone_weights=str(path), backbone_norm="frozen_bn"))
    torch.save([1, 2, 3], path)
    with pytest.raises(ValueError, match="does not hold a state dict"):
        VIBPolicy(make_config(pretrained_backbone_weights=str(path), backbone_norm="frozen_bn"))


def test_loading_a_checkpoint_does_not_need_the_weight_file(tmp_path):
    path = tmp_path / "resnet18.pth"
    torch.save(torchvision.models.resnet18(weights=None).state_dict(), path)
    policy = VIBPolicy(make_config(pretrained_backbone_weights=str(path), backbone_norm="frozen_bn"))
    policy.save_pretrained(tmp_path / "ckpt")
    path.unlink()
    VIBPolicy.from_pretrained(tmp_path / "ckpt")


def test_swap_norm_layers_gives_act_the_same_trunk():
    from lerobot.configs.types import FeatureType, PolicyFeature
    from lerobot.policies.act.configuration_act import ACTConfig
    from lerobot.policies.act.modeling_act import ACTPolicy

    config = ACTConfig(
        device="cpu",
        pretrained_backbone_weights=None,
        input_features={
            "observation.images.top": PolicyFeature(FeatureType.VISUAL, (3, 32, 32)),
            "observation.state": PolicyFeature(FeatureType.STATE, (5,)),
        },
        output_features={"action": PolicyFeature(FeatureType.ACTION, (3,))},
        chunk_size=4,
        n_action_steps=4,
        dim_model=32,
        n_heads=4,
        dim_feedforward=64,
        use_vae=False,
    )
    act = ACTPolicy(config)
    assert norm_types(act.model.backbone) == {FrozenBatchNorm2d}
    swap_norm_layers(act.model.backbone, "group_norm")
    assert norm_types(act.model.backbone) == {nn.GroupNorm}
    batch = make_batch(make_config(cameras={"top": (3, 32, 32)}, chunk_size=4, n_action_steps=4), batch_size=2)
    loss, _ = act.forward(batch)
    assert torch.isfinite(loss)
