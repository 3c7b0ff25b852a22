"""`lerobot-vib-record-sim`: record scripted demonstrations (ALOHA, or the simulated arm) as a LeRobotDataset.

    lerobot-vib-record-sim --task=transfer_cube --num_episodes=50 --root=data/aloha_transfer_cube
    lerobot-vib-record-sim --task=insertion --num_episodes=50 --image_height=120 --image_width=160 \
        --root=data/aloha_insertion_120x160
    lerobot-vib-record-sim --task=grasp_block --root=data/arm_grasp_block   # 96x128, scene camera
    # add episodes to an interrupted or smaller recording:
    lerobot-vib-record-sim --task=insertion --num_episodes=100 --root=data/aloha_insertion_120x160 --resume=true
"""

import json
import logging
import os
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

from lerobot.configs import parser
from lerobot.utils.constants import HF_LEROBOT_HOME

from ..configuration_vib import VIBConfigError
from ..normalization import near_constant_vectors, warn_near_constant
from ..sim.recorder import SIDECAR, RecordingError, RecordingLog, RecordingSettings, record_scripted_dataset
from ..sim.sim_tasks import get_task


@dataclass
class RecordSimConfig:
    """Args:
    task: transfer_cube or insertion (ALOHA), or grasp_block (the simulated 6-DoF arm).
    num_episodes: Successful episodes the dataset should hold (in total, when resuming).
    repo_id: Dataset id written into the metadata (default local/aloha_sim_<task>_scripted for ALOHA,
        local/vib_arm_grasp_block_scripted for the arm).
    root: Where to write the dataset (default $HF_LEROBOT_HOME/<repo_id>).
    image_height, image_width: Camera resolution (default: gym-aloha's 480x640 for ALOHA, 96x128 for the arm).
    cameras: MuJoCo cameras to record, each as observation.images.<camera> (default: top for ALOHA, scene for
        the arm, which also has overhead and wrist).
    workspace: The arm only: the ranges the block is placed in, `wide` (default) or `near` (see
        `lerobot_vib.sim.arm_env`). `--env.dataset_root` makes `lerobot-eval` use the recording's.
    shadows: Render shadows as gym-aloha does; false is about 3x faster on a CPU but the images differ.
    use_videos: Store cameras as MP4 videos (as the Hub datasets) rather than PNG frames.
    seed: First seed; episode seeds are consecutive, failed ones skipped.
    max_attempts: Seeds tried at most in this run (default 3 x missing episodes + 10).
    overwrite: Delete an existing dataset at `root` and start over.
    resume: Add episodes to an existing dataset at `root` recorded by this command.
    push_to_hub: Push the finished dataset to the Hugging Face Hub under `repo_id`.
    """

    task: str = "transfer_cube"
    num_episodes: int = 50
    repo_id: str | None = None
    root: Path | None = None
    image_height: int | None = None
    image_width: int | None = None
    cameras: list[str] | None = None
    workspace: str | None = None
    shadows: bool = True
    use_videos: bool = True
    seed: int = 0
    max_attempts: int | None = None
    overwrite: bool = False
    resume: bool = False
    push_to_hub: bool = False

    def __post_init__(self):
        # draccus would replace a ValueError's text with "Couldn't instantiate class RecordSimConfig".
        try:
            self._check()
        except ValueError as e:
            raise VIBConfigError(str(e)) from None

    def _check(self) -> None:
        task = get_task(self.task)
        if self.repo_id is None:
            robot = "aloha_sim" if task.robot_type == "aloha" else "vib_arm"
            self.repo_id = f"local/{robot}_{self.task}_scripted"
        if self.image_height is None:
            self.image_height = task.default_size[0]
        if self.image_width is None:
            self.image_width = task.default_size[1]
        self.cameras = list(task.default_cameras if self.cameras is None else self.cameras)
        task.check_cameras(self.cameras)
        self.workspace = task.check_workspace(self.workspace)
        if self.root is None:
            self.root = HF_LEROBOT_HOME / self.repo_id
        if self.overwrite and self.resume:
            raise ValueError(
                "Choose one of `--overwrite=true` (delete the dataset and start over) and `--resume=true` (add "
                "episodes to it)."
            )
        _check_writable(Path(self.root))
        if self.num_episodes < 1:
            raise ValueError(f"`num_episodes` must be >= 1, got {self.num_episodes}.")
        if self.image_height < 1 or self.image_width < 1:
            raise ValueError(
                f"`image_height` and `image_width` must be >= 1, got {self.image_height}x{self.image_width}."
            )
        if self.max_attempts is not None and self.max_attempts < 1:
            raise ValueError(f"`max_attempts` must be >= 1 (seeds to try in this run), got {self.max_attempts}.")


