"""Scripted ALOHA demonstrations: open-loop end-effector waypoints planned from the object pose.

A script is, per arm, a list of waypoints (t, position, orientation quaternion, gripper opening in [0, 1])
planned at the first step from the sampled object pose. Between waypoints everything is interpolated
linearly in time (quaternions are re-normalized):

    x(t) = x_i + (x_{i+1} - x_i) * (t - t_i) / (t_{i+1} - t_i),   t_i <= t < t_{i+1}.

The scripts drive gym-aloha's mocap (end-effector) tasks; the joint trajectory this produces, with the
gripper *commands* put in place of the measured gripper positions, is what the joint-controlled task then
replays and a dataset records as actions (`joint_actions`).
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np
from gym_aloha.constants import normalize_puppet_gripper_position
from gym_aloha.utils import sample_box_pose, sample_insertion_pose

from .tasks import check_task, make_end_effector_env

EPISODE_LENGTH = 400  # steps at 50 Hz
SUCCESS_REWARD = 4  # gym-aloha's max reward for both tasks


def object_pose(task: str, seed: int | None) -> np.ndarray:
    """The object pose gym-aloha's `reset(seed)` places: cube (7,) or peg + socket (14,)."""
    if check_task(task) == "transfer_cube":
        return sample_box_pose(seed)
    return np.concatenate(sample_insertion_pose(seed))


def _quat(axis: tuple[float, float, float], degrees: float) -> np.ndarray:
    q = np.zeros(4)
    mujoco.mju_axisAngle2Quat(q, np.asarray(axis, dtype=float), np.deg2rad(degrees))
    return q


def _rotate(q: np.ndarray, axis: tuple[float, float, float], degrees: float) -> np.ndarray:
    """q * rotation(axis, degrees): a rotation about the gripper's own axis."""
    out = np.zeros(4)
    mujoco.mju_mulQuat(out, np.asarray(q, dtype=float), _quat(axis, degrees))
    return out


@dataclass
class Waypoint:
    t: int
    xyz: np.ndarray
    quat: np.ndarray
    gripper: float  # 0: closed, 1: open


class WaypointScript:
    """Interpolates each arm's waypoints; `__call__(t)` is the 16-d mocap action
    [left xyz (3), left quat (4), left gripper (1), right xyz, right quat, right gripper]."""

    def __init__(self, left: list[Waypoint], right: list[Waypoint]):
        for name, wps in (("left", left), ("right", right)):
            ts = [w.t for w in wps]
            if ts[0] != 0 or ts != sorted(ts) or len(set(ts)) != len(ts):
                raise ValueError(f"{name} waypoints must start at t=0 and strictly increase, got {ts}.")
        self.left, self.right = left, right

    @staticmethod
    def _at(wps: list[Waypoint], t: int) -> np.ndarray:
        if t >= wps[-1].t:
            w = wps[-1]
            return np.concatenate([w.xyz, w.quat / np.linalg.norm(w.quat), [w.gripper]])
        i = max(k for k, w in enumerate(wps) if w.t <= t)
        a, b = wps[i], wps[i + 1]
        f = (t - a.t) / (b.t - a.t)
        quat = a.quat + (b.quat - a.quat) * f
        return np.concatenate(
            [a.xyz + (b.xyz - a.xyz) * f, quat / np.linalg.norm(quat), [a.gripper + (b.gripper - a.gripper) * f]]
        )

    def __call__(self, t: int) -> np.ndarray:
        return np.concatenate([self._at(self.left, t), self._at(self.right, t)])


def plan_transfer_cube(first_obs: dict) -> WaypointScript:
    """Right arm picks the cube and carries it to a meeting point; the left arm takes it over."""
    left0, right0 = first_obs["mocap_pose_left"], first_obs["mocap_pose_right"]
    cube = np.asarray(first_obs["env_state"])[:3]
    pick_quat = _rotate(right0[3:], (0.0, 1.0, 0.0), -60)  # tilt the right gripper towards the cube
    meet_quat_left = _quat((1.0, 0.0, 0.0), 90)  # left gripper turned to take the cube from the side
    meet = np.array([0.0, 0.5, 0.25])
    wp = Waypoint
    left = [
        wp(0, left0[:3], left0[3:], 0),
        wp(100, meet + [-0.1, 0, -0.02], meet_quat_left, 1),  # approach the meeting point, open
        wp(260, meet + [0.02, 0, -0.02], meet_quat_left, 1),  # reach around the cube
        wp(310, meet + [0.02, 0, -0.02], meet_quat_left, 0),  # close on it
        wp(360, meet + [-0.1, 0, -0.02], np.array([1.0, 0, 0, 0]), 0),  # pull it away
        wp(400, meet + [-0.1, 0, -0.02], np.array([1.0, 0, 0, 0]), 0),
    ]
    right = [
        wp(0, right0[:3], right0[3:], 0),
        wp(90, cube + [0, 0, 0.08], pick_quat, 1),  # above the cube, open
        wp(130, cube + [0, 0, -0.015], pick_quat, 1),  # down around it
        wp(170, cube + [0, 0, -0.015], pick_quat, 0),  # grasp
        wp(200, meet + [0.05, 0, 0], pick_quat, 0),  # lift towards the meeting point
        wp(220, meet, pick_quat, 0),
        wp(310, meet, pick_quat, 1),  # release once the left gripper holds it
        wp(360, meet + [0.1, 0, 0], pick_quat, 1),  # move away
        wp(400, meet + [0.1, 0, 0], pick_quat, 1),
    ]
    return WaypointScript(left, right)


