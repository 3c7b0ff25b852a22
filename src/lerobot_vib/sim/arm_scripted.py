"""Scripted grasps for the simulated arm: Cartesian waypoints from the block pose, joint targets by IK.

The gripper's tool point (site `grip`, between the fingertips) follows waypoints above, at and above the
block, pointing down with the fingers across two faces of the block. Between waypoints the target moves
with a smooth-step profile s(f) = 3f^2 - 2f^3 (zero velocity at every waypoint). At each control step the
joint targets solve the IK by damped least squares on MuJoCo's site Jacobian J (6x6, position and
rotation), warm-started from the previous step:

    dq = J^T (J J^T + lambda^2 I)^{-1} e,    e = [p* - p, omega(R* R^T)],

where omega(.) is the rotation vector of the orientation error. The kinematics are MuJoCo's own
(`mj_kinematics`, `mj_jacSite`), so the script fits whatever the MJCF says.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from .arm_scene import HOME, JOINTS

# Waypoint times in control steps (20 Hz) and tool-point heights above the block's centre.
APPROACH_END, DESCEND_END, CLOSE_END, LIFT_END = 32, 48, 58, 78
PREGRASP_HEIGHT, GRASP_HEIGHT, LIFT_HEIGHT = 0.10, 0.0, 0.14


def grasp_rotation(block_yaw: float) -> np.ndarray:
    """Tool frame for a top grasp: x (tool axis) down, y (finger travel) across two faces of the block.

    A cube looks the same every 90 degrees, so the yaw is taken modulo 90 degrees into [-45, 45): the wrist
    turns as little as possible.
    """
    yaw = (block_yaw + np.pi / 4) % (np.pi / 2) - np.pi / 4
    x = np.array([0.0, 0.0, -1.0])
    y = np.array([-np.sin(yaw), np.cos(yaw), 0.0])
    return np.stack([x, y, np.cross(x, y)], axis=1)


class ArmIK:
    """Damped-least-squares IK for the tool point on its own MjData (the simulation is never touched)."""

    def __init__(self, model: mujoco.MjModel, damping: float = 1e-2):
        self.model = model
        self.data = mujoco.MjData(model)
        self.damping = damping
        self.site = model.site("grip").id
        self.qadr = np.array([model.joint(j).qposadr[0] for j in JOINTS])
        self.dofs = np.array([model.joint(j).dofadr[0] for j in JOINTS])
        self.lower = np.array([model.joint(j).range[0] for j in JOINTS])
        self.upper = np.array([model.joint(j).range[1] for j in JOINTS])

    def forward(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Tool-point position and rotation matrix at joint angles q."""
        self.data.qpos[self.qadr] = q
        mujoco.mj_kinematics(self.model, self.data)
        return self.data.site_xpos[self.site].copy(), self.data.site_xmat[self.site].reshape(3, 3).copy()

    def solve(
        self, pos: np.ndarray, rot: np.ndarray, q0: np.ndarray, iters: int = 50, tol: float = 1e-4
    ) -> tuple[np.ndarray, float]:
        """Joint angles reaching (pos, rot) from q0, and the remaining error norm (metres + radians)."""
        q = np.array(q0, dtype=float)
        jacp, jacr = np.zeros((3, self.model.nv)), np.zeros((3, self.model.nv))
        target_quat, current_quat, omega = np.zeros(4), np.zeros(4), np.zeros(3)
        mujoco.mju_mat2Quat(target_quat, rot.reshape(-1))
        err = np.inf
        for _ in range(iters):
            p, r = self.forward(q)
            mujoco.mju_mat2Quat(current_quat, r.reshape(-1))
            mujoco.mju_subQuat(omega, target_quat, current_quat)  # in the current frame
            e = np.concatenate([pos - p, r @ omega])
            err = float(np.linalg.norm(e))
            if err < tol:
                break
            mujoco.mj_comPos(self.model, self.data)
            mujoco.mj_jacSite(self.model, self.data, jacp, jacr, self.site)
            jac = np.vstack([jacp, jacr])[:, self.dofs]
            dq = jac.T @ np.linalg.solve(jac @ jac.T + self.damping**2 * np.eye(6), e)
            q = np.clip(q + dq, self.lower, self.upper)
        return q, err


@dataclass
class GraspPlan:
    """Per control step: the 6 joint targets and the gripper opening (1 open, 0 closed)."""

    actions: np.ndarray  # (episode_length, 7)
    max_ik_error: float


def _smooth(f: float) -> float:
    f = min(max(f, 0.0), 1.0)
    return f * f * (3 - 2 * f)


def plan_grasp(
    model: mujoco.MjModel, block_pos: np.ndarray, block_yaw: float, episode_length: int, block_half: float
) -> GraspPlan:
    """Joint-space actions of a top grasp of the block at `block_pos` (its centre) and `block_yaw`."""
    ik = ArmIK(model)
    start_pos, start_rot = ik.forward(HOME)
    rot = grasp_rotation(block_yaw)
    above = block_pos + [0, 0, PREGRASP_HEIGHT]
    at = block_pos + [0, 0, GRASP_HEIGHT + 0.25 * block_half]
    lifted = block_pos + [0, 0, LIFT_HEIGHT]
    # (end step, target position, gripper) of each segment; orientation turns during the approach only.
    segments = [(APPROACH_END, above, 1.0), (DESCEND_END, at, 1.0), (CLOSE_END, at, 0.0), (LIFT_END, lifted, 0.0)]
    start_quat, end_quat = np.zeros(4), np.zeros(4)
    mujoco.mju_mat2Quat(start_quat, start_rot.reshape(-1))
    mujoco.mju_mat2Quat(end_quat, rot.reshape(-1))
    if start_quat @ end_quat < 0:
        end_quat = -end_quat
    q, actions, worst = HOME.copy(), [], 0.0
    seg_start, seg_from, grip_from = 0, start_pos, 1.0
    seg = 0
    for t in range(episode_length):
        while seg < len(segments) and t >= segments[seg][0]:
            seg_start, seg_from, grip_from = segments[seg][0], segments[seg][1], segments[seg][2]
            seg += 1
        if seg < len(segments):
            end, target, grip_to = segments[seg]
            f = _smooth((t - seg_start) / (end - seg_start))
            pos = seg_from + (target - seg_from) * f
            grip = grip_from + (grip_to - grip_from) * f
        else:
            pos, grip = seg_from, grip_from
        if t < APPROACH_END:
            quat = start_quat + (end_quat - start_quat) * _smooth(t / APPROACH_END)
            r = np.zeros(9)
            mujoco.mju_quat2Mat(r, quat / np.linalg.norm(quat))
            r = r.reshape(3, 3)
        else:
            r = rot
        q, err = ik.solve(pos, r, q)
        worst = max(worst, err)
        actions.append(np.concatenate([q, [grip]]))
    return GraspPlan(np.asarray(actions, dtype=np.float32), worst)
