"""The tasks `lerobot-vib-record-sim` records: how each scripts, renders and describes an episode."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from gymnasium import Env

from . import arm_env, arm_scene
from .aloha_env import FastAlohaEnv
from .arm_scripted import plan_grasp
from .env_config import CAMERAS as ALOHA_CAMERAS
from .scripted import SUCCESS_REWARD, script_episode
from .tasks import TASK_STRINGS

ALOHA_MOTORS = [
    f"{side}_{joint}"
    for side in ("left", "right")
    for joint in ("waist", "shoulder", "elbow", "forearm_roll", "wrist_angle", "wrist_rotate", "gripper")
]


@dataclass(frozen=True)
class ScriptedTask:
    name: str
    task_string: str  # the dataset's task (LeRobot's language instruction)
    robot_type: str
    fps: int
    state_names: list[str]  # also the action's names: both are joint positions
    cameras: tuple[str, ...]  # every camera the scene has
    default_cameras: tuple[str, ...]
    default_size: tuple[int, int]  # (height, width)
    # (cameras, height, width, shadows, workspace) -> an env whose reset(seed) places the scene of that seed
    make_env: Callable[[Sequence[str], int, int, bool, str | None], Env]
    # (seed, workspace) -> the joint actions of a scripted episode that succeeds, or None where the script fails
    scripted_actions: Callable[[int, str | None], np.ndarray | None]
    # Named ranges of the object's placement the task offers (the arm's `arm_env.WORKSPACES`); empty where
    # the scene fixes them (ALOHA).
    workspaces: tuple[str, ...] = ()
    default_workspace: str | None = None

    def check_cameras(self, cameras: Sequence[str]) -> tuple[str, ...]:
        unknown = [c for c in cameras if c not in self.cameras]
        if unknown or not cameras:
            raise ValueError(
                f"Cameras must be a non-empty subset of {list(self.cameras)} for {self.name}, got {list(cameras)}."
            )
        return tuple(cameras)

    def check_workspace(self, workspace: str | None) -> str | None:
        """`workspace`, or the task's default where None; a workspace the task does not have is refused."""
        if workspace is None:
            return self.default_workspace
        if workspace not in self.workspaces:
            offered = f"one of {list(self.workspaces)}" if self.workspaces else "none (its scene fixes the placement)"
            raise ValueError(f"Unknown workspace {workspace!r} for {self.name}; it offers {offered}.")
        return workspace


def replay_max_reward(task: str, seed: int, actions: np.ndarray) -> float:
    """Max reward of replaying `actions` from `reset(seed)` in gym-aloha's joint task, physics only."""
    env = FastAlohaEnv(task, cameras=())
    env.reset(seed=seed)
    best = 0.0
    for action in actions:
        _, reward, *_ = env.step(action)
        best = max(best, float(reward))
    return best


def _aloha_task(name: str) -> ScriptedTask:
    def make_env(cameras: Sequence[str], height: int, width: int, shadows: bool, workspace: None = None) -> Env:
        return FastAlohaEnv(name, cameras=cameras, observation_height=height, observation_width=width, shadows=shadows)

    def scripted_actions(seed: int, workspace: None = None) -> np.ndarray | None:
        actions = script_episode(name, seed).joint_actions
        # The end-effector script can succeed where the joint replay does not; only the replay is recorded.
        return actions if replay_max_reward(name, seed, actions) >= SUCCESS_REWARD else None

    return ScriptedTask(
        name=name,
        task_string=TASK_STRINGS[name],
        robot_type="aloha",
        fps=50,
        state_names=ALOHA_MOTORS,
        cameras=ALOHA_CAMERAS,
        default_cameras=("top",),
        default_size=(480, 640),
        make_env=make_env,
        scripted_actions=scripted_actions,
    )


def _arm_env(cameras: Sequence[str], height: int, width: int, shadows: bool, workspace: str | None = None) -> Env:
    return arm_env.ArmGraspEnv(
        observation_height=height,
        observation_width=width,
        cameras=cameras,
        shadows=shadows,
        workspace=workspace or arm_env.DEFAULT_WORKSPACE,
    )


def _arm_actions(seed: int, workspace: str | None = None) -> np.ndarray | None:
    workspace = workspace or arm_env.DEFAULT_WORKSPACE
    # Physics only: the plan is checked before anything is rendered.
    env = arm_env.ArmGraspEnv(cameras=(), workspace=workspace)
    try:
        env.reset(seed=seed)
        xy, yaw = arm_env.block_pose(seed, workspace)
        plan = plan_grasp(env.model, np.array([*xy, env.block_half]), yaw, arm_env.EPISODE_LENGTH, env.block_half)
        for action in plan.actions:
            if env.step(action)[2]:
                return plan.actions
        return None
    finally:
        env.close()


SCRIPTED_TASKS = {
    "transfer_cube": _aloha_task("transfer_cube"),
    "insertion": _aloha_task("insertion"),
    arm_env.TASK: ScriptedTask(
        name=arm_env.TASK,
        task_string=arm_env.TASK_STRING,
        robot_type="vib_sim_arm",
        fps=arm_env.FPS,
        state_names=arm_scene.STATE_NAMES,
        cameras=arm_scene.CAMERAS,
        default_cameras=("scene",),
        default_size=(96, 128),
        make_env=_arm_env,
        scripted_actions=_arm_actions,
        workspaces=tuple(arm_env.WORKSPACES),
        default_workspace=arm_env.DEFAULT_WORKSPACE,
    ),
}


def get_task(name: str) -> ScriptedTask:
    if name not in SCRIPTED_TASKS:
        raise ValueError(f"Unknown task {name!r}; expected one of {list(SCRIPTED_TASKS)}.")
    return SCRIPTED_TASKS[name]