def _check_writable(root: Path) -> None:
    """`root` must be a folder, or a path where one can be made: refused before any episode is recorded."""
    if root.exists():
        if not root.is_dir():
            raise ValueError(f"`--root={root}` is a file, not a folder: choose a folder for the dataset.")
        return
    parent = root.parent
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        raise ValueError(f"`--root={root}` lies under {parent}, which is a file: choose a folder for the dataset.")
    try:  # the only reliable test: make a folder there (and remove it)
        os.rmdir(tempfile.mkdtemp(prefix=".lerobot-vib-check-", dir=parent))
    except OSError as e:
        raise ValueError(
            f"`--root={root}`: cannot create a folder in {parent} ({e.strerror}); choose a writable location."
        ) from None


@parser.wrap()
def record_sim(cfg: RecordSimConfig) -> None:
    settings = RecordingSettings(
        task=cfg.task,
        image_height=cfg.image_height,
        image_width=cfg.image_width,
        cameras=list(cfg.cameras),
        shadows=cfg.shadows,
        use_videos=cfg.use_videos,
        workspace=cfg.workspace,
    )
    result = record_scripted_dataset(
        root=cfg.root,
        repo_id=cfg.repo_id,
        settings=settings,
        num_episodes=cfg.num_episodes,
        seed=cfg.seed,
        max_attempts=cfg.max_attempts,
        overwrite=cfg.overwrite,
        resume=cfg.resume,
    )
    attempts = len(result.episode_seeds) + len(result.failed_seeds)
    print(
        f"{result.root}: {result.num_episodes} episodes of {cfg.task}; scripted success "
        f"{len(result.episode_seeds)}/{attempts} seeds ({100 * result.success_rate:.0f}%), "
        f"failed seeds {result.failed_seeds}"
    )
    stats_file = Path(result.root) / "meta" / "stats.json"
    if stats_file.is_file():
        warn_near_constant(near_constant_vectors(json.loads(stats_file.read_text())), str(result.root))
    if cfg.push_to_hub:
        from lerobot.datasets.lerobot_dataset import LeRobotDataset

        LeRobotDataset(cfg.repo_id, root=cfg.root).push_to_hub()


def main() -> None:
    os.environ.setdefault("MUJOCO_GL", "egl")  # off-screen rendering; works on CPU-only machines (Mesa)
    os.environ.setdefault("SVT_LOG", "1")  # the AV1 encoder prints its whole configuration per episode
    import datasets

    datasets.disable_progress_bars()  # one progress bar per saved episode otherwise
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
    # An import may already have configured the root logger (at WARNING), making basicConfig a no-op: the
    # recorder's own messages (a dropped unfinished episode, kept files) must still reach the user.
    logging.getLogger("lerobot_vib").setLevel(logging.INFO)
    try:
        record_sim()
    except (RecordingError, VIBConfigError) as e:
        sys.exit(f"lerobot-vib-record-sim: {e}")
    except KeyboardInterrupt:
        sys.exit(_interrupted_message())


def _interrupted_message() -> str:
    """One line: what is saved and the command that continues (the recorder rolled back the unfinished episode)."""
    args = [a for a in sys.argv[1:] if not a.startswith(("--resume", "--overwrite"))]
    root = next((a.split("=", 1)[1] for a in args if a.startswith("--root=")), None)
    saved = ""
    if root and (Path(root) / SIDECAR).is_file():
        saved = f" {len(RecordingLog.load(Path(root)).episode_seeds)} episodes are saved in {root};"
    return f"Interrupted:{saved} continue with: lerobot-vib-record-sim {' '.join(args)} --resume=true"


if __name__ == "__main__":
    main()
