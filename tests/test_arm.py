"""The simulated 6-DoF arm: scene, scripted grasp, env, perturbations, recording, LeRobot's train and eval."""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
from pathlib import Path

import mujoco
import numpy as np
import pytest
from lerobot.datasets.lerobot_dataset import LeRobotDataset

from helpers import BIN, TRAIN_ARGS, run
from lerobot_vib.configuration_vib import VIBConfigError
from lerobot_vib.sim.arm_env import EPISODE_LENGTH, WORKSPACES, ArmGraspEnv, block_pose
from lerobot_vib.sim.arm_scene import HOME, load_model
from lerobot_vib.sim.arm_scripted import ArmIK, grasp_rotation, plan_grasp
from lerobot_vib.sim.env_config import ArmGraspEnvConfig
from lerobot_vib.sim.perturbations import PerturbationConfig
from lerobot_vib.sim.recorder import RecordingError, RecordingLog, RecordingSettings, record_scripted_dataset
from lerobot_vib.sim.sim_tasks import get_task

SMALL = dict(image_height=48, image_width=64, cameras=["scene"], shadows=True, use_videos=True)


def _rollout(env: ArmGraspEnv, seed: int, actions: np.ndarray) -> bool:
    env.reset(seed=seed)
    return any(env.step(a)[2] for a in actions)


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_scripted_grasp_lifts_the_block(seed):
    assert get_task("grasp_block").scripted_actions(seed) is not None


def test_ik_reaches_targets_across_the_workspace():
    ik = ArmIK(load_model())
    for x, y, yaw in [(0.30, -0.14, 0.7), (0.48, 0.14, -0.7), (0.4, 0.0, 0.0)]:
        target = np.array([x, y, 0.03])
        q, err = ik.solve(target, grasp_rotation(yaw), HOME, iters=200)
        pos, rot = ik.forward(q)
        assert err < 1e-3
        np.testing.assert_allclose(pos, target, atol=1e-3)
        assert rot[:, 0] @ np.array([0, 0, -1.0]) > 0.999  # tool axis points down


def test_grasp_rotation_puts_the_fingers_across_block_faces():
    for yaw in (-0.7, 0.0, 0.3, 1.2):  # 1.2 rad is the same cube as 1.2 - pi/2
        finger_axis = grasp_rotation(yaw)[:, 1]
        face_normal = np.array([np.cos(yaw), np.sin(yaw), 0.0])
        assert abs(abs(finger_axis @ face_normal) - 0) < 1e-9 or abs(abs(finger_axis @ face_normal) - 1) < 1e-9


def test_the_start_state_does_not_reveal_the_block():
    """Vision is needed: every episode starts in the same joint state, and seed 0's grasp misses seed 1's block."""
    env = ArmGraspEnv(cameras=())
    starts = [env.reset(seed=s)[0]["agent_pos"] for s in (0, 1)]
    np.testing.assert_array_equal(starts[0], starts[1])
    assert np.linalg.norm(block_pose(0)[0] - block_pose(1)[0]) > 0.05
    actions_0 = get_task("grasp_block").scripted_actions(0)
    assert _rollout(env, 0, actions_0)
    assert not _rollout(env, 1, actions_0)


def test_the_workspace_bounds_the_blocks_placement_and_near_lies_inside_wide():
    for name, ranges in WORKSPACES.items():
        poses = np.array([[*xy, yaw] for xy, yaw in (block_pose(seed, name) for seed in range(300))])
        for column, (low, high) in enumerate((ranges.x, ranges.y, ranges.yaw)):
            assert low <= poses[:, column].min() and poses[:, column].max() <= high
            assert poses[:, column].max() - poses[:, column].min() > 0.9 * (high - low)  # the whole range is used
    near, wide = WORKSPACES["near"], WORKSPACES["wide"]
    for inner, outer in ((near.x, wide.x), (near.y, wide.y), (near.yaw, wide.yaw)):
        assert outer[0] < inner[0] < inner[1] < outer[1]


