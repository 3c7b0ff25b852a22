"""benchmarks/latent_noise.py: whether a token network's decoded chunk depends on the camera at all."""

import importlib.util
import sys
from pathlib import Path

import pytest
import torch

from helpers import make_batch, make_config
from lerobot_vib.modeling_vib import VIBPolicy

BENCHMARKS = Path(__file__).parents[1] / "benchmarks"
sys.path.insert(0, str(BENCHMARKS))
_spec = importlib.util.spec_from_file_location("latent_noise", BENCHMARKS / "latent_noise.py")
latent_noise = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(latent_noise)


def frames(policy: VIBPolicy) -> dict:
    batch = make_batch(policy.config, batch_size=4, with_action=False, seed=7)
    batch["action"] = torch.randn(4, policy.config.action_feature.shape[0])  # one recorded action per frame
    return batch


@pytest.fixture
def policy() -> VIBPolicy:
    torch.manual_seed(0)
    config = make_config(cameras={"top": (3, 48, 64)}, state_dim=5, encoder="tokens", backbone_layer="layer2")
    return VIBPolicy(config).eval()


def test_a_network_that_reads_the_camera_changes_its_chunk_when_the_camera_is_swapped(policy):
    row = latent_noise.measure(policy, lambda b: b, frames(policy), draws=1)
    assert row["chunk change, camera swapped"] > 1e-3
    assert row["chunk change, state swapped"] > 1e-3


def test_image_tokens_that_carry_nothing_leave_the_chunk_unchanged_under_a_camera_swap(policy):
    head = policy.network.image_bottleneck.posterior_head
    with torch.no_grad():  # every cell's posterior mean the same, whatever the image
        head.weight[: policy.config.latent_dim].zero_()
        head.bias[: policy.config.latent_dim].zero_()
    row = latent_noise.measure(policy, lambda b: b, frames(policy), draws=1)
    assert row["chunk change, camera swapped"] == 0.0
    assert row["chunk change, state swapped"] > 1e-3
