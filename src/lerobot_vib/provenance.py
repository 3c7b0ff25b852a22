"""Where a policy's numbers come from: the data it was trained on, and the env an evaluation ran in.

A stop threshold set on rollouts is only a threshold for the policy, env and scene those rollouts ran in. So
`lerobot-vib-eval` records its env in `uncertainty_info.json` (`env_record`), and every consumer compares
that record with the checkpoint before trusting it, in this order:

1. the env ran unperturbed (`active_perturbations` is empty): a threshold is set on clean rollouts only;
2. its cameras and image size are the policy's inputs (`input_mismatches`);
3. where the checkpoint names a recording of this project (its `train_config.json`'s dataset root holds the
   recorder's sidecar), the env is that recording's: the same task and, on the arm, the same workspace
   (`recording_mismatches`).

Each check returns what differs, in words, so that a refusal names it.
"""

from __future__ import annotations

import json
from dataclasses import asdict, fields, is_dataclass
from pathlib import Path
from typing import Any

from lerobot.configs.policies import PreTrainedConfig

from .sim.arm_env import LEGACY_WORKSPACE
from .sim.env_config import ARM_TASK, GYM_TASKS, SIDECAR
from .sim.perturbations import PerturbationConfig

# The env type (and gym task) each recorded task is evaluated in.
RECORDED_TASK_ENVS = {
    ARM_TASK: ("vib_arm", None),
    **{task: ("aloha_fast", gym_task) for gym_task, task in GYM_TASKS.items()},
}
# Env types that run the same simulation as the one a recording names (LeRobot's own ALOHA env renders
# all its cameras but simulates the same tasks).
SAME_SIMULATION = {"aloha_fast": ("aloha_fast", "aloha")}


def env_record(env_cfg: Any) -> dict:
    """What an evaluation ran in, as plain JSON: the env type and the fields that change what a policy sees."""
    record: dict[str, Any] = {"type": env_cfg.type}
    for name in ("task", "workspace", "episode_length", "observation_height", "observation_width", "cameras",
                 "shadows", "dataset_root"):  # fmt: skip
        if hasattr(env_cfg, name):
            value = getattr(env_cfg, name)
            record[name] = list(value) if isinstance(value, (list, tuple)) else value
    perturbation = getattr(env_cfg, "perturbation", None)
    record["perturbation"] = asdict(perturbation) if is_dataclass(perturbation) else None
    return record


def active_perturbations(perturbation: dict | None) -> list[str]:
    """The perturbations a recorded `perturbation` turns on, as `name=value` (empty: a clean env)."""
    if not perturbation:
        return []
    known = {f.name for f in fields(PerturbationConfig)}
    p = PerturbationConfig(**{k: v for k, v in perturbation.items() if k in known})
    on = [
        (f"noise_std={p.noise_std}", any(s > 0 for s in p.noise_std)),
        (f"color_jitter={p.color_jitter}", p.color_jitter > 0 and p.color_jitter_p > 0),
        ("black_images=true", p.black_images),
        (f"dim={p.dim}", p.dim < 1),
        (f"frozen_from={p.frozen_from}", p.frozen_from is not None),
        (f"camera_shake={p.camera_shake}", p.camera_shake > 0),
        ("unseen_block=true", p.unseen_block),
        ("occlusion=true", p.occlusion),
    ]
    return [name for name, active in on if active]


def input_mismatches(record: dict, policy: PreTrainedConfig) -> list[str]:
    """Where the env's cameras or image size differ from the policy's image inputs."""
    cameras = record.get("cameras")
    height, width = record.get("observation_height"), record.get("observation_width")
    wanted = {key.removeprefix("observation.images."): tuple(ft.shape) for key, ft in policy.image_features.items()}
    problems = []
    if cameras is not None and sorted(cameras) != sorted(wanted):
        problems.append(f"cameras {sorted(cameras)} (the policy reads {sorted(wanted)})")
    shapes = {shape[1:] for shape in wanted.values()}
    if height is not None and width is not None and shapes and (height, width) not in shapes:
        policy_size = " or ".join(f"{h}x{w}" for h, w in sorted(shapes))
        problems.append(f"images of {height}x{width} (the policy was trained on {policy_size})")
    return problems