@pytest.mark.parametrize("workspace", list(WORKSPACES))
def test_env_places_the_block_where_its_workspace_says(workspace):
    env = ArmGraspEnv(cameras=(), workspace=workspace)
    env.reset(seed=5)
    np.testing.assert_allclose(env.data.qpos[env._block_qadr : env._block_qadr + 2], block_pose(5, workspace)[0])
    assert get_task("grasp_block").scripted_actions(5, workspace) is not None


def test_an_unknown_workspace_is_refused_by_name():
    with pytest.raises(ValueError, match="Unknown arm workspace 'far'"):
        ArmGraspEnv(cameras=(), workspace="far")
    with pytest.raises(ValueError, match="Unknown workspace 'far' for grasp_block"):
        RecordingSettings(task="grasp_block", workspace="far", **SMALL)
    with pytest.raises(ValueError, match="Unknown workspace 'near' for transfer_cube; it offers none"):
        RecordingSettings(task="transfer_cube", workspace="near", **SMALL)
    with pytest.raises(VIBConfigError, match="Unknown arm workspace 'far'"):
        ArmGraspEnvConfig(workspace="far")


def test_env_resets_reproducibly_from_the_seed():
    env = ArmGraspEnv(observation_height=48, observation_width=64)
    a = env.reset(seed=7)[0]["pixels"]["scene"]
    b = env.reset(seed=7)[0]["pixels"]["scene"]
    c = env.reset(seed=8)[0]["pixels"]["scene"]
    np.testing.assert_array_equal(a, b)
    assert np.abs(a.astype(int) - c).sum() > 0
    env.close()


@pytest.mark.parametrize("action", [np.zeros(6), np.full(7, np.nan)])
def test_env_refuses_a_malformed_action(action):
    env = ArmGraspEnv(cameras=())
    env.reset(seed=0)
    with pytest.raises(ValueError, match="7 finite action values"):
        env.step(action)


def test_plan_ends_in_a_hold_above_the_table():
    env = ArmGraspEnv(cameras=())
    env.reset(seed=3)
    xy, yaw = block_pose(3)
    plan = plan_grasp(env.model, np.array([*xy, env.block_half]), yaw, EPISODE_LENGTH, env.block_half)
    assert plan.actions.shape == (EPISODE_LENGTH, 7) and plan.max_ik_error < 1e-3
    assert plan.actions[0, 6] == 1.0 and plan.actions[-1, 6] == 0.0  # open at the start, closed at the end


# --- perturbations ---------------------------------------------------------------------------------------


def _frames(
    perturbation: PerturbationConfig, seed: int = 4, steps: int = 0, camera: str = "scene", **kw
) -> list[np.ndarray]:
    env = ArmGraspEnv(observation_height=48, observation_width=64, perturbation=perturbation, cameras=(camera,), **kw)
    frames = [env.reset(seed=seed)[0]["pixels"][camera]]
    for _ in range(steps):
        frames.append(env.step(np.append(HOME, 1.0))[0]["pixels"][camera])
    env.close()
    return frames


def test_gaussian_noise_has_the_drawn_std_and_repeats_with_the_seed():
    clean = _frames(PerturbationConfig())[0] / 255.0
    noisy = _frames(PerturbationConfig(noise_std=[0.05]))[0] / 255.0
    again = _frames(PerturbationConfig(noise_std=[0.05]))[0] / 255.0
    np.testing.assert_array_equal(noisy, again)
    # clipping at 0 and 1 shrinks the spread a little
    assert 0.04 < np.std(noisy - clean) < 0.055


def test_black_images_are_black():
    assert not _frames(PerturbationConfig(black_images=True))[0].any()


def test_a_dim_camera_scales_every_pixel():
    clean = _frames(PerturbationConfig())[0].astype(float)
    dim = _frames(PerturbationConfig(dim=0.45))[0].astype(float)
    np.testing.assert_allclose(dim, np.round(clean * 0.45), atol=1)


