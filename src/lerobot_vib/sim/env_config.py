"""`--env.type=aloha_fast` and `--env.type=vib_arm`: LeRobot env configs for `FastAlohaEnv` and
`ArmGraspEnv`, and their gym registrations.

The envs themselves are built on `gym.make`.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

import gymnasium as gym
from lerobot.configs import parser
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.envs.configs import AlohaEnv, EnvConfig
from lerobot.utils.constants import ACTION, OBS_IMAGES, OBS_STATE

from ..configuration_vib import VIBConfigError, cli_dataset_action_dim
from .arm_env import DEFAULT_WORKSPACE as ARM_DEFAULT_WORKSPACE
from .arm_env import LEGACY_WORKSPACE as ARM_LEGACY_WORKSPACE
from .arm_env import WORKSPACES as ARM_WORKSPACES
from .arm_scene import CAMERAS as ARM_CAMERAS
from .perturbations import PerturbationConfig

GYM_NAMESPACE = "lerobot_vib"
GYM_TASKS = {"AlohaTransferCube-v0": "transfer_cube", "AlohaInsertion-v0": "insertion"}
ARM_GYM_TASK, ARM_TASK, ARM_STATE_SIZE = "ArmGrasp-v0", "grasp_block", 7
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
if f"{GYM_NAMESPACE}/{ARM_GYM_TASK}" not in gym.registry:
    gym.register(
        id=f"{GYM_NAMESPACE}/{ARM_GYM_TASK}",
        entry_point="lerobot_vib.sim.arm_env:ArmGraspEnv",
        max_episode_steps=100,
    )


def _recorded_settings(root: Path) -> dict:
    sidecar = root / SIDECAR
    if not sidecar.is_file():
        raise VIBConfigError(
            f"--env.dataset_root={root}: no {SIDECAR} there, so this is not a dataset recorded by "
            "lerobot-vib-record-sim. Give the task, size, cameras and shadows as flags instead."
        )
    return json.loads(sidecar.read_text())["settings"]


def _adopt(config: EnvConfig, root: Path, wanted: dict) -> None:
    """Set `wanted` on `config`; a flag given with a value other than its default must agree with it."""
    defaults = {f.name: f.default_factory() if callable(f.default_factory) else f.default for f in fields(config)}
    for name, value in wanted.items():
        current = getattr(config, name)
        if current != defaults[name] and current != value:
            raise VIBConfigError(
                f"--env.{name}={current} contradicts the recording at {root} ({name} = {value}): drop the "
                "flag, or drop --env.dataset_root to evaluate under other settings."
            )
        setattr(config, name, value)


class _RenderingEnv:
    """What both env types share: a gym id in this package's namespace, `pixels/<camera>` and `agent_pos`
    features, and the rendering options passed to the env."""

    def _set_features(self, state_size: int) -> None:
        self.features = {
            ACTION: PolicyFeature(type=FeatureType.ACTION, shape=(state_size,)),
            "agent_pos": PolicyFeature(type=FeatureType.STATE, shape=(state_size,)),
        }
        self.features_map = {ACTION: ACTION, "agent_pos": OBS_STATE}
        for cam in self.cameras:
            self.features[f"pixels/{cam}"] = PolicyFeature(
                type=FeatureType.VISUAL, shape=(self.observation_height, self.observation_width, 3)
            )
            self.features_map[f"pixels/{cam}"] = f"{OBS_IMAGES}.{cam}"
        # A training whose data acts in another space would run to its end and leave a policy this env cannot
        # evaluate (an ALOHA preset on the arm's 7-D recording); say so before it starts.
        recorded = cli_dataset_action_dim()
        if recorded is not None and recorded != state_size:
            raise VIBConfigError(
                f"--env.type={self.type} acts with {state_size} values, but the dataset at --dataset.root="
                f"{parser.parse_arg('dataset.root')} records actions of {recorded}: use the preset and env type "
                "made for that data (the arm's 7: configs/policy/vib_arm_sim.json with --env.type=vib_arm; "
                "ALOHA's 14: configs/policy/vib_aloha_transfer_cube.json with --env.type=aloha_fast)."
            )

    @property
    def package_name(self) -> str:
        return __name__

    @property
    def gym_id(self) -> str:
        return f"{GYM_NAMESPACE}/{self.task}"

    @property
    def gym_kwargs(self) -> dict:
        return {
            "obs_type": self.obs_type,
            "render_mode": self.render_mode,
            "max_episode_steps": self.episode_length,
            "observation_height": self.observation_height,
            "observation_width": self.observation_width,
            "cameras": list(self.cameras),
            "shadows": self.shadows,
            "perturbation": asdict(self.perturbation),
        }


@EnvConfig.register_subclass("aloha_fast")
@dataclass
class AlohaFastEnv(_RenderingEnv, AlohaEnv):
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
        perturbation: Image perturbations drawn per episode from its seed (`--env.perturbation.noise_std`,
            `--env.perturbation.color_jitter`, ...; see `PerturbationConfig`). The scene perturbations
            (camera shake, unseen block, occlusion) exist for the simulated arm only.
    """

    cameras: list[str] = field(default_factory=lambda: ["top"])
    shadows: bool = True
    dataset_root: str | None = None
    perturbation: PerturbationConfig = field(default_factory=PerturbationConfig)

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
        if self.perturbation.scene_perturbations:
            raise VIBConfigError(
                f"aloha_fast takes image perturbations only (noise_std, color_jitter); "
                f"{self.perturbation.scene_perturbations} need the simulated arm (--env.type=vib_arm)."
            )
        self._set_features(14)

    def _use_recording(self, root: Path) -> None:
        recorded = _recorded_settings(root)
        tasks = {task: gym_task for gym_task, task in GYM_TASKS.items()}
        if recorded["task"] not in tasks:
            raise VIBConfigError(f"{root} records {recorded['task']!r}, not an ALOHA task: use its env type.")
        wanted = {
            "task": tasks[recorded["task"]],
            "observation_height": recorded["image_height"],
            "observation_width": recorded["image_width"],
            "cameras": list(recorded["cameras"]),
            "shadows": recorded["shadows"],
        }
        _adopt(self, root, wanted)


