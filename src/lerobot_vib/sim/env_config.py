"""`--env.type=aloha_fast`: LeRobot's ALOHA env config for `FastAlohaEnv`, and its gym registration.

Importing this module is cheap (no MuJoCo); the env itself loads on `gym.make`.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, fields
from pathlib import Path

import gymnasium as gym
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.envs.configs import AlohaEnv, EnvConfig
from lerobot.utils.constants import ACTION, OBS_IMAGES, OBS_STATE

from ..configuration_vib import VIBConfigError

GYM_NAMESPACE = "lerobot_vib"
GYM_TASKS = {"AlohaTransferCube-v0": "transfer_cube", "AlohaInsertion-v0": "insertion"}
# Written by `lerobot-vib-record-sim` beside LeRobot's metadata: the settings a recording was made with.
SIDECAR = "meta/scripted_recording.json"
# Cameras defined in gym-aloha's MJCF scene.
CAMERAS = ("top", "angle", "front_close", "left_pillar", "right_pillar", "left_wrist", "right_wrist")

for _gym_task, _task in GYM_TASKS.items():
    if f"{GYM_NAMESPACE}/{_gym_task}" not in gym.registry:
        gym.register(
            id=f"{GYM_NAMESPACE}/{_gym_task}",
            entry_point="lerobot_vib.sim.aloha_env:FastAlohaEnv",
            max_episode_steps=400,
            nondeterministic=True,  # as gym-aloha: rendering differs slightly between runs
            kwargs={"task": _task},
        )


@EnvConfig.register_subclass("aloha_fast")
@dataclass
class AlohaFastEnv(AlohaEnv):
    """gym-aloha's ALOHA tasks (`AlohaTransferCube-v0`, `AlohaInsertion-v0`) rendering only `cameras`, at
    `observation_height` x `observation_width` (gym-aloha renders three 480x640 cameras every step).

    Args:
        cameras: MuJoCo cameras returned as `observation.images.<camera>`: any of top, angle, front_close,
            left_pillar, right_pillar, left_wrist, right_wrist.
        shadows: Render shadows as gym-aloha does. `false` renders about 3x faster on a CPU, but the images
            then differ from gym-aloha's: use the same setting for recording and evaluation.
        dataset_root: The root of a dataset recorded by `lerobot-vib-record-sim`: its task, image size, cameras
            and shadow setting are used, so the env shows the policy what it was trained on. A flag that
            contradicts the recording is refused.
    """

    cameras: list[str] = field(default_factory=lambda: ["top"])
    shadows: bool = True
    dataset_root: str | None = None

    def __post_init__(self):
        if self.dataset_root is not None:
            self._use_recording(Path(self.dataset_root))
        if self.task not in GYM_TASKS:
            raise VIBConfigError(
                f"Unknown task {self.task!r} for env type aloha_fast; expected one of {list(GYM_TASKS)}."
            )
        if self.obs_type != "pixels_agent_pos":
            raise VIBConfigError(f"aloha_fast supports obs_type=pixels_agent_pos only, got {self.obs_type!r}.")
        unknown = [c for c in self.cameras if c not in CAMERAS]
        if unknown or not self.cameras:
            raise VIBConfigError(f"`cameras` must be a non-empty subset of {list(CAMERAS)}, got {self.cameras}.")
        self.features = {
            ACTION: PolicyFeature(type=FeatureType.ACTION, shape=(14,)),
            "agent_pos": PolicyFeature(type=FeatureType.STATE, shape=(14,)),
        }
        self.features_map = {ACTION: ACTION, "agent_pos": OBS_STATE}
        for cam in self.cameras:
            self.features[f"pixels/{cam}"] = PolicyFeature(
                type=FeatureType.VISUAL, shape=(self.observation_height, self.observation_width, 3)
            )
            self.features_map[f"pixels/{cam}"] = f"{OBS_IMAGES}.{cam}"

    def _use_recording(self, root: Path) -> None:
        sidecar = root / SIDECAR
        if not sidecar.is_file():
            raise VIBConfigError(
                f"--env.dataset_root={root}: no {SIDECAR} there, so this is not a dataset recorded by "
                "lerobot-vib-record-sim. Give the task, size, cameras and shadows as flags instead."
            )
        recorded = json.loads(sidecar.read_text())["settings"]
        tasks = {task: gym_task for gym_task, task in GYM_TASKS.items()}
        wanted = {
            "task": tasks[recorded["task"]],
            "observation_height": recorded["image_height"],
            "observation_width": recorded["image_width"],
            "cameras": list(recorded["cameras"]),
            "shadows": recorded["shadows"],
        }
        # A value other than the default was given on purpose: it must agree with the recording.
        defaults = {f.name: f.default_factory() if callable(f.default_factory) else f.default for f in fields(self)}
        for name, value in wanted.items():
            current = getattr(self, name)
            if current != defaults[name] and current != value:
                raise VIBConfigError(
                    f"--env.{name}={current} contradicts the recording at {root} ({name} = {value}): drop the "
                    "flag, or drop --env.dataset_root to evaluate under other settings."
                )
            setattr(self, name, value)

    @property
    def package_name(self) -> str:
        return __name__

    @property
    def gym_id(self) -> str:
        return f"{GYM_NAMESPACE}/{self.task}"

    @property
    def gym_kwargs(self) -> dict:
        return {
            **super().gym_kwargs,
            "observation_height": self.observation_height,
            "observation_width": self.observation_width,
            "cameras": list(self.cameras),
            "shadows": self.shadows,
        }
