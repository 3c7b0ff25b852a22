"""`ArmGraspEnv`: the simulated 6-DoF arm grasping a block, as a gymnasium env in LeRobot's layout.

Observations are `{"pixels": {camera: HxWx3 uint8}, "agent_pos": (7,)}` (six joint angles and the gripper
opening in [0, 1]); the action is the 7 targets of the same quantities, at 20 Hz. `reset(seed)` draws the
block's position and yaw (and the episode's perturbations) from the seed alone, uniformly over the ranges of
the env's `workspace`:

    wide  x in [0.30, 0.48] m, y in [-0.14, 0.14] m, yaw in [-45, 45] deg   (the default; every yaw of the cube)
    near  x in [0.33, 0.45] m, y in [-0.08, 0.08] m, yaw in [-30, 30] deg

Either way a policy must see the block: the gripper's opening leaves about 1.5 cm either side of it.

Reward per step: 0, 0.5 while both fingers touch the block, 1 while the block is lifted (its bottom at
least `LIFT_SUCCESS` above the table). Success, which ends the episode: lifted for `HOLD_STEPS` steps in a
row.

A missed grasp, the moment an episode's failure can be read from the simulator: the gripper closed past half
the block's width (`MISSED_CLOSURE`; a block held between the fingers keeps them at its width) with no finger
on the block. `info["grasp_missed"]` is true at every such step; failure prediction measures its lead time
against the first one.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import ClassVar

import gymnasium as gym
import mujoco
import numpy as np
from gymnasium import spaces

from .arm_scene import (
    BLOCK_HALF,
    BLOCK_RGBA,
    CAMERAS,
    FINGER_TRAVEL,
    FIXED_CAMERAS,
    HOME,
    JOINTS,
    OCCLUDER_PARKED,
    load_model,
)
from .perturbations import ImagePerturbation, PerturbationConfig, draw_scene_episode

TASK = "grasp_block"
TASK_STRING = "Pick up the block."
FPS = 20
EPISODE_LENGTH = 100
SUBSTEPS = 25  # 0.002 s physics steps per 0.05 s control step
LIFT_SUCCESS = 0.04
HOLD_STEPS = 5
MISSED_CLOSURE = 0.5  # opening (1 open) below this share of the block's width: nothing is between the fingers
# The occluder's pose (position, quaternion) for each fixed camera: about 45% of the way from the camera to
# the workspace's centre, its broad face towards the camera, so it hides the block and the gripper.
OCCLUDER_POSES = {
    "scene": (np.array([0.7, 0.0, 0.3]), np.array([1.0, 0.0, 0.0, 0.0])),
    "overhead": (np.array([0.636, 0.0, 0.488]), np.array([0.875, 0.0, -0.485, 0.0])),  # turned to its pitch
}


@dataclass(frozen=True)
class Workspace:
    """Ranges the block's placement is drawn from, uniformly per episode (metres, radians)."""

    x: tuple[float, float]
    y: tuple[float, float]
    yaw: tuple[float, float]


WORKSPACES = {
    "wide": Workspace(x=(0.30, 0.48), y=(-0.14, 0.14), yaw=(-np.pi / 4, np.pi / 4)),
    "near": Workspace(x=(0.33, 0.45), y=(-0.08, 0.08), yaw=(-np.pi / 6, np.pi / 6)),
}
DEFAULT_WORKSPACE = "wide"
# Recordings made before the workspace was a setting placed the block in the wide one.
LEGACY_WORKSPACE = "wide"


def get_workspace(name: str) -> Workspace:
    if name not in WORKSPACES:
        raise ValueError(f"Unknown arm workspace {name!r}; expected one of {list(WORKSPACES)}.")
    return WORKSPACES[name]


def block_pose(seed: int | None, workspace: str = DEFAULT_WORKSPACE) -> tuple[np.ndarray, float]:
    """The block's centre (x, y on the table) and yaw for `seed` in `workspace`."""
    ranges = get_workspace(workspace)
    rng = np.random.default_rng(seed)
    xy = np.array([rng.uniform(*ranges.x), rng.uniform(*ranges.y)])
    return xy, float(rng.uniform(*ranges.yaw))


def check_cameras(cameras: Sequence[str]) -> tuple[str, ...]:
    unknown = [c for c in cameras if c not in CAMERAS]
    if unknown:
        raise ValueError(f"Unknown arm camera(s) {unknown}; the scene has {list(CAMERAS)}.")
    return tuple(cameras)


