"""A user of a command line sees one line that says what is wrong and what to do, never a traceback: in this
project's commands and, for the plugin's own refusals, in LeRobot's."""

from __future__ import annotations

import math
import os
import shutil
import subprocess
from pathlib import Path

import pytest
import torch

from helpers import BIN, TRAIN_ARGS, make_batch, make_config, with_rate_statistics
from lerobot_vib.cli_errors import install, refusal_in
from lerobot_vib.configuration_vib import SafetyConfig, VIBConfigError
from lerobot_vib.modeling_vib import VIBPolicy
from lerobot_vib.safety import NothingSafeToHoldError
from tiny_dataset import write_tiny_dataset

# The tiny checkpoint's camera and size, as an aloha_fast env shows them.
ALOHA_48x64 = [
    "--env.type=aloha_fast",
    "--env.task=AlohaTransferCube-v0",
    "--env.observation_height=48",
    "--env.observation_width=64",
    "--env.episode_length=2",
    "--eval.n_episodes=1",
    "--eval.batch_size=1",
]


def refused(cmd: list[str], timeout: int = 600) -> str:
    """Run a command that must refuse: non-zero exit, no traceback; returns its last line."""
    env = {**os.environ, "MUJOCO_GL": "egl", "HF_HUB_OFFLINE": "1"}
    proc = subprocess.run([str(c) for c in cmd], capture_output=True, text=True, timeout=timeout, env=env)
    out = proc.stdout + proc.stderr
    assert proc.returncode != 0, out[-3000:]
    assert "Traceback" not in out, out[-3000:]
    return proc.stderr.strip().splitlines()[-1]


@pytest.fixture(scope="module")
def other_datasets(tmp_path_factory) -> dict[str, Path]:
    base = tmp_path_factory.mktemp("other")
    roots = {"wrist": base / "wrist", "large": base / "large"}
    write_tiny_dataset(roots["wrist"], repo_id="local/wrist", cameras={"wrist": (48, 64)}, n_episodes=1)
    write_tiny_dataset(roots["large"], repo_id="local/large", cameras={"top": (96, 128)}, n_episodes=1)
    return roots


@pytest.mark.parametrize(
    ("name", "message"),
    [
        ("wrist", r"no `observation.images.top`"),
        ("large", r"`observation.images.top` of 96x128 \(the policy was trained on 48x64\)"),
    ],
)
def test_calibrating_on_data_with_other_cameras_or_image_size_is_refused_by_name(
    name, message, other_datasets, tiny_checkpoint, tmp_path
):
    import re

    last = refused(
        [
            BIN / "lerobot-vib-calibrate",
            f"--policy.path={tiny_checkpoint}",
            f"--dataset.repo_id=local/{name}",
            f"--dataset.root={other_datasets[name]}",
            f"--output_dir={tmp_path / 'out'}",
        ]
    )
    assert re.search(message, last), last
    assert not (tmp_path / "out").exists()


def test_lerobot_train_refuses_a_home_pose_of_the_wrong_length_before_it_loads_the_dataset(tiny_dataset_root, tmp_path):
    env = {**os.environ, "HF_HUB_OFFLINE": "1"}
    proc = subprocess.run(
        [
            str(BIN / "lerobot-train"),
            *TRAIN_ARGS,
            "--policy.safety.home_pose=[0.0,0.0]",
            "--dataset.repo_id=local/tiny",
            f"--dataset.root={tiny_dataset_root}",
            "--steps=1",
            f"--output_dir={tmp_path / 'run'}",
        ],
        capture_output=True,
        text=True,
        timeout=300,
        env=env,
    )
    out = proc.stdout + proc.stderr
    assert proc.returncode != 0 and "Traceback" not in out, out[-3000:]
    assert "`safety.home_pose` has 2 values, the action of the dataset at --dataset.root=" in out
    assert "has 14" in out and "Creating dataset" not in out