def plan_insertion(first_obs: dict) -> WaypointScript:
    """Each arm grasps its object (left: socket, right: peg); they meet and the peg slides into the socket."""
    left0, right0 = first_obs["mocap_pose_left"], first_obs["mocap_pose_right"]
    env_state = np.asarray(first_obs["env_state"])
    peg, socket = env_state[:3], env_state[7:10]
    pick_quat_right = _rotate(right0[3:], (0.0, 1.0, 0.0), -60)
    pick_quat_left = _rotate(right0[3:], (0.0, 1.0, 0.0), 60)
    meet = np.array([0.0, 0.5, 0.15])
    lift_right = 0.00715  # the peg sits this much lower in the right gripper than the socket's hole
    wp = Waypoint
    left = [
        wp(0, left0[:3], left0[3:], 0),
        wp(120, socket + [0, 0, 0.08], pick_quat_left, 1),
        wp(170, socket + [0, 0, -0.03], pick_quat_left, 1),
        wp(220, socket + [0, 0, -0.03], pick_quat_left, 0),
        wp(285, meet + [-0.1, 0, 0], pick_quat_left, 0),
        wp(340, meet + [-0.05, 0, 0], pick_quat_left, 0),  # insert
        wp(400, meet + [-0.05, 0, 0], pick_quat_left, 0),
    ]
    right = [
        wp(0, right0[:3], right0[3:], 0),
        wp(120, peg + [0, 0, 0.08], pick_quat_right, 1),
        wp(170, peg + [0, 0, -0.03], pick_quat_right, 1),
        wp(220, peg + [0, 0, -0.03], pick_quat_right, 0),
        wp(285, meet + [0.1, 0, lift_right], pick_quat_right, 0),
        wp(340, meet + [0.05, 0, lift_right], pick_quat_right, 0),  # insert
        wp(400, meet + [0.05, 0, lift_right], pick_quat_right, 0),
    ]
    return WaypointScript(left, right)


PLANNERS = {"transfer_cube": plan_transfer_cube, "insertion": plan_insertion}


@dataclass
class ScriptedEpisode:
    task: str
    seed: int
    object_pose: np.ndarray
    joint_actions: np.ndarray  # (episode_length, 14) joint-space actions for gym-aloha's joint task
    max_reward: float  # in the end-effector rollout

    @property
    def success(self) -> bool:
        return self.max_reward >= SUCCESS_REWARD


def script_episode(task: str, seed: int, episode_length: int = EPISODE_LENGTH) -> ScriptedEpisode:
    """Run the script in the end-effector task; return the joint actions that replay it.

    Action t is the arm's joint position at step t of the scripted rollout (t = 0: the start pose) with the
    gripper entries replaced by the normalized gripper commands, as in the original ACT data pipeline.
    """
    pose = object_pose(task, seed)
    env = make_end_effector_env(task)
    env.task.object_pose = pose
    ts = env.reset()
    script = PLANNERS[task](ts.observation)
    joint_actions, max_reward = [], 0.0
    for t in range(episode_length):
        qpos = ts.observation["qpos"].copy()
        ctrl = ts.observation["gripper_ctrl"]
        qpos[6] = normalize_puppet_gripper_position(ctrl[0])
        qpos[13] = normalize_puppet_gripper_position(ctrl[2])
        joint_actions.append(qpos)
        ts = env.step(script(t))
        max_reward = max(max_reward, float(ts.reward or 0.0))
    return ScriptedEpisode(task, seed, pose, np.asarray(joint_actions, dtype=np.float32), max_reward)
