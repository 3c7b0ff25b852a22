"""Record scripted ALOHA demonstrations as a LeRobotDataset (v3, LeRobot's own writer).

Each episode: script the end-effector task from the seed's object pose (`scripted.py`), check the joint
replay succeeds in a physics-only env (cheap), then replay it in `FastAlohaEnv` rendering the requested
cameras and record (observation_t, action_t) for t = 0..399. Failed seeds are skipped, so every saved
episode is a success. Features match the Hub's `lerobot/aloha_sim_*_scripted` datasets:
`observation.images.<camera>` (video), `observation.state` (14), `action` (14), fps 50, one task string.

Seeds are consecutive from `seed`; `meta/scripted_recording.json` keeps the seed of every saved episode and
every failed attempt, so a run can be resumed (`resume=True`) without re-recording or losing episodes.
"""

from __future__ import annotations

import json
import logging
import shutil
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from tqdm import tqdm

from .aloha_env import FastAlohaEnv
from .scripted import SUCCESS_REWARD, script_episode
from .tasks import check_cameras, check_task

logger = logging.getLogger(__name__)

FPS = 50
TASK_STRINGS = {  # the Hub datasets' task strings
    "transfer_cube": "Pick up the cube with the right arm and transfer it to the left arm.",
    "insertion": "Insert the peg into the socket.",
}
MOTOR_NAMES = [
    f"{side}_{joint}"
    for side in ("left", "right")
    for joint in ("waist", "shoulder", "elbow", "forearm_roll", "wrist_angle", "wrist_rotate", "gripper")
]
SIDECAR = "meta/scripted_recording.json"


@dataclass
class RecordingSettings:
    """What must stay the same when a recording is resumed."""

    task: str
    image_height: int
    image_width: int
    cameras: list[str]
    shadows: bool
    use_videos: bool


@dataclass
class RecordingLog:
    settings: RecordingSettings
    episode_seeds: list[int] = field(default_factory=list)  # seed of saved episode i
    failed_seeds: list[int] = field(default_factory=list)
    pending_seed: int | None = None  # being saved; counts as saved if the dataset has the episode

    @property
    def next_seed(self) -> int | None:
        attempted = self.episode_seeds + self.failed_seeds
        return max(attempted) + 1 if attempted else None

    def save(self, root: Path) -> None:
        path = root / SIDECAR
        tmp = path.with_suffix(".tmp")
        tmp.write_text(json.dumps(asdict(self), indent=2))
        tmp.replace(path)  # atomic: an interruption leaves the old or the new log, never half of one

    @classmethod
    def load(cls, root: Path) -> RecordingLog:
        data = json.loads((root / SIDECAR).read_text())
        return cls(settings=RecordingSettings(**data.pop("settings")), **data)


def aloha_features(settings: RecordingSettings) -> dict:
    dtype = "video" if settings.use_videos else "image"
    features = {
        f"observation.images.{cam}": {
            "dtype": dtype,
            "shape": (settings.image_height, settings.image_width, 3),
            "names": ["height", "width", "channels"],
        }
        for cam in settings.cameras
    }
    features["observation.state"] = {"dtype": "float32", "shape": (14,), "names": MOTOR_NAMES}
    features["action"] = {"dtype": "float32", "shape": (14,), "names": MOTOR_NAMES}
    return features


def replay_max_reward(task: str, seed: int, actions: np.ndarray) -> float:
    """Max reward of replaying `actions` from `reset(seed)` in the joint task, physics only."""
    env = FastAlohaEnv(task, cameras=())
    env.reset(seed=seed)
    best = 0.0
    for action in actions:
        _, reward, *_ = env.step(action)
        best = max(best, float(reward))
    return best


@dataclass
class RecordingResult:
    root: Path
    num_episodes: int
    episode_seeds: list[int]
    failed_seeds: list[int]

    @property
    def success_rate(self) -> float:
        attempts = len(self.episode_seeds) + len(self.failed_seeds)
        return len(self.episode_seeds) / attempts if attempts else float("nan")


