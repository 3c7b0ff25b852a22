"""Shapes and the ACT-like inference behaviour of VIBPolicy."""

import json
from pathlib import Path

import pytest
import torch

from helpers import make_batch, make_config, with_rate_statistics
from lerobot_vib.modeling_vib import VIBPolicy
from lerobot_vib.pooled_network import PooledNetwork

LAYOUTS = {
    "one_camera": dict(cameras={"top": (3, 32, 32)}, state_dim=5),
    "two_cameras": dict(cameras={"top": (3, 32, 40), "wrist": (3, 32, 40)}, state_dim=5),
    "state_only": dict(cameras={}, state_dim=5),
    "env_state_only": dict(cameras={}, state_dim=None, env_state_dim=7),
    "camera_no_state": dict(cameras={"top": (3, 32, 32)}, state_dim=None),
}


@pytest.mark.parametrize("layout", LAYOUTS)
def test_output_shapes(layout):
    config = make_config(**LAYOUTS[layout], action_dim=3)
    policy = with_rate_statistics(VIBPolicy(config))
    batch = make_batch(config, batch_size=4)

    policy.train()
    loss, info = policy.forward(batch)
    assert loss.shape == () and torch.isfinite(loss)
    assert set(info) == {"l1_loss", "rate"}

    per_sample, _ = policy.forward(batch, reduction="none")
    assert per_sample.shape == (4,)

    obs = {k: v for k, v in batch.items() if k.startswith("observation")}
    chunk = policy.predict_action_chunk(obs)
    assert chunk.shape == (4, config.chunk_size, 3)
    assert policy.last_rate.shape == (4,)
    assert policy.select_action(obs).shape == (4, 3)


def test_rate_of_each_sample_depends_only_on_that_sample():
    config = make_config()
    policy = VIBPolicy(config).eval()
    obs = make_batch(config, batch_size=3, with_action=False)
    policy.predict_action_chunk(obs)
    rates = policy.last_rate.clone()
    for i in range(3):
        policy.predict_action_chunk({k: v[i : i + 1] for k, v in obs.items()})
        torch.testing.assert_close(policy.last_rate, rates[i : i + 1], rtol=1e-5, atol=1e-6)


def test_select_action_pops_a_queue_of_n_action_steps_then_replans():
    config = make_config(chunk_size=6, n_action_steps=4)
    policy = with_rate_statistics(VIBPolicy(config))
    obs = make_batch(config, batch_size=1, with_action=False)
    chunk = policy.predict_action_chunk(obs)
    decoder = policy.model.decoder
    calls = 0

    def counting(z):
        nonlocal calls
        calls += 1
        return type(decoder).forward(decoder, z)

    decoder.forward = counting
    actions = [policy.select_action(obs) for _ in range(5)]
    assert calls == 2  # one chunk for steps 0-3, a new one at step 4
    torch.testing.assert_close(torch.cat(actions[:4]), chunk[0, :4])
    policy.reset()
    assert not policy.runtime.queued


def test_inference_uses_the_posterior_mean_unless_told_to_sample():
    config = make_config()
    policy = VIBPolicy(config).eval()
    obs = make_batch(config, batch_size=2, with_action=False)
    torch.testing.assert_close(policy.predict_action_chunk(obs), policy.predict_action_chunk(obs))

    policy.config.sample_latent_at_inference = True
    a, b = policy.predict_action_chunk(obs), policy.predict_action_chunk(obs)
    assert not torch.allclose(a, b)


def test_padded_action_steps_do_not_count_in_the_loss():
    config = make_config()
    policy = VIBPolicy(config).eval()
    batch = make_batch(config)
    loss_full, _ = policy.forward(batch)
    batch["action_is_pad"][:, -2:] = True
    batch["action"][:, -2:] = 1e6  # padded targets: any value must leave the loss unchanged
    loss_a, _ = policy.forward(batch)
    batch["action"][:, -2:] = -1e6
    loss_b, _ = policy.forward(batch)
    assert loss_a == loss_b and loss_a != loss_full


def test_backbone_gets_its_own_learning_rate():
    config = make_config(optimizer_lr=1e-4, optimizer_lr_backbone=1e-6)
    policy = VIBPolicy(config)
    groups = policy.get_optim_params()
    n_backbone = sum(p.numel() for p in policy.model.encoder.backbone.parameters())
    assert groups[1]["lr"] == 1e-6 and sum(p.numel() for p in groups[1]["params"]) == n_backbone
    trainable = sum(p.numel() for p in policy.parameters() if p.requires_grad)
    assert sum(p.numel() for g in groups for p in g["params"]) == trainable


@pytest.mark.parametrize("pooling", ["spatial_softmax", "spatial_softmax_avg", "avg"])
@pytest.mark.parametrize("position_embedding", ["learned", "sinusoidal"])
def test_pooling_and_position_embedding_options(pooling, position_embedding):
    config = make_config(image_pooling=pooling, position_embedding=position_embedding)
    policy = VIBPolicy(config)
    loss, _ = policy.forward(make_batch(config))
    loss.backward()
    assert torch.isfinite(loss)


def test_a_pooled_checkpoint_keeps_every_tensor_name_and_shape_it_was_saved_with():
    """The pooled network lives in its own module now; `fixtures/pooled_state_dict.json` lists the policy's
    tensors as they were saved before the move, so an older checkpoint still loads strictly (and, with the
    same tensors and the same code, acts as it did)."""
    saved = json.loads((Path(__file__).parent / "fixtures" / "pooled_state_dict.json").read_text())
    torch.manual_seed(0)
    policy = VIBPolicy(make_config())
    assert isinstance(policy.network, PooledNetwork)
    assert {k: list(v.shape) for k, v in policy.state_dict().items()} == saved
