"""Recordings survive SIGKILL and Ctrl-C; `--overwrite` deletes only datasets this command wrote.

Every kill below is a real SIGKILL of a real `lerobot-vib-record-sim` process, sent at a chosen point of
LeRobot's save sequence: while frames are buffered, after the data parquet is written (its writer still
open), after the episode metadata and info.json are written, and after the files are closed but before the
recorder's commit. After each, every episode the process reported as saved must load, frame for frame, and
resuming must finish the dataset with contiguous episode indices.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from lerobot.datasets.lerobot_dataset import LeRobotDataset

from helpers import BIN
from lerobot_vib.sim.recorder import SIDECAR, RecordingError, RecordingSettings, record_scripted_dataset

SETTINGS = RecordingSettings(
    task="transfer_cube", image_height=48, image_width=64, cameras=["top"], shadows=False, use_videos=True
)
CLI_ARGS = ["--task=transfer_cube", "--image_height=48", "--image_width=64", "--shadows=false", "--repo_id=local/k"]

# Runs the recorder's command line with one function patched to SIGKILL the process at its n-th call.
KILLER = """
import importlib, os, signal, sys
module_name, attr, n, when = sys.argv.pop(1).split(":")
owner_name, _, method = attr.rpartition(".")
module = importlib.import_module(module_name)
owner = getattr(module, owner_name) if owner_name else module
original = getattr(owner, method)
calls = 0
def patched(*args, **kwargs):
    global calls
    calls += 1
    if calls == int(n) and when == "before":
        os.kill(os.getpid(), signal.SIGKILL)
    out = original(*args, **kwargs)
    if calls == int(n) and when == "after":
        os.kill(os.getpid(), signal.SIGKILL)
    return out
