"""Small builders shared by the tests."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import torch
from lerobot.configs.types import FeatureType, PolicyFeature

from lerobot_vib.configuration_vib import VIBConfig

BIN = Path(sys.executable).parent
# Small enough for a CPU: a handful of steps at batch 2.
TRAIN_ARGS = [
    "--policy.type=vib",
    "--policy.device=cpu",
    "--policy.push_to_hub=false",
    "--policy.pretrained_backbone_weights=null",
    "--policy.chunk_size=8",
    "--policy.n_action_steps=8",
    "--policy.dim_model=64",
    "--policy.dim_feedforward=128",
    "--policy.n_layers=2",
    "--policy.uncertainty_score=rate",  # as SMALL below: the mechanics on the score training normalizes
    "--wandb.enable=false",
    "--num_workers=0",
    "--batch_size=2",
    "--log_freq=1",
]


def run(cmd: list[str], timeout: int = 600, **kwargs) -> str:
    """Run a command line (a LeRobot or lerobot-vib console script), fail with its output's tail."""
    env = {**os.environ, "MUJOCO_GL": "egl", "HF_HUB_OFFLINE": "1"}
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=env, **kwargs)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, f"{cmd[0]} failed ({proc.returncode}):\n{out[-6000:]}"
    return out


SMALL = dict(
    chunk_size=6,
    n_action_steps=6,
    n_state_tokens=4,
    d_token=8,
    latent_dim=4,
    dim_model=32,
    n_heads=4,
    dim_feedforward=64,
    n_layers=2,
    mlp_hidden_dim=32,
    spatial_softmax_num_keypoints=8,
    # The stop's mechanics are tested on the rate, which training normalizes; the other scores need
    # `lerobot-vib-calibrate` first and have their own tests (test_scores.py).
    uncertainty_score="rate",
)


def make_config(
    cameras: dict[str, tuple[int, int, int]] | None = None,
    state_dim: int | None = 5,
    env_state_dim: int | None = None,
    action_dim: int = 3,
    **overrides,
) -> VIBConfig:
    """A small CPU VIBConfig; `cameras` maps a name to its (C, H, W) shape."""
    cameras = {"top": (3, 32, 32)} if cameras is None else cameras
    inputs = {f"observation.images.{k}": PolicyFeature(FeatureType.VISUAL, s) for k, s in cameras.items()}
    if state_dim:
        inputs["observation.state"] = PolicyFeature(FeatureType.STATE, (state_dim,))
    if env_state_dim:
        inputs["observation.environment_state"] = PolicyFeature(FeatureType.ENV, (env_state_dim,))
    kwargs = {**SMALL, "device": "cpu", "pretrained_backbone_weights": None, **overrides}
    return VIBConfig(
        input_features=inputs,
        output_features={"action": PolicyFeature(FeatureType.ACTION, (action_dim,))},
        **kwargs,
    )


def make_batch(config: VIBConfig, batch_size: int = 2, with_action: bool = True, seed: int = 0) -> dict:
    g = torch.Generator().manual_seed(seed)
    batch = {key: torch.rand(batch_size, *ft.shape, generator=g) for key, ft in config.input_features.items()}
    if with_action:
        a_dim = config.action_feature.shape[0]
        batch["action"] = torch.randn(batch_size, config.chunk_size, a_dim, generator=g)
        batch["action_is_pad"] = torch.zeros(batch_size, config.chunk_size, dtype=torch.bool)
    return batch


def with_rate_statistics(policy, batch: dict | None = None):
    """Give a fresh policy the running rate statistics training would leave, from one batch in eval mode."""
    import torch

    batch = make_batch(policy.config, batch_size=8, with_action=False, seed=123) if batch is None else batch
    with torch.no_grad():
        _, rate = policy.eval()._encode(batch)
    policy.rate_tracker.update(rate)
    return policy
