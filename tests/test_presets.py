"""Every preset in configs/policy/ trains with the command the README gives for it."""

import json
from pathlib import Path

import pytest

from helpers import BIN, run
from lerobot_vib.configuration_vib import DEFAULT_SCORE, SCRATCH_BACKBONE_NORM
from tiny_dataset import write_tiny_dataset

PRESETS = Path(__file__).parents[1] / "configs" / "policy"


# What a user of each preset must add on this machine: the GPU presets' device and ImageNet weights.
GPU_ON_CPU = ["--policy.device=cpu", "--policy.pretrained_backbone_weights=null"]
OFFLINE_CPU = {
    "vib.json": GPU_ON_CPU,
    "vib_cpu.json": [],
    "vib_aloha_transfer_cube.json": GPU_ON_CPU,
    "vib_aloha_insertion.json": GPU_ON_CPU,
    "vib_arm_sim.json": [],
    "vib_arm_tokens.json": [],
    "vib_real_arm.json": GPU_ON_CPU,
}
# The presets whose env is the simulated arm act with 7 values; lerobot-train refuses them on 14-D data.
ARM_PRESETS = {"vib_arm_sim.json", "vib_arm_tokens.json"}


@pytest.fixture(scope="module")
def tiny_arm_dataset_root(tmp_path_factory) -> Path:
    """The tiny dataset with the simulated arm's 7-D state and action."""
    root = tmp_path_factory.mktemp("arm_data") / "tiny_arm"
    write_tiny_dataset(root, repo_id="local/tiny", state_dim=7, action_dim=7)
    return root


def test_every_preset_is_tested():
    assert sorted(p.name for p in PRESETS.glob("*.json")) == sorted(OFFLINE_CPU)


@pytest.mark.parametrize("name", sorted(OFFLINE_CPU))
def test_preset_trains_through_config_path(name, tiny_dataset_root, tiny_arm_dataset_root, tmp_path):
    """`lerobot-train --config_path=configs/policy/<preset>` plus the dataset flags (and for the GPU preset,
    the CPU and no ImageNet weights), on data shaped as the preset's env acts."""
    out = tmp_path / "run"
    root = tiny_arm_dataset_root if name in ARM_PRESETS else tiny_dataset_root
    log = run(
        [
            str(BIN / "lerobot-train"),
            f"--config_path={PRESETS / name}",
            "--dataset.repo_id=local/tiny",
            f"--dataset.root={root}",
            *OFFLINE_CPU[name],
            "--steps=1",
            "--num_workers=0",
            "--log_freq=1",  # the presets log every 50 or 200 steps; one step must still show its loss
            f"--output_dir={out}",
        ]
    )
    assert "step:1" in log
    preset = json.loads((PRESETS / name).read_text())["policy"]
    saved = json.loads((out / "checkpoints/last/pretrained_model/config.json").read_text())
    overridden = {"type", "device", "pretrained_backbone_weights", "backbone_norm", "input_features", "output_features"}
    overridden |= {"uncertainty_score"}  # None resolves when the policy is built
    for key in preset.keys() - overridden:
        assert saved[key] == preset[key], key
    # vib.json leaves the norm to follow the weights: without ImageNet weights the trunk trains from scratch.
    assert saved["backbone_norm"] == (preset["backbone_norm"] or SCRATCH_BACKBONE_NORM)
    assert saved["pretrained_backbone_weights"] is None
    # null: the best measured score for a policy with a camera (the tiny dataset has one)
    assert saved["uncertainty_score"] == (preset.get("uncertainty_score") or DEFAULT_SCORE)