def test_a_frozen_camera_repeats_its_frame_while_the_arm_moves():
    def moving(perturbation):
        env = ArmGraspEnv(observation_height=48, observation_width=64, perturbation=perturbation)
        frames = [env.reset(seed=4)[0]["pixels"]["scene"]]
        for t in range(6):
            frames.append(env.step(np.append(HOME + 0.05 * (t + 1), 1.0))[0]["pixels"]["scene"])
        env.close()
        return frames

    clean, frozen = moving(PerturbationConfig()), moving(PerturbationConfig(frozen_from=3))
    for t in range(4):
        np.testing.assert_array_equal(frozen[t], clean[t])
    assert not np.array_equal(clean[3], clean[6])  # the arm moved in the scene camera's view
    for t in range(4, 7):
        np.testing.assert_array_equal(frozen[t], clean[3])


def test_color_jitter_changes_colours_only_for_jittered_episodes():
    clean = _frames(PerturbationConfig())[0]
    jittered = _frames(PerturbationConfig(color_jitter=0.2, color_jitter_p=1.0))[0]
    never = _frames(PerturbationConfig(color_jitter=0.2, color_jitter_p=0.0))[0]
    np.testing.assert_array_equal(clean, never)
    assert np.abs(clean.astype(int) - jittered).mean() > 1


def test_occluder_is_in_view_exactly_on_its_steps():
    clean = _frames(PerturbationConfig(), steps=6)
    occluded = _frames(PerturbationConfig(occlusion=True, occlusion_start=2, occlusion_duration=3), steps=6)
    diffs = [np.abs(a.astype(int) - b).mean() for a, b in zip(clean, occluded, strict=True)]
    assert [d > 5 for d in diffs] == [False, False, True, True, True, False, False]


def _red_pixels(image: np.ndarray) -> int:
    r, g, b = image.astype(int).transpose(2, 0, 1)
    return int(((r > 120) & (g < 60) & (b < 60)).sum())


@pytest.mark.parametrize("camera", ["scene", "overhead"])
def test_the_occluder_hides_the_block_from_the_fixed_camera_observed(camera):
    occlusion = PerturbationConfig(occlusion=True, occlusion_start=0, occlusion_duration=5)
    assert _red_pixels(_frames(PerturbationConfig(), camera=camera)[0]) > 3
    assert _red_pixels(_frames(occlusion, camera=camera)[0]) == 0


def _block_pixel(env: ArmGraspEnv, x: float, y: float, camera: str) -> np.ndarray:
    """Where the block's red pixels are centred in `camera` with the block placed at (x, y), yaw 0."""
    q = env._block_qadr
    env.data.qpos[q : q + 7] = [x, y, env.block_half, 1, 0, 0, 0]
    mujoco.mj_forward(env.model, env.data)
    r, g, b = env._observation()["pixels"][camera].astype(int).transpose(2, 0, 1)
    rows, cols = np.nonzero((r > 120) & (g < 60) & (b < 60))
    return np.array([rows.mean(), cols.mean()])


def test_the_overhead_camera_resolves_the_blocks_distance_from_the_arm_better_than_the_scene_camera():
    """The grasps that miss close the fingers off the block along x, the scene camera's depth axis."""
    env = ArmGraspEnv(cameras=("scene", "overhead"), workspace="near")
    env.reset(seed=0)
    shift = {}
    for camera in ("scene", "overhead"):
        centre = _block_pixel(env, 0.39, 0.0, camera)
        shift[camera] = [
            np.linalg.norm(_block_pixel(env, 0.39 + dx, dy, camera) - centre) for dx, dy in ((0.05, 0), (0, 0.05))
        ]
    env.close()
    assert shift["overhead"][0] > 1.4 * shift["scene"][0]  # along x, towards and away from the arm
    assert shift["overhead"][1] > shift["scene"][1]  # along y, across


def test_unseen_block_is_not_the_red_training_block():
    assert _red_pixels(_frames(PerturbationConfig())[0]) > 3
    assert _red_pixels(_frames(PerturbationConfig(unseen_block=True))[0]) == 0