@pytest.mark.parametrize("preset", ["vib_aloha_transfer_cube.json", "vib_arm_sim.json"])
def test_lerobot_train_refuses_a_preset_whose_env_acts_in_another_space_than_the_data(preset, tmp_path):
    """An ALOHA preset (14 values) on the arm's 7-D recording, or the arm's preset on 14-D data, would train to
    its end and leave a policy its own env cannot run: refused before the dataset is loaded."""
    action_dim = 7 if "aloha" in preset else 14
    root = tmp_path / "data"
    write_tiny_dataset(root, state_dim=action_dim, action_dim=action_dim, n_episodes=1)
    last = refused(
        [
            BIN / "lerobot-train",
            f"--config_path={Path(__file__).parents[1] / 'configs' / 'policy' / preset}",
            "--dataset.repo_id=local/tiny",
            f"--dataset.root={root}",
            "--steps=1",
            f"--output_dir={tmp_path / 'run'}",
        ],
        timeout=300,
    )
    env_dim = 14 if "aloha" in preset else 7
    assert (
        f"acts with {env_dim} values, but the dataset at --dataset.root={root} records actions of {action_dim}" in last
    )
    assert not (tmp_path / "run").exists()


def test_lerobot_vib_eval_refuses_an_env_whose_images_differ_from_the_policys(tiny_checkpoint, tmp_path):
    last = refused(
        [
            BIN / "lerobot-vib-eval",
            f"--policy.path={tiny_checkpoint}",
            "--policy.device=cpu",
            *[a for a in ALOHA_48x64 if "observation_" not in a],  # gym-aloha's 480x640
            f"--output_dir={tmp_path / 'eval'}",
        ]
    )
    assert "images of 480x640 (the policy was trained on 48x64)" in last and "--env.dataset_root" in last