@EnvConfig.register_subclass("vib_arm")
@dataclass
class ArmGraspEnvConfig(_RenderingEnv, EnvConfig):
    """The simulated 6-DoF arm with a parallel gripper picking up a block (`ArmGraspEnv`): 7 joint values
    (six joints and the gripper opening) as state and action, at 20 Hz, 100 steps an episode.

    Args:
        observation_height, observation_width: Camera image size.
        cameras: Any of `scene` (fixed, in front of the arm), `overhead` (fixed, above the table's front edge,
            looking down: the block's distance from the arm shows better than in `scene`) and `wrist`.
        shadows: Render shadows (cheap at this scene's size; `false` changes the images).
        workspace: The ranges the block is placed in per episode: `wide` (default) or `near` (`arm_env.WORKSPACES`).
        dataset_root: The root of a dataset recorded by `lerobot-vib-record-sim --task=grasp_block`: its image
            size, cameras, shadow setting and workspace are used. A flag that contradicts the recording is
            refused.
        perturbation: Perturbations drawn per episode from its seed: `noise_std`, `color_jitter`,
            `camera_shake`, `unseen_block`, `occlusion` (with `occlusion_start` / `occlusion_duration`).
    """

    task: str | None = ARM_GYM_TASK
    fps: int = 20
    episode_length: int = 100
    obs_type: str = "pixels_agent_pos"
    render_mode: str = "rgb_array"
    observation_height: int = 96
    observation_width: int = 128
    cameras: list[str] = field(default_factory=lambda: ["scene"])
    shadows: bool = True
    workspace: str = ARM_DEFAULT_WORKSPACE
    dataset_root: str | None = None
    perturbation: PerturbationConfig = field(default_factory=PerturbationConfig)

    def __post_init__(self):
        if self.dataset_root is not None:
            root = Path(self.dataset_root)
            recorded = _recorded_settings(root)
            if recorded["task"] != ARM_TASK:
                raise VIBConfigError(f"{root} records {recorded['task']!r}; --env.type=vib_arm needs {ARM_TASK!r}.")
            wanted = {
                "observation_height": recorded["image_height"],
                "observation_width": recorded["image_width"],
                "cameras": list(recorded["cameras"]),
                "shadows": recorded["shadows"],
                "workspace": recorded.get("workspace") or ARM_LEGACY_WORKSPACE,
            }
            _adopt(self, root, wanted)
        if self.workspace not in ARM_WORKSPACES:
            raise VIBConfigError(f"Unknown arm workspace {self.workspace!r}; expected one of {list(ARM_WORKSPACES)}.")
        if self.task != ARM_GYM_TASK:
            raise VIBConfigError(f"Unknown task {self.task!r} for env type vib_arm; expected {ARM_GYM_TASK!r}.")
        if self.obs_type != "pixels_agent_pos":
            raise VIBConfigError(f"vib_arm supports obs_type=pixels_agent_pos only, got {self.obs_type!r}.")
        if not self.cameras or any(c not in ARM_CAMERAS for c in self.cameras):
            raise VIBConfigError(f"`cameras` must be a non-empty subset of {list(ARM_CAMERAS)}, got {self.cameras}.")
        self._set_features(ARM_STATE_SIZE)

    @property
    def gym_kwargs(self) -> dict:
        return {**super().gym_kwargs, "workspace": self.workspace}
