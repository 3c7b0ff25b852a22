"""A tiny LeRobotDataset written with LeRobot's own writer, for end-to-end tests."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from lerobot.datasets.lerobot_dataset import LeRobotDataset

ALOHA_JOINTS = [
    f"{side}_{j}"
    for side in ("left", "right")
    for j in ("waist", "shoulder", "elbow", "forearm_roll", "wrist_angle", "wrist_rotate", "gripper")
]


def write_tiny_dataset(
    root: Path,
    repo_id: str = "local/tiny",
    cameras: dict[str, tuple[int, int]] | None = None,
    state_dim: int | None = 14,
    action_dim: int = 14,
    n_episodes: int = 2,
    frames_per_episode: int = 20,
    fps: int = 50,
    seed: int = 0,
) -> LeRobotDataset:
    """Random-walk states and actions, and camera images of a moving bright square (so images vary)."""
    cameras = {"top": (48, 64)} if cameras is None else cameras
    features: dict = {
        "action": {"dtype": "float32", "shape": (action_dim,), "names": _names(action_dim)},
    }
    if state_dim:
        features["observation.state"] = {
            "dtype": "float32",
            "shape": (state_dim,),
            "names": _names(state_dim),
        }
    for cam, (h, w) in cameras.items():
        features[f"observation.images.{cam}"] = {
            "dtype": "image",
            "shape": (h, w, 3),
            "names": ["height", "width", "channels"],
        }
    ds = LeRobotDataset.create(repo_id=repo_id, fps=fps, features=features, root=root, use_videos=False)
    rng = np.random.default_rng(seed)
    for _ in range(n_episodes):
        state = rng.normal(size=state_dim or 1).astype(np.float32)
        for t in range(frames_per_episode):
            frame = {"task": "tiny task", "action": rng.normal(size=action_dim).astype(np.float32)}
            if state_dim:
                state = (state + 0.1 * rng.normal(size=state_dim)).astype(np.float32)
                frame["observation.state"] = state
            for cam, (h, w) in cameras.items():
                img = (rng.random((h, w, 3)) * 60).astype(np.uint8)
                y, x = (t * 3) % (h - 8), (t * 5) % (w - 8)
                img[y : y + 8, x : x + 8] = 255
                frame[f"observation.images.{cam}"] = img
            ds.add_frame(frame)
        ds.save_episode()
    ds.finalize()
    return ds


def _names(n: int) -> list[str]:
    return ALOHA_JOINTS if n == len(ALOHA_JOINTS) else [f"dim_{i}" for i in range(n)]
