import os
import sys
from pathlib import Path

import pytest

# MuJoCo renders off-screen through EGL (Mesa on a CPU-only machine); osmesa fails there.
os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("HF_HUB_OFFLINE", "1")
sys.path.insert(0, str(Path(__file__).parent))

from tiny_dataset import write_tiny_dataset


@pytest.fixture(scope="session")
def tiny_dataset_root(tmp_path_factory) -> Path:
    """Two short episodes, one 48x64 camera, 14-d state and action."""
    root = tmp_path_factory.mktemp("data") / "tiny"
    write_tiny_dataset(root, repo_id="local/tiny")
    return root
