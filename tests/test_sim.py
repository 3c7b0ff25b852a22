"""Scripted ALOHA demonstrations, the dataset recorder and the selective-rendering env."""

from __future__ import annotations

import csv
import json
import subprocess
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from lerobot.datasets.lerobot_dataset import LeRobotDataset

from helpers import BIN, TRAIN_ARGS, run
from lerobot_vib.sim.aloha_env import FastAlohaEnv
from lerobot_vib.sim.recorder import SIDECAR, RecordingSettings, record_scripted_dataset
from lerobot_vib.sim.scripted import object_pose, script_episode
from lerobot_vib.sim.sim_tasks import replay_max_reward
from lerobot_vib.sim.tasks import TASK_STRINGS

SMALL = dict(image_height=48, image_width=64, cameras=["top"], shadows=False, use_videos=True)


@pytest.mark.parametrize("task", ["transfer_cube", "insertion"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_scripted_policy_succeeds_on_fixed_seeds(task, seed):
    episode = script_episode(task, seed)
    assert episode.joint_actions.shape == (400, 14)
    assert replay_max_reward(task, seed, episode.joint_actions) == 4


def test_waypoints_follow_the_object_pose():
    """Two seeds put the cube in different places; the right gripper goes to each one."""
    from lerobot_vib.sim.scripted import PLANNERS
    from lerobot_vib.sim.tasks import make_end_effector_env

    for seed in (0, 7):
        env = make_end_effector_env("transfer_cube")
        env.task.object_pose = object_pose("transfer_cube", seed)
        script = PLANNERS["transfer_cube"](env.reset().observation)
        grasp_xy = script(170)[8:10]  # right arm position while grasping
        np.testing.assert_allclose(grasp_xy, object_pose("transfer_cube", seed)[:2], atol=1e-9)


def test_fast_env_matches_gym_aloha_top_image_and_agent_pos():
    import gym_aloha  # noqa: F401

    seed = 3
    actions = script_episode("transfer_cube", seed).joint_actions[:4]
    reference = gym.make("gym_aloha/AlohaTransferCube-v0", obs_type="pixels_agent_pos").unwrapped
    fast = FastAlohaEnv("transfer_cube", cameras=["top"], observation_height=480, observation_width=640)
    ref_obs, _ = reference.reset(seed=seed)
    fast_obs, _ = fast.reset(seed=seed)
    for t in range(len(actions) + 1):
        assert fast_obs["pixels"]["top"].shape == ref_obs["pixels"]["top"].shape == (480, 640, 3)
        np.testing.assert_array_equal(fast_obs["agent_pos"], ref_obs["agent_pos"])
        diff = np.abs(fast_obs["pixels"]["top"].astype(int) - ref_obs["pixels"]["top"].astype(int))
        assert diff.mean() < 0.5, f"step {t}: mean abs pixel difference {diff.mean():.3f}"
        if t < len(actions):
            ref_obs, *_ = reference.step(actions[t])
            fast_obs, *_ = fast.step(actions[t])


def test_fast_env_renders_only_the_cameras_asked_for():
    env = FastAlohaEnv("insertion", cameras=["top", "left_wrist"], observation_height=24, observation_width=32)
    obs, _ = env.reset(seed=0)
    assert set(obs["pixels"]) == {"top", "left_wrist"}
    assert obs["pixels"]["left_wrist"].shape == (24, 32, 3) and obs["pixels"]["top"].dtype == np.uint8
    assert env.observation_space.contains(obs)
    with pytest.raises(ValueError, match="Unknown ALOHA camera"):
        FastAlohaEnv("insertion", cameras=["wrist"])


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> dict[str, Path]:
    """One episode per task at 48x64: transfer-cube through the CLI, insertion through the function."""
    base = tmp_path_factory.mktemp("sim")
    roots = {"transfer_cube": base / "transfer_cube", "insertion": base / "insertion"}
    run(
        [
            str(BIN / "lerobot-vib-record-sim"),
            "--task=transfer_cube",
            "--num_episodes=1",
            "--image_height=48",
            "--image_width=64",
            "--shadows=false",
            "--repo_id=local/tc",
            f"--root={roots['transfer_cube']}",
        ]
    )
    record_scripted_dataset(
        roots["insertion"], "local/ins", RecordingSettings(task="insertion", **SMALL), 1, progress=False
    )
    return roots


@pytest.mark.parametrize("task", ["transfer_cube", "insertion"])
def test_recorded_episode_loads_back_with_hub_compatible_features(recorded, task):
    ds = LeRobotDataset("local/x", root=recorded[task])
    assert ds.fps == 50 and ds.num_episodes == 1 and ds.num_frames == 400
    assert ds.meta.features["observation.images.top"]["dtype"] == "video"
    assert tuple(ds.meta.features["observation.images.top"]["shape"]) == (48, 64, 3)
    assert tuple(ds.meta.features["observation.state"]["shape"]) == (14,)
    assert tuple(ds.meta.features["action"]["shape"]) == (14,)
    frame = ds[10]
    assert frame["observation.images.top"].shape == (3, 48, 64)
    assert frame["task"] == TASK_STRINGS[task]


@pytest.mark.parametrize("task", ["transfer_cube", "insertion"])
def test_replaying_a_recorded_episode_in_gym_aloha_reproduces_its_success(recorded, task, monkeypatch):
    """gym-aloha's own env, reset from the episode's seed, given the dataset's actions.

    gym-aloha renders three 480x640 cameras per step (minutes per episode on a CPU); rendering never feeds
    back into the physics, so it is replaced by a blank image here. Observations are compared separately.
    """
    import gym_aloha  # noqa: F401
    from dm_control.mujoco import Physics

    monkeypatch.setattr(Physics, "render", lambda self, height=240, width=320, **kw: np.zeros((height, width, 3)))
    seed = json.loads((recorded[task] / SIDECAR).read_text())["episode_seeds"][0]
    ds = LeRobotDataset("local/x", root=recorded[task])
    actions = ds.hf_dataset.with_format("numpy")["action"]
    gym_id = {"transfer_cube": "gym_aloha/AlohaTransferCube-v0", "insertion": "gym_aloha/AlohaInsertion-v0"}[task]
    env = gym.make(gym_id, obs_type="pixels_agent_pos").unwrapped
    obs, _ = env.reset(seed=seed)
    np.testing.assert_allclose(obs["agent_pos"], ds[0]["observation.state"].numpy(), atol=1e-6)
    rewards = [env.step(a)[1] for a in actions]
    assert max(rewards) == 4


def test_lerobot_train_vib_runs_on_a_recorded_dataset(recorded, tmp_path):
    log = run(
        [
            str(BIN / "lerobot-train"),
            *TRAIN_ARGS,
            "--dataset.repo_id=local/tc",
            f"--dataset.root={recorded['transfer_cube']}",
            "--steps=2",
            "--save_freq=2",
            f"--output_dir={tmp_path / 'out'}",
        ]
    )
    assert "step:2" in log


@pytest.fixture(scope="module")
def recorded_checkpoint(recorded, tmp_path_factory) -> Path:
    """A VIB checkpoint from one lerobot-train step on the recorded transfer-cube episode."""
    out = tmp_path_factory.mktemp("train") / "run"
    run(
        [
            str(BIN / "lerobot-train"),
            *TRAIN_ARGS,
            "--dataset.repo_id=local/tc",
            f"--dataset.root={recorded['transfer_cube']}",
            "--steps=1",
            "--save_freq=1",
            f"--output_dir={out}",
        ]
    )
    return out / "checkpoints" / "last" / "pretrained_model"


def test_lerobot_eval_runs_on_the_fast_env_with_the_recordings_settings(recorded, recorded_checkpoint, tmp_path):
    """`--env.type=aloha_fast` is registered with LeRobot; `--env.dataset_root` supplies task, size, cameras and
    shadows, so the 48x64 policy is fed 48x64 images without a size flag."""
    run(
        [
            str(BIN / "lerobot-eval"),
            f"--policy.path={recorded_checkpoint}",
            "--policy.device=cpu",
            "--env.type=aloha_fast",
            f"--env.dataset_root={recorded['transfer_cube']}",
            "--env.episode_length=5",
            "--eval.n_episodes=1",
            "--eval.batch_size=1",
            # run-time options as overrides of the checkpoint's config
            "--policy.temporal_ensemble=uncertainty",
            "--policy.n_action_steps=1",
            "--policy.safety.enabled=true",
            f"--output_dir={tmp_path / 'eval'}",
        ]
    )
    assert json.loads((tmp_path / "eval" / "eval_info.json").read_text())["overall"]["n_episodes"] == 1


def test_env_dataset_root_refuses_a_contradicting_flag(recorded):
    from lerobot_vib.configuration_vib import VIBConfigError
    from lerobot_vib.sim.env_config import AlohaFastEnv

    env = AlohaFastEnv(dataset_root=str(recorded["insertion"]))
    assert (env.task, env.observation_height, env.observation_width, env.shadows) == (
        "AlohaInsertion-v0",
        48,
        64,
        False,
    )
    with pytest.raises(VIBConfigError, match="observation_width=160 contradicts"):
        AlohaFastEnv(dataset_root=str(recorded["insertion"]), observation_width=160)
    with pytest.raises(VIBConfigError, match="not a dataset recorded by lerobot-vib-record-sim"):
        AlohaFastEnv(dataset_root=str(recorded["insertion"] / "meta"))


def test_lerobot_vib_eval_reports_u_and_stops_per_episode(recorded, recorded_checkpoint, tmp_path):
    """LeRobot's eval with two envs per batch; three episodes kept of four run, each cut at its own end.

    gamma = 1e-6 makes every step a stop, so each episode's record must read: one stop, at step 0, held throughout.
    """
    out = tmp_path / "eval"
    run(
        [
            str(BIN / "lerobot-vib-eval"),
            f"--policy.path={recorded_checkpoint}",
            "--policy.device=cpu",
            "--policy.safety.enabled=true",
            "--policy.safety.gamma=1e-6",
            "--env.type=aloha_fast",
            f"--env.dataset_root={recorded['transfer_cube']}",
            "--env.episode_length=4",
            "--eval.n_episodes=3",
            "--eval.batch_size=2",
            "--seed=7",
            f"--output_dir={out}",
        ]
    )
    eval_info = json.loads((out / "eval_info.json").read_text())
    info = json.loads((out / "uncertainty_info.json").read_text())
    episodes = info["per_episode"]
    assert [e["seed"] for e in episodes] == [7, 8, 9]
    assert [e["success"] for e in episodes] == eval_info["per_task"][0]["metrics"]["successes"]
    assert info["safety_enabled"] and info["gamma"] == 1e-6
    for e in episodes:
        assert e["steps"] == 4 and e["stops"] == 1 and e["stop_steps"] == [0] and e["stopped_steps"] == 4
        assert 0 < e["u_mean"] <= e["u_max"]
    assert info["overall"]["episodes_with_stop"] == 3 and info["overall"]["stopped_step_fraction"] == 1.0
    trace = list(csv.DictReader((out / "uncertainty_trace.csv").open()))
    assert len(trace) == 12 and [int(r["episode"]) for r in trace[::4]] == [0, 1, 2]
    assert {float(r["threshold"]) for r in trace} == {1e-6}  # the threshold in force at every step
    assert info["env"]["type"] == "aloha_fast" and info["env"]["perturbation"]["noise_std"] == [0.0]
    assert sorted(p.name for p in (out / "pictures").iterdir()) == [f"episode_{i}.png" for i in range(3)]
    assert {"stop_value", "threshold", "u_rate"} <= set(trace[0]) and info["score_means"]["rate"] > 0
    for e in episodes:
        u = [float(r["u"]) for r in trace if int(r["episode"]) == e["episode_ix"]]
        assert np.isclose(np.mean(u), e["u_mean"], rtol=1e-4)


def test_recorder_refuses_to_overwrite(recorded):
    proc = subprocess.run(
        [
            str(BIN / "lerobot-vib-record-sim"),
            "--task=transfer_cube",
            "--num_episodes=1",
            f"--root={recorded['transfer_cube']}",
        ],
        capture_output=True,
        text=True,
    )
    assert proc.returncode != 0 and "--resume=true" in proc.stderr and "--overwrite=true" in proc.stderr
    assert LeRobotDataset("local/x", root=recorded["transfer_cube"]).num_episodes == 1


def test_resume_refuses_other_settings(recorded):
    other = RecordingSettings(task="transfer_cube", **{**SMALL, "image_height": 96})
    with pytest.raises(ValueError, match="Cannot resume"):
        record_scripted_dataset(recorded["transfer_cube"], "local/tc", other, 2, resume=True, progress=False)


def test_interrupted_recording_resumes_without_losing_episodes(tmp_path, monkeypatch):
    root = tmp_path / "ds"
    settings = RecordingSettings(task="transfer_cube", **{**SMALL, "use_videos": False})
    frames = 0
    original = LeRobotDataset.add_frame

    def interrupt_mid_second_episode(self, frame):
        nonlocal frames
        frames += 1
        if frames == 500:
            raise KeyboardInterrupt
        original(self, frame)

    monkeypatch.setattr(LeRobotDataset, "add_frame", interrupt_mid_second_episode)
    with pytest.raises(KeyboardInterrupt):
        record_scripted_dataset(root, "local/r", settings, 2, progress=False)
    monkeypatch.setattr(LeRobotDataset, "add_frame", original)
    assert LeRobotDataset("local/r", root=root).num_episodes == 1

    result = record_scripted_dataset(root, "local/r", settings, 2, resume=True, progress=False)
    ds = LeRobotDataset("local/r", root=root)
    assert ds.num_episodes == 2 and ds.num_frames == 800
    assert result.episode_seeds == sorted(set(result.episode_seeds)) and len(result.episode_seeds) == 2