@pytest.mark.parametrize("camera", ["scene", "overhead"])
def test_camera_shake_moves_the_view(camera):
    clean = _frames(PerturbationConfig(), camera=camera)[0].astype(int)
    assert np.abs(clean - _frames(PerturbationConfig(camera_shake=0.02), camera=camera)[0]).mean() > 0.5


def test_aloha_env_takes_image_perturbations_and_refuses_scene_ones():
    from lerobot_vib.sim.aloha_env import FastAlohaEnv
    from lerobot_vib.sim.env_config import AlohaFastEnv

    env = FastAlohaEnv("transfer_cube", observation_height=48, observation_width=64, shadows=False)
    noisy = FastAlohaEnv(
        "transfer_cube", observation_height=48, observation_width=64, shadows=False,
        perturbation={"noise_std": [0.1]},
    )  # fmt: skip
    clean = env.reset(seed=0)[0]["pixels"]["top"] / 255.0
    assert 0.07 < np.std(noisy.reset(seed=0)[0]["pixels"]["top"] / 255.0 - clean) < 0.11
    with pytest.raises(VIBConfigError, match="simulated arm"):
        AlohaFastEnv(perturbation=PerturbationConfig(occlusion=True))


def test_perturbation_config_refuses_bad_values():
    bad_values = (dict(noise_std=[]), dict(noise_std=[-0.1]), dict(color_jitter=0.9), dict(occlusion_duration=0),
                  dict(dim=0.0), dict(dim=1.5), dict(frozen_from=-1))  # fmt: skip
    for bad in bad_values:
        with pytest.raises(ValueError):
            PerturbationConfig(**bad)


# --- recording, LeRobot's train and eval ------------------------------------------------------------------


@pytest.fixture(scope="module")
def arm_recording(tmp_path_factory):
    root = tmp_path_factory.mktemp("arm") / "grasp"
    record_scripted_dataset(root, "local/arm", RecordingSettings(task="grasp_block", **SMALL), 2, progress=False)
    return root


def test_recorded_arm_episode_has_seven_joint_values_and_replays_to_success(arm_recording):
    ds = LeRobotDataset("local/arm", root=arm_recording)
    assert ds.fps == 20 and ds.num_episodes == 2 and ds.num_frames == 2 * EPISODE_LENGTH
    assert ds.meta.robot_type == "vib_sim_arm"
    assert tuple(ds.meta.features["observation.state"]["shape"]) == (7,)
    assert ds.meta.features["action"]["names"][-1] == "gripper"
    assert ds[0]["task"] == "Pick up the block."
    seed = json.loads((arm_recording / "meta/scripted_recording.json").read_text())["episode_seeds"][0]
    actions = ds.hf_dataset.with_format("numpy")["action"][:EPISODE_LENGTH]
    assert _rollout(ArmGraspEnv(cameras=()), seed, actions)


def test_env_config_takes_the_recordings_settings(arm_recording):
    cfg = ArmGraspEnvConfig(dataset_root=str(arm_recording))
    assert (cfg.observation_height, cfg.observation_width, cfg.cameras) == (48, 64, ["scene"])
    assert tuple(cfg.features["agent_pos"].shape) == (7,)
    with pytest.raises(VIBConfigError, match="observation_height=120 contradicts"):
        ArmGraspEnvConfig(dataset_root=str(arm_recording), observation_height=120)
    assert cfg.workspace == "wide" and cfg.gym_kwargs["workspace"] == "wide"
    with pytest.raises(VIBConfigError, match="workspace=near contradicts"):
        ArmGraspEnvConfig(dataset_root=str(arm_recording), workspace="near")


