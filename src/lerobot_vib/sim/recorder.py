"""Record scripted demonstrations (ALOHA or the simulated arm) as a LeRobotDataset (v3, LeRobot's own writer).

Each episode: script it from the seed's object pose and check that it succeeds in a physics-only env (cheap),
then replay it in the rendering env and record (observation_t, action_t) for every step. Failed seeds are
skipped, so every saved episode is a success. ALOHA's features match the Hub's `lerobot/aloha_sim_*_scripted`
datasets: `observation.images.<camera>` (video), `observation.state` (14), `action` (14), fps 50, one task
string; the arm's are the same with 7 joint values at 20 fps (`sim_tasks.py`).

Seeds are consecutive from `seed`; `meta/scripted_recording.json` keeps the seed of every saved episode and
every failed attempt, so a run can be resumed (`resume=True`) without re-recording or losing episodes.
"""

from __future__ import annotations

import contextlib
import fnmatch
import json
import logging
import os
import shutil
import signal
import sys
import threading
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
from gymnasium import Env
from lerobot.datasets.lerobot_dataset import LeRobotDataset, LeRobotDatasetMetadata
from tqdm import tqdm

from .arm_env import LEGACY_WORKSPACE
from .env_config import SIDECAR
from .sim_tasks import get_task

logger = logging.getLogger(__name__)

# Where LeRobot writes under a dataset root, and the files it writes there (its v3 path templates). Only these
# are ever deleted or rewritten by the recorder; anything else a user puts there is kept and never checked.
DATASET_DIRS = ("data", "meta", "videos", "images")
EPISODE_FILES = (  # an episode's own files: what an unfinished one can have left
    "data/chunk-*/file-*.parquet",
    "meta/episodes/chunk-*/file-*.parquet",
    "videos/*/chunk-*/file-*.mp4",
    "images/*/episode-*/frame-*.png",
)
STAGED_FRAMES = EPISODE_FILES[-1]  # LeRobot's PNG frames of an episode, before they are encoded
RESTORED_FILES = ("meta/info.json", "meta/stats.json")  # rewritten by every save: restored, not size-checked
LEROBOT_FILES = (*EPISODE_FILES, *RESTORED_FILES, "meta/tasks.parquet")
# info.json keys that saving an episode changes; any other change is an edit made outside this command.
EPISODE_INFO_KEYS = ("total_episodes", "total_frames", "total_tasks", "splits")


class RecordingError(ValueError):
    """A refusal that names the problem; the command line prints it without a traceback."""


@dataclass
class RecordingSettings:
    """What must stay the same when a recording is resumed."""

    task: str
    image_height: int
    image_width: int
    cameras: list[str]
    shadows: bool
    use_videos: bool
    # The arm's block placement ranges (`arm_env.WORKSPACES`); None: the task's default (none for ALOHA).
    workspace: str | None = None

    def __post_init__(self):
        self.workspace = get_task(self.task).check_workspace(self.workspace)


@dataclass
class RecordingLog:
    """The sidecar: seeds, and the dataset's state after the last saved episode (the commit point)."""

    settings: RecordingSettings
    episode_seeds: list[int] = field(default_factory=list)  # seed of saved episode i
    failed_seeds: list[int] = field(default_factory=list)
    # After the last saved episode: size of every file LeRobot had written, and info.json / stats.json.
    committed_files: dict[str, int] = field(default_factory=dict)
    committed_meta: dict[str, dict] = field(default_factory=dict)

    @property
    def next_seed(self) -> int | None:
        attempted = self.episode_seeds + self.failed_seeds
        return max(attempted) + 1 if attempted else None

    def save(self, root: Path) -> None:
        _durable_write(root / SIDECAR, json.dumps(asdict(self), indent=2))

    @classmethod
    def load(cls, root: Path) -> RecordingLog:
        data = json.loads((root / SIDECAR).read_text())
        data.pop("pending_seed", None)  # written by earlier versions
        settings = data.pop("settings")
        if get_task(settings["task"]).workspaces:  # an arm recording made before the workspace was a setting
            settings.setdefault("workspace", LEGACY_WORKSPACE)
        return cls(settings=RecordingSettings(**settings), **data)