@pytest.mark.parametrize("command", ["lerobot-vib-eval", "lerobot-eval"])
def test_a_truncated_weights_file_is_named_in_one_line(command, tiny_checkpoint, tmp_path):
    ckpt = tmp_path / "pretrained_model"
    shutil.copytree(tiny_checkpoint, ckpt)
    weights = ckpt / "model.safetensors"
    weights.write_bytes(weights.read_bytes()[: weights.stat().st_size // 2])
    last = refused(
        [BIN / command, f"--policy.path={ckpt}", "--policy.device=cpu", *ALOHA_48x64, f"--output_dir={tmp_path / 'e'}"]
    )
    assert last.startswith(f"{command}: Cannot read the weights in") and "damaged or only partly" in last


def test_weights_of_another_chunk_size_are_named_with_the_flag_to_drop(tiny_checkpoint, tmp_path):
    last = refused(
        [
            BIN / "lerobot-vib-eval",
            f"--policy.path={tiny_checkpoint}",
            "--policy.device=cpu",
            "--policy.chunk_size=16",
            *ALOHA_48x64,
            f"--output_dir={tmp_path / 'e'}",
        ]
    )
    assert "do not fit this configuration" in last and "chunk_size" in last and "drop it" in last


def test_a_stop_on_an_uncalibrated_checkpoint_is_refused_when_it_loads(tiny_checkpoint, tmp_path):
    """The default score needs lerobot-vib-calibrate; without it the stop used to fail at the first step."""
    from lerobot.configs.policies import PreTrainedConfig

    config = PreTrainedConfig.from_pretrained(tiny_checkpoint)
    config.safety.enabled, config.uncertainty_score = True, "low_image_rate"
    with pytest.raises(VIBConfigError, match=r"cannot act on u.*low_image_rate.*lerobot-vib-calibrate"):
        VIBPolicy.from_pretrained(tiny_checkpoint, config=config)
    config.safety.enabled = False
    VIBPolicy.from_pretrained(tiny_checkpoint, config=config)  # nothing acts on u: it loads
    last = refused(
        [
            BIN / "lerobot-vib-eval",
            f"--policy.path={tiny_checkpoint}",
            "--policy.device=cpu",
            "--policy.safety.enabled=true",
            "--policy.uncertainty_score=low_image_rate",
            *ALOHA_48x64,
            f"--output_dir={tmp_path / 'e'}",
        ]
    )
    assert "cannot act on u" in last


def test_a_resume_threshold_above_gamma_is_refused_by_the_config():
    with pytest.raises(VIBConfigError, match=r"`safety.resume_threshold` \(1.5\) must not exceed `safety.gamma`"):
        SafetyConfig(gamma=1.2, resume_threshold=1.5)
    config = make_config()
    config.calibration.gamma = 1.2
    config.safety.resume_threshold = 1.5
    with pytest.raises(VIBConfigError, match="must not exceed the calibrated gamma"):
        config.__post_init__()
    config.calibration.gamma_band = [1.3, 1.2]  # a band keeps the hysteresis below itself at every step
    config.__post_init__()


def test_a_resume_threshold_above_the_running_gamma_is_refused_when_the_checkpoint_loads(tmp_path):
    config = make_config()
    policy = with_rate_statistics(VIBPolicy(config))
    policy.save_pretrained(tmp_path)
    gamma = policy.stop_threshold(step=0)
    assert math.isfinite(gamma)
    loaded = VIBPolicy.config_class.from_pretrained(tmp_path)
    loaded.safety.enabled, loaded.safety.resume_threshold = True, gamma + 1.0
    with pytest.raises(VIBConfigError, match="must not exceed gamma"):
        VIBPolicy.from_pretrained(tmp_path, config=loaded)


@pytest.mark.parametrize("value", [float("nan"), float("inf")])
def test_a_non_finite_state_at_the_first_step_is_named_as_such(value):
    """It used to read "no measured pose", sending the user after a missing sensor instead of a bad reading."""
    policy = with_rate_statistics(VIBPolicy(make_config(cameras={"top": (3, 32, 32)}, state_dim=3)))
    obs = make_batch(policy.config, with_action=False)
    obs["observation.state"][0, 1] = value
    policy.reset()
    with pytest.raises(NothingSafeToHoldError, match=r"observation.state\) is not finite \(NaN or inf\) in env 0,"):
        policy.select_action(obs)
    try:
        policy.select_action(obs)
    except NothingSafeToHoldError as e:
        assert refusal_in(e) is e  # a command line shows it as one line


def test_only_this_plugins_refusals_become_one_line_and_only_in_lerobots_commands(capsys, monkeypatch):
    import sys

    assert refusal_in(RuntimeError("x")) is None
    try:
        try:
            raise VIBConfigError("the cause")
        except VIBConfigError as e:
            raise RuntimeError("wrapped") from e
    except RuntimeError as wrapped:
        assert str(refusal_in(wrapped)) == "the cause"
    calls = []
    monkeypatch.setattr(sys, "excepthook", lambda *a: calls.append(a))
    assert not install("python")  # a user's own script keeps Python's traceback
    assert install("/usr/bin/lerobot-eval")
    sys.excepthook(VIBConfigError, VIBConfigError("bad weights"), None)
    assert capsys.readouterr().err == "lerobot-eval: bad weights\n" and not calls
    sys.excepthook(KeyError, KeyError("other"), None)
    assert len(calls) == 1  # any other error reaches the previous hook unchanged
    assert not install("/usr/bin/lerobot-train")  # installed once


def test_a_policy_with_nan_free_inputs_still_acts(tmp_path):
    """The checks above are refusals of bad input only: a calibrated, clean policy loads and acts."""
    policy = with_rate_statistics(VIBPolicy(make_config()))
    policy.save_pretrained(tmp_path)
    loaded = VIBPolicy.from_pretrained(tmp_path)
    action = loaded.select_action(make_batch(loaded.config, with_action=False))
    assert torch.isfinite(action).all()
