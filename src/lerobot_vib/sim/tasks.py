"""gym-aloha's ALOHA tasks with rendering limited to the cameras asked for, at the size asked for.

gym-aloha's tasks render three 480x640 cameras on every step although the env returns only `top`;
rendering is almost all of a step's cost (physics is under 1 ms). These subclasses change nothing but
`get_observation`, so dynamics, rewards and object placement stay gym-aloha's.

Joint-controlled tasks (what policies act in) place objects from gym-aloha's global `BOX_POSE`, set by
`gym_aloha.env.AlohaEnv.reset(seed)`. End-effector (mocap) tasks, used only to script demonstrations,
take the object pose explicitly instead of gym-aloha's unseeded sampling.
"""

from __future__ import annotations

import collections
from collections.abc import Sequence

import numpy as np
from dm_control import mujoco
from dm_control.rl import control
from gym_aloha.constants import ASSETS_DIR, DT
from gym_aloha.tasks.sim import InsertionTask, TransferCubeTask
from gym_aloha.tasks.sim_end_effector import (
    BimanualViperXEndEffectorTask,
    InsertionEndEffectorTask,
    TransferCubeEndEffectorTask,
)

from .env_config import CAMERAS

TASKS = ("transfer_cube", "insertion")
TASK_STRINGS = {  # the Hub datasets' task strings
    "transfer_cube": "Pick up the cube with the right arm and transfer it to the left arm.",
    "insertion": "Insert the peg into the socket.",
}
WELD_SOLIMP = (0.9, 0.95, 0.001, 0.5, 2.0)  # MuJoCo's default solimp


def check_task(task: str) -> str:
    if task not in TASKS:
        raise ValueError(f"Unknown ALOHA task {task!r}; expected one of {TASKS}.")
    return task


def check_cameras(cameras: Sequence[str]) -> tuple[str, ...]:
    unknown = [c for c in cameras if c not in CAMERAS]
    if unknown:
        raise ValueError(f"Unknown ALOHA camera(s) {unknown}; gym-aloha's scene has {list(CAMERAS)}.")
    return tuple(cameras)


class _SelectiveRender:
    """Mixin: render `cameras` at (height, width) in `get_observation`, nothing else.

    `shadows=False` skips MuJoCo's shadow passes (three lights: about 3x faster on a CPU renderer) at the
    cost of images that differ from gym-aloha's.
    """

    def __init__(
        self,
        cameras: Sequence[str] = ("top",),
        height: int = 480,
        width: int = 640,
        shadows: bool = True,
        random=None,
    ):
        super().__init__(random=random)
        self.cameras = check_cameras(cameras)
        self.height, self.width = height, width
        self.render_flags = None if shadows else {"shadow": False}

    def get_observation(self, physics):
        obs = collections.OrderedDict()
        obs["qpos"] = self.get_qpos(physics)
        obs["qvel"] = self.get_qvel(physics)
        obs["env_state"] = self.get_env_state(physics)
        obs["images"] = {
            c: physics.render(self.height, self.width, camera_id=c, render_flag_overrides=self.render_flags)
            for c in self.cameras
        }
        return obs


class FastTransferCubeTask(_SelectiveRender, TransferCubeTask):
    pass


class FastInsertionTask(_SelectiveRender, InsertionTask):
    pass


class _PosedEndEffector:
    """Mixin for the mocap tasks: objects at `self.object_pose` (set before reset); no camera rendering."""

    object_pose: np.ndarray | None = None

    def initialize_episode(self, physics):
        if self.object_pose is None:
            raise RuntimeError("Set `task.object_pose` before resetting a scripted end-effector episode.")
        self.initialize_robots(physics)
        # The objects' free joints follow the 16 robot joints in qpos, 7 numbers (position, quaternion) each.
        np.copyto(physics.data.qpos[16 : 16 + len(self.object_pose)], self.object_pose)
        # Skip the task classes' initialize_episode, which samples a new, unseeded pose.
        BimanualViperXEndEffectorTask.initialize_episode(self, physics)

    def get_observation(self, physics):
        obs = collections.OrderedDict()
        obs["qpos"] = self.get_qpos(physics)
        obs["env_state"] = self.get_env_state(physics)
        obs["mocap_pose_left"] = np.concatenate([physics.data.mocap_pos[0], physics.data.mocap_quat[0]]).copy()
        obs["mocap_pose_right"] = np.concatenate([physics.data.mocap_pos[1], physics.data.mocap_quat[1]]).copy()
        obs["gripper_ctrl"] = physics.data.ctrl.copy()
        return obs


class PosedTransferCubeEndEffectorTask(_PosedEndEffector, TransferCubeEndEffectorTask):
    pass


class PosedInsertionEndEffectorTask(_PosedEndEffector, InsertionEndEffectorTask):
    pass


def make_joint_env(
    task: str, cameras: Sequence[str], height: int, width: int, shadows: bool = True
) -> control.Environment:
    """The joint-controlled dm_control environment gym-aloha builds, with selective rendering."""
    task_cls = {"transfer_cube": FastTransferCubeTask, "insertion": FastInsertionTask}[check_task(task)]
    physics = mujoco.Physics.from_xml_path(str(ASSETS_DIR / f"bimanual_viperx_{task}.xml"))
    return control.Environment(
        physics,
        task_cls(cameras, height, width, shadows),
        time_limit=float("inf"),
        control_timestep=DT,
        n_sub_steps=None,
        flat_observation=False,
    )


def make_end_effector_env(task: str) -> control.Environment:
    """The mocap-controlled environment for scripting demonstrations (no rendering)."""
    task_cls = {
        "transfer_cube": PosedTransferCubeEndEffectorTask,
        "insertion": PosedInsertionEndEffectorTask,
    }[check_task(task)]
    physics = mujoco.Physics.from_xml_path(str(ASSETS_DIR / f"bimanual_viperx_end_effector_{task}.xml"))
    # gym-aloha's mocap welds use solimp=".25 .25 .001": with current MuJoCo the grippers then sag far off
    # their targets and the scripts miss the objects. MuJoCo's default impedance makes the welds track.
    # This only shapes the scripted motion; datasets replay it in gym-aloha's unmodified joint task.
    physics.model.eq_solimp[:] = WELD_SOLIMP
    return control.Environment(
        physics, task_cls(), time_limit=float("inf"), control_timestep=DT, n_sub_steps=None, flat_observation=False
    )