def _durable_write(path: Path, text: str) -> None:
    """Atomic and on disk: an interruption or power loss leaves the old or the new file, never half of one."""
    tmp = path.with_suffix(path.suffix + ".tmp")
    with tmp.open("w") as f:
        f.write(text)
        f.flush()
        os.fsync(f.fileno())
    tmp.replace(path)
    _fsync_dir(path.parent)


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _matches(rel: str, patterns: tuple[str, ...]) -> bool:
    """Whether a relative path fits one of the patterns, segment by segment (a * never crosses a /)."""
    parts = rel.split("/")
    return any(len(parts) == len(p.split("/")) and all(map(fnmatch.fnmatchcase, parts, p.split("/"))) for p in patterns)


def _files_under(root: Path) -> dict[str, int]:
    """Relative path -> size of every file under LeRobot's folders of `root` (the sidecar excluded)."""
    files = {}
    for top in DATASET_DIRS:
        for path in (root / top).rglob("*") if (root / top).is_dir() else ():
            rel = path.relative_to(root).as_posix()
            if path.is_file() and not rel.startswith(SIDECAR):
                files[rel] = path.stat().st_size
    return files


def _dataset_files(root: Path) -> dict[str, int]:
    """Relative path -> size of every file LeRobot wrote under `root`."""
    return {rel: size for rel, size in _files_under(root).items() if _matches(rel, LEROBOT_FILES)}


def _foreign_files(root: Path, log: RecordingLog | None = None) -> list[str]:
    """Files in LeRobot's folders of `root` that LeRobot does not write (a user's notes, labels, ...), and with
    the recording's `log`, staged frames that belong to none of its episodes."""
    foreign = [rel for rel in _files_under(root) if not _matches(rel, LEROBOT_FILES)]
    if log is not None and (log.committed_files or not log.episode_seeds):
        foreign += _stray_frames(root, log)
    return sorted(foreign)


def _edited_json(root: Path, log: RecordingLog, rel: str, saving_changes: tuple[str, ...]) -> list[str]:
    """What changed in the JSON file `rel` since the last saved episode, other than the keys that saving an
    episode changes (`saving_changes`)."""
    saved = log.committed_meta.get(rel)
    path = root / rel
    if saved is None or not path.is_file():
        return []
    try:
        now = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        return [f"it is not valid JSON ({e})"]
    edits = [f"added `{k}`" for k in now if k not in saved and k not in saving_changes]
    edits += [f"removed `{k}`" for k in saved if k not in now and k not in saving_changes]
    edits += [f"changed `{k}`" for k in saved if k in now and now[k] != saved[k] and k not in saving_changes]
    return edits


def _edited_info(root: Path, log: RecordingLog) -> list[str]:
    """What changed in meta/info.json since the last saved episode, other than what saving an episode changes."""
    return _edited_json(root, log, "meta/info.json", EPISODE_INFO_KEYS)


def _edited_stats(root: Path, log: RecordingLog) -> list[str]:
    """What changed in meta/stats.json since the last saved episode, when no unfinished save explains it.

    Saving an episode rewrites every statistic, so a change is LeRobot's only if an episode's save began after
    the last commit (its files are there, uncommitted); otherwise someone edited the file."""
    return [] if _unfinished_save(root, log) else _edited_json(root, log, "meta/stats.json", ())


def _unfinished_save(root: Path, log: RecordingLog) -> bool:
    """Whether LeRobot began saving an episode after the last commit: its data or episode metadata is there."""
    saved_by_lerobot = ("data/chunk-*/file-*.parquet", "meta/episodes/chunk-*/file-*.parquet")
    return any(rel not in log.committed_files and _matches(rel, saved_by_lerobot) for rel in _dataset_files(root))


def _frame_episode(rel: str) -> int | None:
    """The episode index of a staged frame, images/<camera>/episode-<index>/frame-<k>.png (None otherwise)."""
    if not _matches(rel, (STAGED_FRAMES,)):
        return None
    try:
        return int(rel.split("/")[2].removeprefix("episode-"))
    except ValueError:
        return None


def _stray_frames(root: Path, log: RecordingLog) -> list[str]:
    """Staged frames that are neither saved nor the unfinished episode's (whose index is the next to save):
    not this recording's, so kept."""
    unfinished = len(log.episode_seeds)
    return sorted(
        rel
        for rel in _dataset_files(root)
        if rel not in log.committed_files and (episode := _frame_episode(rel)) is not None and episode != unfinished
    )