class ArmGraspEnv(gym.Env):
    metadata: ClassVar[dict] = {"render_modes": ["rgb_array"], "render_fps": FPS}

    def __init__(
        self,
        observation_height: int = 96,
        observation_width: int = 128,
        cameras: Sequence[str] = ("scene",),
        shadows: bool = True,
        workspace: str = DEFAULT_WORKSPACE,
        perturbation: PerturbationConfig | dict | None = None,
        render_mode: str = "rgb_array",
        visualization_height: int = 240,
        visualization_width: int = 320,
        obs_type: str = "pixels_agent_pos",
    ):
        if obs_type != "pixels_agent_pos":
            raise ValueError(f"ArmGraspEnv supports obs_type='pixels_agent_pos' only, got {obs_type!r}.")
        if isinstance(perturbation, dict):
            perturbation = PerturbationConfig(**perturbation)
        self.perturbation = perturbation or PerturbationConfig()
        self.cameras = check_cameras(cameras)
        get_workspace(workspace)
        self.workspace = workspace
        self.height, self.width = observation_height, observation_width
        self.vis_size = (visualization_height, visualization_width)
        self.render_mode = render_mode
        self.shadows = shadows
        self.model = load_model()
        self.data = mujoco.MjData(self.model)
        self._renderers: dict[tuple[int, int], mujoco.Renderer] = {}
        self._ids()
        # Shake and occlusion act on the fixed cameras observed (the scene camera if only the wrist is).
        observed_fixed = [c for c in FIXED_CAMERAS if c in self.cameras] or ["scene"]
        self._shaken = {c: self.model.camera(c).id for c in observed_fixed}
        self._cam_pose0 = {
            c: (self.model.cam_pos[i].copy(), self.model.cam_quat[i].copy()) for c, i in self._shaken.items()
        }
        self._occluder_pose = OCCLUDER_POSES[observed_fixed[0]]
        self.image_perturbation = ImagePerturbation(self.perturbation)
        self.scene = draw_scene_episode(self.perturbation, None)
        self.step_count = 0
        self.lifted_steps = 0

        image = spaces.Box(0, 255, shape=(observation_height, observation_width, 3), dtype=np.uint8)
        self.observation_space = spaces.Dict(
            {
                "pixels": spaces.Dict({cam: image for cam in self.cameras}),
                "agent_pos": spaces.Box(-10.0, 10.0, shape=(len(JOINTS) + 1,), dtype=np.float64),
            }
        )
        low = np.append(self.model.actuator_ctrlrange[: len(JOINTS), 0], 0.0)
        high = np.append(self.model.actuator_ctrlrange[: len(JOINTS), 1], 1.0)
        self.action_space = spaces.Box(low.astype(np.float32), high.astype(np.float32), dtype=np.float32)

    def _ids(self) -> None:
        m = self.model
        self._qadr = np.array([m.joint(j).qposadr[0] for j in JOINTS])
        self._finger = m.joint("finger_left").qposadr[0]
        self._finger_r = m.joint("finger_right").qposadr[0]
        self._block_qadr = m.joint("block").qposadr[0]
        self._block_geom = m.geom("block").id
        self._finger_geoms = {m.body("finger_left").id, m.body("finger_right").id}
        self._occluder = m.body("occluder").mocapid[0]
        self._occluder_geom = m.geom("occluder").id

    @property
    def task(self) -> str:
        """The task's name. LeRobot asks every env of a batch for `task` and `task_description`; in a batch of
        subprocess envs a missing attribute shuts the workers down."""
        return TASK

    @property
    def task_description(self) -> str:
        return TASK_STRING

    @property
    def block_half(self) -> float:
        return float(self.model.geom_size[self._block_geom][0])

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        if seed is None:  # an unseeded episode still needs a reproducible draw from the env's generator
            seed = int(self.np_random.integers(2**31))
        self.scene = draw_scene_episode(self.perturbation, seed)
        self.image_perturbation.reset(seed)
        half = self.scene.block_half or BLOCK_HALF
        self.model.geom_size[self._block_geom] = half
        self.model.geom_rgba[self._block_geom] = self.scene.block_rgba or BLOCK_RGBA
        mujoco.mj_resetData(self.model, self.data)
        xy, yaw = block_pose(seed, self.workspace)
        self.data.qpos[self._qadr] = HOME
        self.data.qpos[self._finger] = self.data.qpos[self._finger_r] = FINGER_TRAVEL
        self.data.qpos[self._block_qadr : self._block_qadr + 7] = [*xy, half, np.cos(yaw / 2), 0, 0, np.sin(yaw / 2)]
        self.data.ctrl[: len(JOINTS)] = HOME
        self.data.ctrl[len(JOINTS)] = FINGER_TRAVEL
        self.step_count = self.lifted_steps = 0
        self._place_scene_perturbations()
        mujoco.mj_forward(self.model, self.data)
        return self._observation(), {"is_success": False, "grasp_missed": False}

    def step(self, action):
        action = np.asarray(action, dtype=np.float64)
        if action.shape != (len(JOINTS) + 1,) or not np.all(np.isfinite(action)):
            raise ValueError(f"ArmGraspEnv expects 7 finite action values, got shape {action.shape}: {action}.")
        self.data.ctrl[: len(JOINTS)] = action[: len(JOINTS)]
        self.data.ctrl[len(JOINTS)] = np.clip(action[len(JOINTS)], 0.0, 1.0) * FINGER_TRAVEL
        mujoco.mj_step(self.model, self.data, nstep=SUBSTEPS)
        self.step_count += 1
        self._place_scene_perturbations()
        mujoco.mj_forward(self.model, self.data)  # the moved camera and occluder are in the rendered frame
        lifted = self.block_height() - self.block_half >= LIFT_SUCCESS
        self.lifted_steps = self.lifted_steps + 1 if lifted else 0
        reward = 1.0 if lifted else 0.5 if self.fingers_touch_block() else 0.0
        success = self.lifted_steps >= HOLD_STEPS
        info = {"is_success": success, "grasp_missed": self.grasp_missed()}
        return self._observation(), reward, success, False, info

    def grasp_missed(self) -> bool:
        """The gripper is closed past the block's width and does not touch it (the module docstring)."""
        opening = self.data.qpos[self._finger] / FINGER_TRAVEL
        closed_past_block = opening < MISSED_CLOSURE * self.block_half / FINGER_TRAVEL
        return bool(closed_past_block and not self.fingers_touch_block())

    def block_height(self) -> float:
        return float(self.data.qpos[self._block_qadr + 2])

    def fingers_touch_block(self) -> bool:
        touching = set()
        for c in self.data.contact[: self.data.ncon]:
            for mine, other in ((c.geom1, c.geom2), (c.geom2, c.geom1)):
                if mine == self._block_geom and self.model.geom_bodyid[other] in self._finger_geoms:
                    touching.add(int(self.model.geom_bodyid[other]))
        return len(touching) == 2

    def _place_scene_perturbations(self) -> None:
        occluded = self.scene.occluded(self.step_count)
        pos, quat = self._occluder_pose
        self.data.mocap_pos[self._occluder] = pos if occluded else OCCLUDER_PARKED
        self.data.mocap_quat[self._occluder] = quat
        for camera, cam in self._shaken.items():
            pos0, quat0 = self._cam_pose0[camera]
            if self.scene.shake > 0:
                rng, amp = self.scene.rng, self.scene.shake
                self.model.cam_pos[cam] = pos0 + rng.uniform(-amp, amp, 3)
                turn = np.zeros(4)
                axis = rng.normal(size=3) / np.sqrt(3) + 1e-9
                mujoco.mju_axisAngle2Quat(turn, axis, rng.uniform(-10 * amp, 10 * amp))
                mujoco.mju_mulQuat(self.model.cam_quat[cam], quat0, turn)
            else:
                self.model.cam_pos[cam] = pos0
                self.model.cam_quat[cam] = quat0

    def occluder_mask(self) -> np.ndarray:
        """(H, W) bool at the observation's size: the pixels of the occluded camera (the first fixed camera
        observed) that show the occluder in the current frame; all False while the board is parked. MuJoCo's
        segmentation rendering names the geom each pixel shows, so the mask follows a shaken camera too."""
        renderer = self._renderer(self.height, self.width)
        renderer.update_scene(self.data, camera=next(iter(self._shaken)))
        renderer.enable_segmentation_rendering()
        try:
            ids = renderer.render()
        finally:
            renderer.disable_segmentation_rendering()
        return (ids[..., 0] == self._occluder_geom) & (ids[..., 1] == int(mujoco.mjtObj.mjOBJ_GEOM))

    def _renderer(self, height: int, width: int) -> mujoco.Renderer:
        if (height, width) not in self._renderers:
            self._renderers[(height, width)] = mujoco.Renderer(self.model, height, width)
        return self._renderers[(height, width)]

    def _render(self, camera: str, height: int, width: int) -> np.ndarray:
        renderer = self._renderer(height, width)
        renderer.update_scene(self.data, camera=camera)
        renderer.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = self.shadows
        return renderer.render()

    def _observation(self) -> dict:
        state = np.append(self.data.qpos[self._qadr], self.data.qpos[self._finger] / FINGER_TRAVEL)
        pixels = {c: self.image_perturbation(self._render(c, self.height, self.width), c) for c in self.cameras}
        return {"pixels": pixels, "agent_pos": state}

    def render(self) -> np.ndarray:
        return self._render("scene", *self.vis_size)

    def close(self) -> None:
        for renderer in self._renderers.values():
            renderer.close()
        self._renderers.clear()
