"""The README's "Use it with LeRobot" block runs as it is written, on a small recording with a few steps."""

from __future__ import annotations

import json
import os
import re
import subprocess
from pathlib import Path

import pytest

from helpers import BIN
from lerobot_vib.sim.recorder import RecordingSettings, record_scripted_dataset

ROOT = Path(__file__).parents[1]
# Each command of the block keeps its flags; these are appended to make it small (bash functions that wrap
# the real command, so the block's text runs unchanged).
SMALL = {
    "lerobot-train": "--steps=2 --save_freq=2 --batch_size=2 --num_workers=0 --log_freq=1",
    "lerobot-vib-calibrate": "--rnd_steps=20",
    "lerobot-vib-eval": "--env.episode_length=4",
    "lerobot-eval": "--env.episode_length=4",
}


def readme_block(heading: str) -> str:
    text = (ROOT / "README.md").read_text()
    section = text[text.index(heading) :]
    return re.search(r"```bash\n(.*?)```", section, re.S).group(1)


@pytest.mark.slow
def test_the_use_it_with_lerobot_block_runs_as_pasted(tmp_path):
    work = tmp_path / "work"
    (work / "outputs" / "demo").mkdir(parents=True)
    (work / "configs").symlink_to(ROOT / "configs")
    settings = RecordingSettings(
        task="grasp_block", image_height=48, image_width=64, cameras=["scene"], shadows=False, use_videos=False,
        workspace="near",
    )  # fmt: skip
    record_scripted_dataset(
        work / "outputs/demo/data", "local/vib_arm_grasp_block_scripted", settings, 2, progress=False
    )
    wrappers = "\n".join(f'{name}() {{ command {name} "$@" {flags}; }}' for name, flags in SMALL.items())
    script = f"set -euo pipefail\npip() {{ :; }}\n{wrappers}\n{readme_block('## Use it with LeRobot')}"
    env = {**os.environ, "PATH": f"{BIN}:{os.environ['PATH']}", "MUJOCO_GL": "egl", "HF_HUB_OFFLINE": "1"}
    proc = subprocess.run(["bash", "-c", script], cwd=work, capture_output=True, text=True, env=env, timeout=1500)
    assert proc.returncode == 0, (proc.stdout + proc.stderr)[-6000:]
    calibrated = work / "outputs/vib/checkpoints/last/pretrained_model_calibrated"
    calibration = json.loads((calibrated / "config.json").read_text())["calibration"]
    assert calibration["gamma_method"] == "time_band_rollouts" and len(calibration["rollout_seeds"]) == 20
    env_record = json.loads((work / "outputs/eval/uncertainty_info.json").read_text())["env"]
    assert env_record["workspace"] == "near"  # lerobot-vib-eval took the recording's workspace by itself
    assert (work / "outputs/eval_stop/eval_info.json").is_file()
    assert "Safety stop on:" in proc.stderr  # the threshold in force, said once
