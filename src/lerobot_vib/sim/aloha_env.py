"""`FastAlohaEnv`: gym-aloha's env, rendering only the cameras asked for, at the size asked for.

Observations have gym-aloha's `pixels_agent_pos` layout, `{"pixels": {camera: HxWx3 uint8}, "agent_pos": (14,)}`,
and resets, dynamics, rewards and success are gym-aloha's (this class only swaps the task's rendering).
`cameras=()` renders nothing: a physics-only env for checking action sequences. `perturbation` adds the
image perturbations of `perturbations.py` (noise, colour jitter), drawn per episode from the reset seed.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from gym_aloha.constants import JOINTS
from gym_aloha.env import AlohaEnv
from gymnasium import spaces

from .perturbations import ImagePerturbation, PerturbationConfig
from .tasks import TASK_STRINGS, check_cameras, make_joint_env


class FastAlohaEnv(AlohaEnv):
    def __init__(
        self,
        task: str,
        obs_type: str = "pixels_agent_pos",
        render_mode: str = "rgb_array",
        observation_width: int = 640,
        observation_height: int = 480,
        visualization_width: int = 640,
        visualization_height: int = 480,
        cameras: Sequence[str] = ("top",),
        shadows: bool = True,
        perturbation: PerturbationConfig | dict | None = None,
    ):
        if isinstance(perturbation, dict):
            perturbation = PerturbationConfig(**perturbation)
        perturbation = perturbation or PerturbationConfig()
        if perturbation.scene_perturbations:
            raise ValueError(f"FastAlohaEnv takes image perturbations only, got {perturbation.scene_perturbations}.")
        self.image_perturbation = ImagePerturbation(perturbation)
        if obs_type != "pixels_agent_pos":
            raise ValueError(f"FastAlohaEnv supports obs_type='pixels_agent_pos' only, got {obs_type!r}.")
        self.cameras = check_cameras(cameras)
        self.shadows = shadows
        super().__init__(
            task=task,
            obs_type=obs_type,
            render_mode=render_mode,
            observation_width=observation_width,
            observation_height=observation_height,
            visualization_width=visualization_width,
            visualization_height=visualization_height,
        )
        image = spaces.Box(0, 255, shape=(observation_height, observation_width, 3), dtype=np.uint8)
        self.observation_space = spaces.Dict(
            {
                "pixels": spaces.Dict({cam: image for cam in self.cameras}),
                "agent_pos": spaces.Box(-1000.0, 1000.0, shape=(len(JOINTS),), dtype=np.float64),
            }
        )

    @property
    def task_description(self) -> str:
        """The recorded datasets' task string. LeRobot's eval loop asks every env for one; in a batch of
        subprocess envs a missing attribute shuts the workers down."""
        return TASK_STRINGS[self.task]

    def reset(self, seed: int | None = None, options: dict | None = None):
        self.image_perturbation.reset(seed)  # before the first frame is rendered; unseeded: fresh entropy
        return super().reset(seed=seed, options=options)

    def _make_env_task(self, task_name: str):
        return make_joint_env(task_name, self.cameras, self.observation_height, self.observation_width, self.shadows)

    def _format_raw_obs(self, raw_obs: dict) -> dict:
        return {
            "pixels": {cam: self.image_perturbation(raw_obs["images"][cam].copy(), cam) for cam in self.cameras},
            "agent_pos": raw_obs["qpos"],
        }