def test_an_arm_recording_from_before_workspaces_is_read_as_wide(arm_recording, tmp_path):
    """Its blocks were placed in the wide ranges, the only ones there were."""
    sidecar = json.loads((arm_recording / "meta/scripted_recording.json").read_text())
    del sidecar["settings"]["workspace"]
    (tmp_path / "meta").mkdir()
    (tmp_path / "meta/scripted_recording.json").write_text(json.dumps(sidecar))
    assert RecordingLog.load(tmp_path).settings.workspace == "wide"
    assert ArmGraspEnvConfig(dataset_root=str(tmp_path)).workspace == "wide"


def test_resuming_in_another_workspace_is_refused_and_changes_nothing(arm_recording):
    before = sorted((p.relative_to(arm_recording), p.stat().st_size) for p in arm_recording.rglob("*"))
    near = RecordingSettings(task="grasp_block", workspace="near", **SMALL)
    with pytest.raises(RecordingError, match="'workspace': 'wide'"):
        record_scripted_dataset(arm_recording, "local/arm", near, 3, resume=True, progress=False)
    assert sorted((p.relative_to(arm_recording), p.stat().st_size) for p in arm_recording.rglob("*")) == before


@pytest.fixture(scope="module")
def arm_checkpoint(arm_recording, tmp_path_factory):
    """A VIB checkpoint from one `lerobot-train` step on the arm recording."""
    out = tmp_path_factory.mktemp("arm_train") / "run"
    run(
        [
            str(BIN / "lerobot-train"),
            *TRAIN_ARGS,
            "--dataset.repo_id=local/arm",
            f"--dataset.root={arm_recording}",
            "--steps=1",
            "--save_freq=1",
            f"--output_dir={out}",
        ]
    )
    return out / "checkpoints" / "last" / "pretrained_model"


@pytest.mark.parametrize(
    "flags",
    [
        ["--env.perturbation.occlusion=true", "--eval.use_async_envs=false"],
        # LeRobot's default where there are several cores: it asks each subprocess env for `task`, which the
        # arm once lacked, and the workers died
        ["--eval.use_async_envs=true"],
    ],
)
def test_lerobot_eval_runs_on_the_arm(flags, arm_recording, arm_checkpoint, tmp_path):
    run(
        [
            str(BIN / "lerobot-eval"),
            f"--policy.path={arm_checkpoint}",
            "--policy.device=cpu",
            "--env.type=vib_arm",
            f"--env.dataset_root={arm_recording}",
            "--env.episode_length=4",
            "--eval.n_episodes=2",
            "--eval.batch_size=2",
            *flags,
            f"--output_dir={tmp_path / 'eval'}",
        ]
    )
    info = json.loads((tmp_path / "eval" / "eval_info.json").read_text())
    assert info["overall"]["n_episodes"] == 2


def test_lerobot_vib_eval_takes_the_training_recordings_settings_and_records_its_env(
    arm_recording, arm_checkpoint, tmp_path
):
    """Without --env.dataset_root the env once ran at its defaults (another workspace) without a word."""
    out = tmp_path / "eval"
    log = run(
        [
            str(BIN / "lerobot-vib-eval"),
            f"--policy.path={arm_checkpoint}",
            "--policy.device=cpu",
            "--env.type=vib_arm",
            "--env.episode_length=3",
            "--eval.n_episodes=1",
            "--eval.batch_size=1",
            f"--output_dir={out}",
        ]
    )
    assert "takes the settings of the policy's training recording" in log
    env = json.loads((out / "uncertainty_info.json").read_text())["env"]
    assert (env["observation_height"], env["observation_width"], env["cameras"]) == (48, 64, ["scene"])
    assert env["dataset_root"] == str(arm_recording) and env["episode_length"] == 3
    assert env["perturbation"]["occlusion"] is False
    # and beside the trace, the observation embedding at every step (an RND can be fitted on rollouts)
    from lerobot_vib.scripts.eval_uncertainty import read_embeddings

    assert [e.shape[0] for e in read_embeddings(out / "embeddings.safetensors", 1)] == [3]
    proc = subprocess.run(
        [str(BIN / "lerobot-vib-eval"), f"--policy.path={arm_checkpoint}", "--env.type=vib_arm",
         "--env.workspace=near", f"--output_dir={tmp_path / 'near'}"],
        capture_output=True, text=True, timeout=300, env={**os.environ, "HF_HUB_OFFLINE": "1"},
    )  # fmt: skip
    assert proc.returncode != 0 and "Traceback" not in proc.stderr, proc.stderr[-3000:]
    assert "workspace=near contradicts the recording" in proc.stderr.strip().splitlines()[-1]


