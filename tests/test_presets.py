"""The presets in configs/policy/ load with the command the README gives for them."""

import json
from pathlib import Path

from helpers import BIN, run

PRESETS = Path(__file__).parents[1] / "configs" / "policy"


def test_cpu_preset_trains_through_config_path(tiny_dataset_root, tmp_path):
    """`lerobot-train --config_path=configs/policy/vib_cpu.json` plus the dataset flags, nothing else."""
    out = tmp_path / "run"
    log = run(
        [
            str(BIN / "lerobot-train"),
            f"--config_path={PRESETS / 'vib_cpu.json'}",
            "--dataset.repo_id=local/tiny",
            f"--dataset.root={tiny_dataset_root}",
            "--steps=1",
            "--num_workers=0",
            "--log_freq=1",  # the preset logs every 50 steps; one step must still show its loss
            f"--output_dir={out}",
        ]
    )
    assert "step:1" in log
    preset = json.loads((PRESETS / "vib_cpu.json").read_text())["policy"]
    saved = json.loads((out / "checkpoints/last/pretrained_model/config.json").read_text())
    for key in ("backbone_norm", "pretrained_backbone_weights", "chunk_size", "dim_model", "n_layers", "optimizer_lr"):
        assert saved[key] == preset[key], key