def _commit(root: Path, log: RecordingLog) -> None:
    """Make the closed dataset files durable, then record them as the state to return to."""
    _remove_empty_dirs(root)
    files = _dataset_files(root)
    for rel in files:
        if rel in RESTORED_FILES or log.committed_files.get(rel) != files[rel]:
            with (root / rel).open("rb") as f:
                os.fsync(f.fileno())
    for directory in {(root / rel).parent for rel in files}:
        _fsync_dir(directory)
    log.committed_files = {rel: size for rel, size in files.items() if rel not in RESTORED_FILES}
    log.committed_meta = {rel: json.loads((root / rel).read_text()) for rel in RESTORED_FILES if (root / rel).exists()}
    log.save(root)  # the commit point


def _adopt_uncommitted(root: Path, log: RecordingLog) -> None:
    """A dataset recorded before the commit record existed: take it as it is if it is complete, else refuse."""
    problem = None
    try:
        total = LeRobotDatasetMetadata("local/check", root=root).total_episodes
        for path in sorted((root / "data").rglob("*.parquet")):
            pq.read_metadata(path)  # an unclosed parquet file has no footer
        if total != len(log.episode_seeds):
            problem = f"it holds {total} episodes, its log lists {len(log.episode_seeds)}"
    except Exception as e:
        problem = f"{type(e).__name__}: {e}"
    if problem:
        raise RecordingError(
            f"Cannot resume {root}: it was recorded by an earlier version of this command without a record of its "
            f"saved state, and is incomplete ({problem}). Record it again with `--overwrite=true`."
        )
    _commit(root, log)


def _rollback(root: Path, log: RecordingLog) -> list[str]:
    """Return the dataset to its state after the last saved episode: delete the files of an unfinished one,
    restore info.json and stats.json. Refuses, before touching anything, if a saved file changed or info.json
    or stats.json was edited. Files that LeRobot does not write, and staged frames of any other episode, are
    kept. Returns the deleted paths."""
    changed = [
        rel
        for rel, size in log.committed_files.items()
        if not (root / rel).is_file() or (root / rel).stat().st_size != size
    ]
    if changed:
        raise RecordingError(
            f"Cannot repair {root}: files of saved episodes are missing or changed since they were saved "
            f"({', '.join(changed[:5])}{' ...' if len(changed) > 5 else ''}). Record it again with `--overwrite=true`."
        )
    for name, edits in (("info.json", _edited_info(root, log)), ("stats.json", _edited_stats(root, log))):
        if edits:
            raise RecordingError(
                f"Cannot resume {root}: meta/{name} was edited since the last saved episode ({'; '.join(edits)}), "
                "and resuming restores it as it was then. Undo the edit (or keep an edited copy elsewhere) and "
                "resume again. Nothing was changed."
            )
    stray = set(_stray_frames(root, log))
    deleted = [
        rel
        for rel in _dataset_files(root)
        if rel not in log.committed_files
        and rel not in RESTORED_FILES
        and rel not in stray
        and _matches(rel, EPISODE_FILES)
    ]
    for rel in deleted:
        (root / rel).unlink()
    for rel, content in log.committed_meta.items():
        _durable_write(root / rel, json.dumps(content, indent=4))
    _remove_empty_dirs(root)
    return deleted


def _remove_empty_dirs(root: Path) -> None:
    """Empty folders that LeRobot's image staging or an unfinished episode left behind."""
    for top in DATASET_DIRS:
        for directory in sorted((root / top).rglob("*"), reverse=True) if (root / top).is_dir() else ():
            if directory.is_dir() and not any(directory.iterdir()):
                directory.rmdir()
        if (root / top).is_dir() and not any((root / top).iterdir()):
            (root / top).rmdir()


def dataset_features(settings: RecordingSettings) -> dict:
    task = get_task(settings.task)
    dtype = "video" if settings.use_videos else "image"
    features = {
        f"observation.images.{cam}": {
            "dtype": dtype,
            "shape": (settings.image_height, settings.image_width, 3),
            "names": ["height", "width", "channels"],
        }
        for cam in settings.cameras
    }
    names = list(task.state_names)
    features["observation.state"] = {"dtype": "float32", "shape": (len(names),), "names": names}
    features["action"] = {"dtype": "float32", "shape": (len(names),), "names": names}
    return features


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