def test_rollout_example_traces_the_arm_with_the_occluder_in_the_scene(arm_checkpoint, tmp_path):
    out = tmp_path / "trace"
    run(
        [
            sys.executable,
            str(Path(__file__).parents[1] / "examples" / "rollout_uncertainty.py"),
            "--task=grasp_block",
            f"--policy_path={arm_checkpoint}",
            "--steps=8",
            "--occlude=2:5",
            "--safety",
            "--gamma=1e6",
            f"--out={out}",
        ]
    )
    with open(out / "trace.csv") as f:
        rows = list(csv.DictReader(f))
    assert [r["occluded"] for r in rows] == ["False"] * 2 + ["True"] * 3 + ["False"] * 3
    summary = json.loads((out / "summary.json").read_text())
    assert summary["task"] == "grasp_block" and summary["occluded_steps"] == [2, 4] and summary["success"] is False


# --- the occlusion scenario (paper Fig. 3c) on a controlled score ------------------------------------------


def test_occluder_stops_the_arm_which_holds_until_u_falls_and_then_resumes():
    """The stop's plumbing on the arm: the score is the darkness of the image's centre, where the occluder
    appears (a trained policy's rate is what `examples/rollout_uncertainty.py --task=grasp_block` traces)."""
    import torch

    from helpers import make_config
    from lerobot_vib.modeling_vib import VIBPolicy

    cfg = make_config(cameras={"scene": (3, 48, 64)}, state_dim=7, action_dim=7, chunk_size=4, n_action_steps=4)
    cfg.safety.enabled, cfg.safety.gamma, cfg.safety.resume_steps = True, 1.0, 3
    cfg.calibration.rate_mean = 1.0  # u = rate
    stats = {"action": {"mean": torch.tensor([*HOME, 1.0]), "std": torch.full((7,), 0.02)}}
    policy = VIBPolicy(cfg, dataset_stats=stats).eval()
    encode = policy.observation_scores

    def darkness_score(batch, wanted=None):
        posterior, scores = encode(batch, wanted)
        centre = batch["observation.images.scene"][:, :, 12:36, 16:48].mean(dim=(1, 2, 3)) * 255
        return posterior, {**scores, "rate": torch.clamp((100 - centre) / 10, min=0)}

    policy.observation_scores = darkness_score
    env = ArmGraspEnv(
        observation_height=48, observation_width=64,
        perturbation=PerturbationConfig(occlusion=True, occlusion_start=5, occlusion_duration=6),
    )  # fmt: skip
    obs, _ = env.reset(seed=1)
    stopped, actions, joints = [], [], []
    for _ in range(16):
        batch = {
            "observation.images.scene": torch.from_numpy(obs["pixels"]["scene"]).permute(2, 0, 1)[None] / 255.0,
            "observation.state": torch.from_numpy(obs["agent_pos"]).float()[None],
        }
        with torch.inference_mode():
            action = policy.select_action(batch)[0]
        action = action * stats["action"]["std"] + stats["action"]["mean"]  # the postprocessor's unnormalization
        stopped.append(bool(policy.last_step.stopped))
        actions.append(action.numpy())
        obs = env.step(action.numpy())[0]
        joints.append(obs["agent_pos"])
    env.close()
    # occluded on steps 5-10; three calm steps (11, 12, 13) resume at 13
    assert stopped == [5 <= t <= 12 for t in range(16)]
    for t in range(5, 13):  # held: the command from just before the occluder came
        np.testing.assert_array_equal(actions[t], actions[4])
    assert np.abs(joints[12] - joints[11]).max() < 2e-3  # the arm stands still under the hold
