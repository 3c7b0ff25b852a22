"""Evaluation perturbations, drawn per episode from its seed so that every cell of a table can be rerun.

Image perturbations (any env that returns camera images, ALOHA included), applied to a uint8 frame x:

    Gaussian noise:  x' = clip(x / 255 + n, 0, 1) * 255,   n ~ N(0, sigma^2) per pixel and frame,
                     sigma drawn once per episode from `noise_std` (the paper's set is {0, 0.05, 0.1});
    colour jitter:   torchvision's ColorJitter(b, c, s, h) with every strength `color_jitter` (paper: 0.2),
                     applied with probability `color_jitter_p` (paper: 0.5), its factors drawn once per episode;
    black:           x' = 0 (a control: does the policy need vision at all?);
    dim:             x' = round(x * dim), dim < 1 (an under-exposed camera);
    frozen:          from frame `frozen_from` on, every frame repeats that one while the arm moves (a camera
                     driver that stopped delivering new images).

Scene perturbations (the simulated arm only, rendered by MuJoCo): camera shake (the scene camera's pose
jitters every step), an unseen block (another colour and size), and an occluder (a board between the camera
and the workspace) present from `occlusion_start` for `occlusion_duration` steps, each drawn per episode
when not given.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

# Salts keep each perturbation's random stream independent of the task's own use of the seed.
IMAGE_SALT, SCENE_SALT = 0x1A6E, 0x5CE9


@dataclass
class PerturbationConfig:
    """Args:
    noise_std: Standard deviations of Gaussian image noise (images in [0, 1]); one is drawn per episode.
        `[0.0]` is no noise; the paper's Gaussian condition is `[0.0, 0.05, 0.1]`.
    color_jitter: Brightness, contrast, saturation and hue strength of torchvision's ColorJitter; 0 is off.
        The paper's colour condition is 0.2.
    color_jitter_p: Probability that an episode is colour-jittered (when `color_jitter` > 0).
    black_images: Replace every camera image by a black one: a control showing whether a policy needs vision.
    dim: Multiply every camera image by this factor in (0, 1]; 1 is off. The `dim` condition is 0.45.
    frozen_from: From this frame of the episode on (0 is the reset's), each camera repeats that frame: the
        image stops changing while the arm moves. None is off; the `frozen` condition is 20.
    camera_shake: Fixed-camera shake amplitude: a uniform offset of up to this many metres along each axis
        and up to 10x this many radians about each axis, drawn every step for each fixed camera observed
        (`scene`, `overhead`). 0 is off. Simulated arm only.
    unseen_block: Replace the red 4 cm training block by one of another colour and size. Simulated arm only.
    occlusion: Put a board between the first fixed camera observed (`scene`, else `overhead`) and the
        workspace for part of the episode. Simulated arm only.
    occlusion_start: First occluded step; drawn from [10, 40) per episode when not given.
    occlusion_duration: Occluded steps; drawn from [15, 40) per episode when not given.
    """

    noise_std: list[float] = field(default_factory=lambda: [0.0])
    color_jitter: float = 0.0
    color_jitter_p: float = 0.5
    black_images: bool = False
    dim: float = 1.0
    frozen_from: int | None = None
    camera_shake: float = 0.0
    unseen_block: bool = False
    occlusion: bool = False
    occlusion_start: int | None = None
    occlusion_duration: int | None = None

    def __post_init__(self):
        if not self.noise_std or any(not np.isfinite(s) or s < 0 for s in self.noise_std):
            raise ValueError(f"`noise_std` must be a non-empty list of finite values >= 0, got {self.noise_std}.")
        if not 0 <= self.color_jitter <= 0.5:
            raise ValueError(f"`color_jitter` must be in [0, 0.5] (hue's limit), got {self.color_jitter}.")
        if not 0 <= self.color_jitter_p <= 1:
            raise ValueError(f"`color_jitter_p` must be a probability, got {self.color_jitter_p}.")
        if not 0 <= self.camera_shake <= 0.1:
            raise ValueError(f"`camera_shake` must be in [0, 0.1] metres, got {self.camera_shake}.")
        if not 0 < self.dim <= 1:
            raise ValueError(f"`dim` must be in (0, 1] (1 is off), got {self.dim}.")
        if self.frozen_from is not None and self.frozen_from < 0:
            raise ValueError(f"`frozen_from` must be a frame index >= 0 or None, got {self.frozen_from}.")
        for name in ("occlusion_start", "occlusion_duration"):
            value = getattr(self, name)
            if value is not None and (value < 0 or (name == "occlusion_duration" and value == 0)):
                raise ValueError(f"`{name}` must be {'>= 1' if name == 'occlusion_duration' else '>= 0'}, got {value}.")

    @property
    def scene_perturbations(self) -> list[str]:
        """Names of the perturbations that need a scene (not only images)."""
        return [
            name
            for name, on in (
                ("camera_shake", self.camera_shake > 0),
                ("unseen_block", self.unseen_block),
                ("occlusion", self.occlusion),
            )
            if on
        ]

    @property
    def is_clean(self) -> bool:
        images = max(self.noise_std) > 0 or self.color_jitter > 0 or self.black_images or self.dim < 1
        images = images or self.frozen_from is not None
        return not images and not self.scene_perturbations


class ImagePerturbation:
    """The image perturbations of one env; `reset(seed)` draws an episode's parameters. Each call is the
    next frame of the camera it names (frames are counted per camera from the reset, for `frozen_from`)."""

    def __init__(self, config: PerturbationConfig):
        self.config = config
        self.noise_std = 0.0
        self.jitter: tuple | None = None
        self.rng = np.random.default_rng()
        self._frames: dict[str, int] = {}
        self._frozen: dict[str, np.ndarray] = {}

    def reset(self, seed: int | None) -> None:
        self.rng = np.random.default_rng(None if seed is None else [seed, IMAGE_SALT])
        self._frames, self._frozen = {}, {}
        self.noise_std = float(self.rng.choice(self.config.noise_std))
        self.jitter = None
        strength = self.config.color_jitter
        if strength > 0 and self.rng.random() < self.config.color_jitter_p:
            from torchvision.transforms import ColorJitter  # not at import: env configs load with LeRobot's CLI

            with torch.random.fork_rng(devices=[]):
                torch.manual_seed(int(self.rng.integers(2**31)))
                self.jitter = ColorJitter.get_params(
                    (1 - strength, 1 + strength), (1 - strength, 1 + strength), (1 - strength, 1 + strength),
                    (-strength, strength),
                )  # fmt: skip

    @property
    def active(self) -> bool:
        return self.noise_std > 0 or self.jitter is not None

    def __call__(self, image: np.ndarray, camera: str = "") -> np.ndarray:
        """`image`: HxWx3 uint8, the next frame of `camera`. Returns a new HxWx3 uint8 array (the input is left
        as it is)."""
        frame = self._frames.get(camera, 0)
        self._frames[camera] = frame + 1
        frozen_from = self.config.frozen_from
        if frozen_from is not None and frame > frozen_from and camera in self._frozen:
            return self._frozen[camera].copy()
        out = self._perturbed(image)
        if frozen_from is not None and frame == frozen_from:
            self._frozen[camera] = out.copy()
        return out

    def _perturbed(self, image: np.ndarray) -> np.ndarray:
        if self.config.black_images:
            return np.zeros_like(image)
        out = image
        if self.config.dim < 1:
            out = (out.astype(np.float32) * self.config.dim).round().astype(np.uint8)
        if not self.active:
            return out
        if self.jitter is not None:
            from torchvision.transforms.v2 import functional as TF

            order, brightness, contrast, saturation, hue = self.jitter
            x = torch.from_numpy(np.ascontiguousarray(out)).permute(2, 0, 1)
            for i in order.tolist():  # torchvision's own random order of the four adjustments
                if i == 0:
                    x = TF.adjust_brightness(x, brightness)
                elif i == 1:
                    x = TF.adjust_contrast(x, contrast)
                elif i == 2:
                    x = TF.adjust_saturation(x, saturation)
                else:
                    x = TF.adjust_hue(x, hue)
            out = x.permute(1, 2, 0).numpy()
        if self.noise_std > 0:
            noisy = out / 255.0 + self.rng.normal(0.0, self.noise_std, size=out.shape)
            out = (np.clip(noisy, 0.0, 1.0) * 255.0).round().astype(np.uint8)
        return out


@dataclass
class SceneEpisode:
    """Scene perturbations of one episode of the simulated arm."""

    shake: float
    block_rgba: tuple[float, float, float, float] | None  # None: the training block
    block_half: float | None
    occluded_steps: range  # empty when not occluded
    rng: np.random.Generator

    def occluded(self, step: int) -> bool:
        return step in self.occluded_steps


UNSEEN_BLOCKS = (  # (rgba, half size): colours and sizes the training data never shows
    ((0.1, 0.3, 0.85, 1.0), 0.016),
    ((0.15, 0.7, 0.2, 1.0), 0.024),
    ((0.9, 0.8, 0.1, 1.0), 0.018),
)


# The paper's evaluation conditions at its strengths (Tables I, III, IV): what `lerobot-vib-benchmark` runs.
CONDITIONS: dict[str, PerturbationConfig] = {
    "normal": PerturbationConfig(),
    "gaussian": PerturbationConfig(noise_std=[0.0, 0.05, 0.1]),
    "color": PerturbationConfig(color_jitter=0.2, color_jitter_p=0.5),
    "camera_shake": PerturbationConfig(camera_shake=0.005),
    "unseen_block": PerturbationConfig(unseen_block=True),
    "occlusion": PerturbationConfig(occlusion=True),
    # Beyond the paper: a camera that shows nothing, too little light, or stopped delivering new frames.
    "black": PerturbationConfig(black_images=True),
    "dim": PerturbationConfig(dim=0.45),
    "frozen": PerturbationConfig(frozen_from=20),
}
SCENE_CONDITIONS = ("camera_shake", "unseen_block", "occlusion")  # these need the simulated arm


def draw_scene_episode(config: PerturbationConfig, seed: int | None) -> SceneEpisode:
    rng = np.random.default_rng(None if seed is None else [seed, SCENE_SALT])
    rgba = half = None
    if config.unseen_block:
        rgba, half = UNSEEN_BLOCKS[int(rng.integers(len(UNSEEN_BLOCKS)))]
    steps = range(0)
    if config.occlusion:
        start = config.occlusion_start if config.occlusion_start is not None else int(rng.integers(10, 40))
        length = config.occlusion_duration if config.occlusion_duration is not None else int(rng.integers(15, 40))
        steps = range(start, start + length)
    return SceneEpisode(config.camera_shake, rgba, half, steps, rng)