setattr(owner, method, patched)
from lerobot_vib.scripts.record_sim import main
main()
"""

KILL_POINTS = {
    "while recording frames": "lerobot.datasets.lerobot_dataset:LeRobotDataset.add_frame:600:before",
    "after the data parquet": "lerobot.datasets.dataset_writer:DatasetWriter._save_episode_video:2:before",
    "after info.json and episode metadata": (
        "lerobot.datasets.dataset_metadata:LeRobotDatasetMetadata.save_episode:2:after"
    ),
    "after closing, before the commit": "lerobot_vib.sim.recorder:_commit:2:before",
}


def env() -> dict:
    return {**os.environ, "MUJOCO_GL": "egl", "HF_HUB_OFFLINE": "1"}


def record_cli(*args: str) -> subprocess.CompletedProcess:
    """`lerobot-vib-record-sim` with the test settings and `args`, its output captured."""
    cmd = [str(BIN / "lerobot-vib-record-sim"), *CLI_ARGS, *args]
    return subprocess.run(cmd, capture_output=True, text=True, env=env(), timeout=600)


def record_killed(root: Path, kill_point: str, num_episodes: int, tmp_path: Path, resume: bool = False) -> list[int]:
    """Run the recorder until the kill; return the episode indices it reported as saved."""
    script = tmp_path / "killer.py"
    script.write_text(KILLER)
    args = [*CLI_ARGS, f"--num_episodes={num_episodes}", f"--root={root}"] + (["--resume=true"] if resume else [])
    proc = subprocess.run(
        [sys.executable, str(script), kill_point, *args], capture_output=True, text=True, env=env(), timeout=600
    )
    assert proc.returncode == -signal.SIGKILL, proc.stderr[-3000:]
    return [int(i) for i in re.findall(r"saved episode (\d+)", proc.stderr)]


def episode_arrays(root: Path) -> dict[int, dict[str, np.ndarray]]:
    ds = LeRobotDataset("local/k", root=root)
    data = ds.hf_dataset.with_format("numpy")
    columns = {key: np.asarray(data[key]) for key in ("episode_index", "observation.state", "action", "frame_index")}
    out = {}
    for ep in np.unique(columns["episode_index"]):
        rows = columns["episode_index"] == ep
        out[int(ep)] = {
            "state": columns["observation.state"][rows],
            "action": columns["action"][rows],
            "frame_index": columns["frame_index"][rows],
            "image_0": ds[int(np.flatnonzero(rows)[0])]["observation.images.top"].numpy(),
            "image_last": ds[int(np.flatnonzero(rows)[-1])]["observation.images.top"].numpy(),
        }
    return out


def assert_same_episodes(before: dict, after: dict) -> None:
    for ep, arrays in before.items():
        for key, value in arrays.items():
            np.testing.assert_array_equal(after[ep][key], value, err_msg=f"episode {ep} {key}")


@pytest.mark.parametrize("point", list(KILL_POINTS))
def test_sigkill_loses_no_saved_episode(point, tmp_path):
    root = tmp_path / "ds"
    saved = record_killed(root, KILL_POINTS[point], num_episodes=3, tmp_path=tmp_path)
    assert saved == [0], f"the kill should come during episode 1, the process reported {saved}"

    # Resuming with nothing left to record repairs the dataset: the saved episode loads, the unfinished is gone.
    record_scripted_dataset(root, "local/k", SETTINGS, num_episodes=1, resume=True, progress=False)
    repaired = episode_arrays(root)
    assert sorted(repaired) == [0] and len(repaired[0]["state"]) == 400

    record_scripted_dataset(root, "local/k", SETTINGS, num_episodes=2, resume=True, progress=False)
    final = episode_arrays(root)
    assert sorted(final) == [0, 1] and all(len(a["state"]) == 400 for a in final.values())
    assert_same_episodes(repaired, final)
    np.testing.assert_array_equal(final[1]["frame_index"], np.arange(400))


def test_a_killed_resumed_recording_keeps_its_episodes(tmp_path):
    """Killed, resumed, killed again during the resume, resumed: every reported episode, indices contiguous."""
    root = tmp_path / "ds"
    point = KILL_POINTS["after info.json and episode metadata"]
    assert record_killed(root, point, num_episodes=4, tmp_path=tmp_path) == [0]
    # The second process saves episode 1 (the first save_episode of its own), then dies in episode 2's.
    assert record_killed(root, point, num_episodes=4, tmp_path=tmp_path, resume=True) == [1]
    record_scripted_dataset(root, "local/k", SETTINGS, num_episodes=2, resume=True, progress=False)  # repair only
    before = episode_arrays(root)
    assert sorted(before) == [0, 1]
    record_scripted_dataset(root, "local/k", SETTINGS, num_episodes=3, resume=True, progress=False)
    after = episode_arrays(root)
    assert sorted(after) == [0, 1, 2]
    assert_same_episodes(before, after)
    ds = LeRobotDataset("local/k", root=root)
    assert ds.meta.total_episodes == 3 and ds.num_frames == 1200


def test_ctrl_c_prints_the_resume_command_not_a_traceback(tmp_path):
    root = tmp_path / "ds"
    proc = subprocess.Popen(
        [str(BIN / "lerobot-vib-record-sim"), *CLI_ARGS, "--num_episodes=3", f"--root={root}"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env(),
    )
    deadline = time.monotonic() + 300
    while not (root / SIDECAR).is_file() or 'episode_seeds": [\n    0' not in (root / SIDECAR).read_text():
        assert time.monotonic() < deadline and proc.poll() is None, "no episode was saved"
        time.sleep(0.2)
    time.sleep(1.0)  # into episode 1
    proc.send_signal(signal.SIGINT)
    _, stderr = proc.communicate(timeout=120)
    assert proc.returncode != 0
    assert "Traceback" not in stderr, stderr[-3000:]
    last = stderr.strip().splitlines()[-1]
    assert last.startswith("Interrupted: 1 episodes are saved in") and "--resume=true" in last, last
    assert LeRobotDataset("local/k", root=root).num_episodes == 1


def test_overwrite_refuses_a_folder_it_did_not_write(tmp_path):
    root = tmp_path / "R"
    (root / "sub").mkdir(parents=True)
    (root / "notes.txt").write_text("x")
    proc = record_cli("--num_episodes=1", f"--root={root}", "--overwrite=true")
    assert proc.returncode != 0 and "Traceback" not in proc.stderr
    assert "not empty" in proc.stderr and "Choose another `--root`" in proc.stderr
    assert (root / "notes.txt").read_text() == "x" and (root / "sub").is_dir()


def test_overwrite_deletes_only_the_dataset(tmp_path):
    root = tmp_path / "R"
    record_scripted_dataset(root, "local/k", SETTINGS, num_episodes=1, progress=False)
    assert not (root / "images").exists(), "an empty staging folder was left in a video dataset"
    (root / "notes.txt").write_text("x")
    with pytest.raises(RecordingError, match=r"notes\.txt.*Nothing was deleted"):
        record_scripted_dataset(root, "local/k", SETTINGS, num_episodes=1, overwrite=True, progress=False)
    assert LeRobotDataset("local/k", root=root).num_episodes == 1

    (root / "notes.txt").unlink()
    record_scripted_dataset(root, "local/k", SETTINGS, num_episodes=1, overwrite=True, seed=5, progress=False)
    assert LeRobotDataset("local/k", root=root).num_episodes == 1


def test_overwrite_refuses_a_lerobot_dataset_of_another_origin(tmp_path, tiny_dataset_root):
    with pytest.raises(RecordingError, match="not recorded by this command"):
        record_scripted_dataset(tiny_dataset_root, "local/k", SETTINGS, num_episodes=1, overwrite=True, progress=False)
    assert LeRobotDataset("local/tiny", root=tiny_dataset_root).num_episodes == 2


def test_a_dataset_from_before_the_commit_record_resumes_without_losing_files(tmp_path):
    """Sidecars written by earlier versions have no commit record: the dataset is adopted, not rolled back."""
    import json

    root = tmp_path / "ds"
    record_scripted_dataset(root, "local/k", SETTINGS, num_episodes=1, progress=False)
    before = episode_arrays(root)
    log = json.loads((root / SIDECAR).read_text())
    for key in ("committed_files", "committed_meta"):
        del log[key]
    (root / SIDECAR).write_text(json.dumps({**log, "pending_seed": None}))

    record_scripted_dataset(root, "local/k", SETTINGS, num_episodes=2, resume=True, progress=False)
    after = episode_arrays(root)
    assert sorted(after) == [0, 1]
    assert_same_episodes(before, after)


def test_resume_keeps_files_it_did_not_write_and_drops_only_the_unfinished_episode(tmp_path):
    root = tmp_path / "ds"
    assert record_killed(root, KILL_POINTS["after the data parquet"], num_episodes=3, tmp_path=tmp_path) == [0]
    (root / "meta/README.md").write_text("# my notes")
    (root / "images").mkdir(exist_ok=True)
    (root / "images/labels.csv").write_text("frame,label\n0,grasp\n")
    proc = record_cli("--num_episodes=1", f"--root={root}", "--resume=true")
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "Dropped the unfinished episode" in proc.stderr  # logging reaches the user after a kill
    assert "Kept 2 files" in proc.stderr and "meta/README.md" in proc.stderr
    assert (root / "meta/README.md").read_text() == "# my notes"
    assert (root / "images/labels.csv").read_text() == "frame,label\n0,grasp\n"
    assert sorted(episode_arrays(root)) == [0]
    # They are the user's from now on: never deleted, never checked as episode files.
    (root / "meta/README.md").write_text("# my notes, longer now")
    record_scripted_dataset(root, "local/k", SETTINGS, num_episodes=2, resume=True, progress=False)
    assert sorted(episode_arrays(root)) == [0, 1] and (root / "images/labels.csv").is_file()
    with pytest.raises(RecordingError, match=r"meta/README\.md.*Nothing was deleted"):
        record_scripted_dataset(root, "local/k", SETTINGS, num_episodes=1, overwrite=True, progress=False)
    assert (root / "meta/README.md").is_file() and sorted(episode_arrays(root)) == [0, 1]


def test_an_edited_info_json_is_refused_by_name_not_rewritten(tmp_path):
    import json

    root = tmp_path / "ds"
    record_scripted_dataset(root, "local/k", SETTINGS, num_episodes=1, progress=False)
    info = json.loads((root / "meta/info.json").read_text())
    edited = {**info, "license": "cc-by-4.0", "fps": 25}
    (root / "meta/info.json").write_text(json.dumps(edited, indent=4))
    with pytest.raises(RecordingError, match=r"added `license`; changed `fps`.*Nothing was changed"):
        record_scripted_dataset(root, "local/k", SETTINGS, num_episodes=2, resume=True, progress=False)
    assert json.loads((root / "meta/info.json").read_text()) == edited


def test_an_edited_stats_json_is_refused_by_name_not_rewritten(tmp_path):
    import json

    root = tmp_path / "ds"
    record_scripted_dataset(root, "local/k", SETTINGS, num_episodes=1, progress=False)
    stats = json.loads((root / "meta/stats.json").read_text())
    stats["observation.state"]["std"] = [max(s, 0.5) for s in stats["observation.state"]["std"]]  # a floor
    (root / "meta/stats.json").write_text(json.dumps(stats, indent=4))
    with pytest.raises(RecordingError, match=r"meta/stats\.json was edited.*changed `observation\.state`.*Nothing"):
        record_scripted_dataset(root, "local/k", SETTINGS, num_episodes=2, resume=True, progress=False)
    assert json.loads((root / "meta/stats.json").read_text()) == stats


def _png(path: Path) -> Path:
    from PIL import Image

    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.full((4, 4, 3), 7, dtype=np.uint8)).save(path)
    return path


def test_resume_deletes_only_the_unfinished_episodes_frames_and_names_the_others(tmp_path, caplog):
    import logging

    root = tmp_path / "ds"
    record_scripted_dataset(root, "local/k", SETTINGS, num_episodes=1, progress=False)
    frames = root / "images" / "observation.images.top"
    unfinished = _png(frames / "episode-000001" / "frame-000000.png")  # as an interrupted episode 1 leaves it
    other = _png(frames / "episode-000000" / "frame-000003.png")  # an episode already saved: not ours to delete
    beyond = _png(frames / "episode-000007" / "frame-000000.png")  # an episode this run will not record
    with caplog.at_level(logging.INFO, logger="lerobot_vib"):
        record_scripted_dataset(root, "local/k", SETTINGS, num_episodes=2, resume=True, progress=False)
    assert not unfinished.exists() and other.is_file() and beyond.is_file()
    assert sorted(episode_arrays(root)) == [0, 1]
    assert "Dropped the unfinished episode 1 of an interrupted run (1 files)" in caplog.text
    assert "Kept 2 files" in caplog.text and "episode-000000/frame-000003.png" in caplog.text


def test_resume_with_nothing_interrupted_drops_nothing_and_says_nothing_of_it(tmp_path, caplog):
    import logging

    root = tmp_path / "ds"
    record_scripted_dataset(root, "local/k", SETTINGS, num_episodes=1, progress=False)
    other = _png(root / "images" / "observation.images.top" / "episode-000000" / "frame-000000.png")
    with caplog.at_level(logging.INFO, logger="lerobot_vib"):
        record_scripted_dataset(root, "local/k", SETTINGS, num_episodes=1, resume=True, progress=False)
    assert other.is_file() and "Dropped" not in caplog.text and "Kept 1 files" in caplog.text


def test_frames_where_this_run_will_stage_its_own_are_refused_and_nothing_changes(tmp_path):
    root = tmp_path / "ds"
    record_scripted_dataset(root, "local/k", SETTINGS, num_episodes=1, progress=False)
    in_the_way = _png(root / "images" / "observation.images.top" / "episode-000002" / "frame-000000.png")
    before = sorted((p.relative_to(root), p.stat().st_size) for p in root.rglob("*"))
    with pytest.raises(RecordingError, match=r"episode-000002/frame-000000\.png.*would be overwritten"):
        record_scripted_dataset(root, "local/k", SETTINGS, num_episodes=3, resume=True, progress=False)
    assert sorted((p.relative_to(root), p.stat().st_size) for p in root.rglob("*")) == before
    assert in_the_way.is_file()


@pytest.mark.parametrize(
    ("flag", "message"),
    [
        ("--task=bogus", "Unknown task 'bogus'"),
        ("--num_episodes=0", "`num_episodes` must be >= 1, got 0"),
        ("--image_height=0", "`image_height` and `image_width` must be >= 1"),
        ("--max_attempts=0", "`max_attempts` must be >= 1"),
        ("--max_attempts=-2", "`max_attempts` must be >= 1"),
        ("--cameras=[nocam]", "Cameras must be a non-empty subset of ['top', "),
        ("--cameras=[]", "got []"),
        ("--overwrite=true --resume=true", "Choose one of `--overwrite=true`"),
    ],
)
def test_bad_recording_arguments_end_with_the_cause(flag, message, tmp_path):
    proc = record_cli(f"--root={tmp_path / 'ds'}", *flag.split(" "))
    last = proc.stderr.strip().splitlines()[-1]
    assert proc.returncode != 0 and message in last and "Traceback" not in proc.stderr, proc.stderr[-2000:]
    assert not (tmp_path / "ds").exists()
    with pytest.raises(ValueError, match="max_attempts"):
        record_scripted_dataset(tmp_path / "ds", "local/k", SETTINGS, num_episodes=1, max_attempts=0, progress=False)


@pytest.mark.parametrize(
    ("root", "message"),
    [
        ("/proc/x/ds", "cannot create a folder in /proc"),
        ("{file}/ds", "which is a file: choose a folder"),
        ("{file}", "is a file, not a folder"),
    ],
)
def test_a_root_where_no_dataset_can_be_written_is_refused_in_one_line(root, message, tmp_path):
    """/proc/x once ended in a FileNotFoundError traceback, as if the folder were only missing."""
    file = tmp_path / "notes.txt"
    file.write_text("mine")
    proc = record_cli(f"--root={root.format(file=file)}", "--num_episodes=1")
    last = proc.stderr.strip().splitlines()[-1]
    assert proc.returncode != 0 and message in last and "Traceback" not in proc.stderr, proc.stderr[-2000:]
    assert file.read_text() == "mine"