def record_scripted_dataset(
    root: Path,
    repo_id: str,
    settings: RecordingSettings,
    num_episodes: int,
    seed: int = 0,
    max_attempts: int | None = None,
    overwrite: bool = False,
    resume: bool = False,
    progress: bool = True,
    on_episode_saved: Callable[[int], None] | None = None,
) -> RecordingResult:
    """Record until the dataset holds `num_episodes` successful episodes (in total, when resuming).

    `max_attempts` bounds the seeds tried in this call (default: 3 * episodes still missing + 10).
    `on_episode_saved(n_saved)` is called after each saved episode.
    """
    check_task(settings.task)
    check_cameras(settings.cameras)
    if not settings.cameras:
        raise ValueError("Record at least one camera.")
    if overwrite and resume:
        raise ValueError("Choose one of `overwrite` (start over) and `resume` (add to the dataset).")
    root = Path(root)
    exists = (root / "meta" / "info.json").exists()

    if exists and resume:
        dataset = LeRobotDataset.resume(repo_id, root=root)
        log = _reconcile(root, dataset.meta.total_episodes, settings)
    elif exists and not overwrite:
        raise FileExistsError(
            f"A dataset already exists at {root}. Pass `--resume=true` to add episodes to it or "
            "`--overwrite=true` to delete it and start over."
        )
    else:
        if root.exists():
            if not overwrite and any(root.iterdir()):
                raise FileExistsError(f"{root} exists and is not a dataset; pass `--overwrite=true` to replace it.")
            shutil.rmtree(root)
        dataset = LeRobotDataset.create(
            repo_id=repo_id,
            fps=FPS,
            features=aloha_features(settings),
            root=root,
            robot_type="aloha",
            use_videos=settings.use_videos,
            metadata_buffer_size=1,  # flush episode metadata at once: an interruption loses no saved episode
        )
        log = RecordingLog(settings=settings)
        log.save(root)

    missing = num_episodes - len(log.episode_seeds)
    next_seed = log.next_seed if log.next_seed is not None else seed
    max_attempts = 3 * max(missing, 0) + 10 if max_attempts is None else max_attempts
    env = FastAlohaEnv(
        settings.task,
        cameras=settings.cameras,
        observation_height=settings.image_height,
        observation_width=settings.image_width,
        shadows=settings.shadows,
    )
    bar = tqdm(total=num_episodes, initial=len(log.episode_seeds), desc=f"{settings.task}", disable=not progress)
    attempts = 0
    try:
        while len(log.episode_seeds) < num_episodes:
            if attempts >= max_attempts:
                raise RuntimeError(
                    f"Only {len(log.episode_seeds)}/{num_episodes} successful episodes after {attempts} attempts "
                    f"in this run (seeds up to {next_seed - 1}); raise `max_attempts` to keep trying."
                )
            attempts += 1
            episode = script_episode(settings.task, next_seed)
            if replay_max_reward(settings.task, next_seed, episode.joint_actions) < SUCCESS_REWARD:
                log.failed_seeds.append(next_seed)
            else:
                _record_episode(dataset, env, settings, next_seed, episode.joint_actions)
                log.pending_seed = next_seed
                log.save(root)
                dataset.save_episode()
                log.episode_seeds.append(next_seed)
                log.pending_seed = None
                bar.update(1)
                if on_episode_saved is not None:
                    on_episode_saved(len(log.episode_seeds))
            log.save(root)
            next_seed += 1
            bar.set_postfix(success=f"{len(log.episode_seeds)}/{len(log.episode_seeds) + len(log.failed_seeds)}")
    finally:
        bar.close()
        if dataset.has_pending_frames():
            dataset.clear_episode_buffer()
        dataset.finalize()
        env.close()
    return RecordingResult(root, len(log.episode_seeds), log.episode_seeds, log.failed_seeds)


def _record_episode(
    dataset: LeRobotDataset, env: FastAlohaEnv, settings: RecordingSettings, seed: int, actions: np.ndarray
) -> None:
    task_string = TASK_STRINGS[settings.task]
    obs, _ = env.reset(seed=seed)
    for action in actions:
        frame = {f"observation.images.{cam}": obs["pixels"][cam] for cam in settings.cameras}
        frame["observation.state"] = obs["agent_pos"].astype(np.float32)
        frame["action"] = action.astype(np.float32)
        frame["task"] = task_string
        dataset.add_frame(frame)
        obs, *_ = env.step(action)


def _reconcile(root: Path, saved_episodes: int, settings: RecordingSettings) -> RecordingLog:
    if not (root / SIDECAR).exists():
        raise FileNotFoundError(
            f"{root} has no {SIDECAR}: it was not recorded by this command and cannot be resumed by it."
        )
    log = RecordingLog.load(root)
    if log.settings != settings:
        raise ValueError(
            f"Cannot resume {root}: it was recorded with {asdict(log.settings)}, this run asks for {asdict(settings)}."
        )
    if log.pending_seed is not None and saved_episodes == len(log.episode_seeds) + 1:
        log.episode_seeds.append(log.pending_seed)  # interrupted right after LeRobot saved the episode
    log.pending_seed = None
    if saved_episodes != len(log.episode_seeds):
        raise RuntimeError(
            f"{root} holds {saved_episodes} episodes but its recording log lists {len(log.episode_seeds)}; "
            "record it again with `--overwrite=true`."
        )
    log.save(root)
    return log
