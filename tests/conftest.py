import os
import sys
from pathlib import Path

import pytest

# MuJoCo renders off-screen through EGL (Mesa on a CPU-only machine); osmesa fails there.
os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("HF_HUB_OFFLINE", "1")
sys.path.insert(0, str(Path(__file__).parent))

from helpers import BIN, TRAIN_ARGS, run
from tiny_dataset import write_tiny_dataset


@pytest.fixture(scope="session")
def tiny_dataset_root(tmp_path_factory) -> Path:
    """Two short episodes, one 48x64 camera, 14-d state and action."""
    root = tmp_path_factory.mktemp("data") / "tiny"
    write_tiny_dataset(root, repo_id="local/tiny")
    return root


@pytest.fixture(scope="session")
def tiny_checkpoint(tiny_dataset_root, tmp_path_factory) -> Path:
    """A VIB checkpoint from a 2-step lerobot-train run on the tiny dataset."""
    out = tmp_path_factory.mktemp("tiny_train") / "run"
    run(
        [
            str(BIN / "lerobot-train"),
            *TRAIN_ARGS,
            "--dataset.repo_id=local/tiny",
            f"--dataset.root={tiny_dataset_root}",
            "--steps=2",
            "--save_freq=2",
            f"--output_dir={out}",
        ]
    )
    return out / "checkpoints" / "last" / "pretrained_model"