class _DeferredInterrupt:
    """Ctrl-C as a KeyboardInterrupt raised at the recorder's next check (every frame and every episode).

    Raised wherever the signal lands, it can land in a finalizer (a closed dataset being collected), where
    Python prints "Exception ignored" and goes on: the recording would finish as if nothing had been asked.
    A second Ctrl-C interrupts at once.
    """

    def __init__(self) -> None:
        self.requested = False

    @contextlib.contextmanager
    def installed(self) -> Iterator[_DeferredInterrupt]:
        if threading.current_thread() is not threading.main_thread():
            yield self  # signal handlers live in the main thread; elsewhere Ctrl-C is not ours to handle
            return
        previous = signal.signal(signal.SIGINT, self._handle)
        try:
            yield self
        finally:
            signal.signal(signal.SIGINT, previous)

    def _handle(self, signum, frame) -> None:
        if self.requested:
            raise KeyboardInterrupt
        self.requested = True

    def check(self) -> None:
        if self.requested:
            raise KeyboardInterrupt


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

    Durability: every saved episode is written to files of its own, closed and synced to disk, before the
    sidecar records it (the commit point); `on_episode_saved(n_saved)` is called after that. An interruption
    (an exception here, or SIGKILL and power loss at the next `resume`) rolls the dataset back to the last
    saved episode: only the unfinished one is lost.

    `max_attempts` bounds the seeds tried in this call (default: 3 * episodes still missing + 10).
    """
    task = get_task(settings.task)
    task.check_cameras(settings.cameras)
    if max_attempts is not None and max_attempts < 1:
        raise ValueError(f"`max_attempts` must be >= 1 (seeds to try in this run), got {max_attempts}.")
    if overwrite and resume:
        raise ValueError("Choose one of `overwrite` (start over) and `resume` (add to the dataset).")
    root = Path(root)
    ours = (root / SIDECAR).is_file()
    if root.exists() and not ours and any(root.iterdir()):
        what = "a LeRobot dataset not recorded by this command" if (root / "meta/info.json").exists() else "not empty"
        raise RecordingError(
            f"{root} is {what}; this command only writes into an empty folder or a dataset it recorded "
            "(`--overwrite` deletes only such datasets). Choose another `--root`."
        )
    foreign = sorted(p.name for p in root.iterdir() if p.name not in DATASET_DIRS) if ours else []
    foreign += _foreign_files(root, RecordingLog.load(root)) if ours else []
    if foreign and (overwrite or not _saved_episodes(root)):
        raise RecordingError(
            f"{root} holds files that are not part of the dataset ({', '.join(foreign[:8])}"
            f"{' ...' if len(foreign) > 8 else ''}); move them elsewhere before starting the dataset over. "
            "Nothing was deleted."
        )
    if ours and not (resume or overwrite):
        raise RecordingError(
            f"A dataset already exists at {root}. Pass `--resume=true` to add episodes to it or "
            "`--overwrite=true` to delete it and start over."
        )

    dataset = None
    if ours and resume:
        log = RecordingLog.load(root)
        if log.settings != settings:
            raise RecordingError(
                f"Cannot resume {root}: it was recorded with {asdict(log.settings)}, this run asks for "
                f"{asdict(settings)}."
            )
        if log.episode_seeds and not log.committed_files:
            _adopt_uncommitted(root, log)
        unfinished = len(log.episode_seeds)
        in_the_way = [rel for rel in _stray_frames(root, log) if unfinished < _frame_episode(rel) < num_episodes]
        if in_the_way:  # LeRobot stages that episode's frames there, then deletes the folder
            raise RecordingError(
                f"Cannot resume {root}: {', '.join(in_the_way[:5])}{' ...' if len(in_the_way) > 5 else ''} lie where "
                "this run will stage the frames of episodes it records, and would be overwritten. Move them "
                "elsewhere and resume again. Nothing was changed."
            )
        deleted = _rollback(root, log)
        if deleted:
            logger.info("Dropped the unfinished episode %d of an interrupted run (%d files).", unfinished, len(deleted))
        kept = _foreign_files(root, log)
        if kept:
            logger.info("Kept %d files that are not part of the saved dataset: %s", len(kept), ", ".join(kept[:8]))
        if not log.episode_seeds:
            _delete_dataset(root)
    else:
        if ours:
            _delete_dataset(root)
        log = RecordingLog(settings=settings)

    missing = num_episodes - len(log.episode_seeds)
    next_seed = log.next_seed if log.next_seed is not None else seed
    max_attempts = 3 * max(missing, 0) + 10 if max_attempts is None else max_attempts
    env = task.make_env(
        settings.cameras, settings.image_height, settings.image_width, settings.shadows, settings.workspace
    )
    bar = tqdm(total=num_episodes, initial=len(log.episode_seeds), desc=f"{settings.task}", disable=not progress)
    attempts = 0
    interrupt = _DeferredInterrupt()
    try:
        with interrupt.installed():
            while len(log.episode_seeds) < num_episodes:
                interrupt.check()
                if attempts >= max_attempts:
                    raise RuntimeError(
                        f"Only {len(log.episode_seeds)}/{num_episodes} successful episodes after {attempts} attempts "
                        f"in this run (seeds up to {next_seed - 1}); raise `max_attempts` to keep trying."
                    )
                attempts += 1
                actions = task.scripted_actions(next_seed, settings.workspace)
                if actions is None:
                    log.failed_seeds.append(next_seed)
                else:
                    if dataset is None:
                        dataset = _open_for_writing(root, repo_id, settings, new=not log.episode_seeds)
                    _record_episode(dataset, env, settings, next_seed, actions, interrupt.check)
                    dataset.save_episode()
                    dataset.finalize()  # closes LeRobot's parquet writers: the episode's files are complete
                    dataset = None  # the next episode reopens the dataset and so writes files of its own
                    log.episode_seeds.append(next_seed)
                    _commit(root, log)
                    # stderr is line-buffered: a line reporting an episode saved is out before anything can kill us
                    bar.write(f"saved episode {len(log.episode_seeds) - 1} (seed {next_seed})", file=sys.stderr)
                    bar.update(1)
                    if on_episode_saved is not None:
                        on_episode_saved(len(log.episode_seeds))
                if (root / SIDECAR).parent.is_dir():
                    log.save(root)
                next_seed += 1
                bar.set_postfix(success=f"{len(log.episode_seeds)}/{len(log.episode_seeds) + len(log.failed_seeds)}")
    except BaseException:
        # Whatever stopped the run, leave the dataset as it was after its last saved episode.
        if dataset is not None:
            with contextlib.suppress(Exception):
                dataset.clear_episode_buffer()
                dataset.finalize()
        if (root / SIDECAR).is_file():
            if log.episode_seeds:
                try:
                    _rollback(root, log)
                except RecordingError as e:  # the next resume refuses with the same message
                    logger.warning("%s", e)
            else:
                _delete_dataset(root)
        raise
    finally:
        bar.close()
        env.close()
    return RecordingResult(root, len(log.episode_seeds), log.episode_seeds, log.failed_seeds)


def _open_for_writing(root: Path, repo_id: str, settings: RecordingSettings, new: bool) -> LeRobotDataset:
    if not new:
        return LeRobotDataset.resume(repo_id, root=root)
    if root.exists():
        root.rmdir()  # empty (checked above); LeRobot creates the folder itself
    task = get_task(settings.task)
    dataset = LeRobotDataset.create(
        repo_id=repo_id,
        fps=task.fps,
        features=dataset_features(settings),
        root=root,
        robot_type=task.robot_type,
        use_videos=settings.use_videos,
    )
    RecordingLog(settings=settings).save(root)  # marks the folder as this command's from its first file on
    return dataset


def _saved_episodes(root: Path) -> int:
    return len(RecordingLog.load(root).episode_seeds)


def _delete_dataset(root: Path) -> None:
    """Delete a dataset this command recorded: LeRobot's folders only, then `root` if nothing else is left."""
    for top in DATASET_DIRS:
        if (root / top).is_dir():
            shutil.rmtree(root / top)
    if root.is_dir() and not any(root.iterdir()):
        root.rmdir()


def _record_episode(
    dataset: LeRobotDataset,
    env: Env,
    settings: RecordingSettings,
    seed: int,
    actions: np.ndarray,
    check_interrupt: Callable[[], None],
) -> None:
    task_string = get_task(settings.task).task_string
    obs, _ = env.reset(seed=seed)
    for action in actions:
        check_interrupt()
        frame = {f"observation.images.{cam}": obs["pixels"][cam] for cam in settings.cameras}
        frame["observation.state"] = obs["agent_pos"].astype(np.float32)
        frame["action"] = action.astype(np.float32)
        frame["task"] = task_string
        dataset.add_frame(frame)
        obs, *_ = env.step(action)