def dataset_mismatches(policy: PreTrainedConfig, features: dict) -> list[str]:
    """Where a LeRobot dataset's features (meta/info.json's `features`) differ from the inputs the policy reads:
    a missing camera or state, or another image or vector size."""
    problems = []
    for key, ft in policy.input_features.items():
        if key not in features:
            problems.append(f"no `{key}` (it has {sorted(k for k in features if k.startswith('observation'))})")
            continue
        shape = tuple(features[key]["shape"])
        if key in policy.image_features:
            names = features[key].get("names") or []
            # LeRobot records images as (H, W, C) and hands them to the policy as (C, H, W)
            chw = (shape[2], shape[0], shape[1]) if len(shape) == 3 and names[:1] != ["channels"] else shape
            if chw != tuple(ft.shape):
                problems.append(f"`{key}` of {chw[1]}x{chw[2]} (the policy was trained on {ft.shape[1]}x{ft.shape[2]})")
        elif shape != tuple(ft.shape):
            problems.append(f"`{key}` of shape {shape} (the policy reads {tuple(ft.shape)})")
    return problems


def training_recording(checkpoint: Path | str) -> tuple[Path, dict] | None:
    """(root, settings) of the recording a checkpoint was trained on, where its `train_config.json` names a
    dataset root that holds this project's recorder sidecar; None where that cannot be known."""
    train_config = Path(checkpoint) / "train_config.json"
    if not train_config.is_file():
        return None
    try:
        dataset = json.loads(train_config.read_text()).get("dataset") or {}
    except json.JSONDecodeError:
        return None
    root = dataset.get("root")
    if not root or not (Path(root) / SIDECAR).is_file():
        return None
    settings = json.loads((Path(root) / SIDECAR).read_text()).get("settings") or {}
    return Path(root), settings


def recording_mismatches(record: dict, settings: dict) -> list[str]:
    """Where the env differs from the recording the policy was trained on: task, workspace."""
    task = settings.get("task")
    if task not in RECORDED_TASK_ENVS:
        return []
    env_type, gym_task = RECORDED_TASK_ENVS[task]
    problems = []
    if record.get("type") not in SAME_SIMULATION.get(env_type, (env_type,)):
        problems.append(f"env type {record.get('type')} (the policy was trained on {task}, a {env_type} task)")
    elif gym_task is not None and record.get("task") not in (gym_task, None):
        problems.append(f"task {record.get('task')} (the policy was trained on {gym_task})")
    recorded_workspace = settings.get("workspace") or (LEGACY_WORKSPACE if task == ARM_TASK else None)
    if recorded_workspace is not None and record.get("workspace") not in (recorded_workspace, None):
        problems.append(f"workspace {record.get('workspace')} (the policy was trained on {recorded_workspace})")
    return problems


def rollout_env_problems(info: dict, policy: PreTrainedConfig | None, recording: dict | None) -> list[str]:
    """Why rollouts recorded in `info` (lerobot-vib-eval's uncertainty_info.json) are not clean rollouts of this
    policy in the env it was trained for; empty if they are."""
    record = info.get("env")
    if record is None:
        return ["it does not record the env the rollouts ran in (written by an earlier lerobot-vib-eval)"]
    problems = []
    if perturbed := active_perturbations(record.get("perturbation")):
        problems.append(f"the env was perturbed ({', '.join(perturbed)})")
    if policy is not None:
        problems += [f"the env had {p}" for p in input_mismatches(record, policy)]
    if recording is not None:
        problems += [f"the env had {p}" for p in recording_mismatches(record, recording)]
    return problems
