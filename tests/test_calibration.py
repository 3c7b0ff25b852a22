"""u = R / R_bar: running statistics from training, exact calibration over a dataset, and thresholds."""

import json
import math
import os

import numpy as np
import pytest
import torch
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot.utils.feature_utils import dataset_to_policy_features

from helpers import BIN, SMALL, make_batch, make_config, run
from lerobot_vib.calibration import RateTracker, conformal_gamma, mean_plus_2std_gamma
from lerobot_vib.configuration_vib import VIBConfig, VIBConfigError
from lerobot_vib.modeling_vib import VIBPolicy
from lerobot_vib.processor_vib import make_vib_pre_post_processors
from lerobot_vib.scripts.calibrate import calibrate


def test_running_statistics_are_debiased_moments():
    tracker = RateTracker(momentum=0.1)
    assert math.isnan(tracker.mean)
    tracker.update(torch.tensor([2.0, 4.0]))
    assert tracker.mean == pytest.approx(3.0) and tracker.std == pytest.approx(1.0)
    for _ in range(200):
        tracker.update(torch.tensor([5.0, 7.0]))
    assert tracker.mean == pytest.approx(6.0, abs=1e-6) and tracker.std == pytest.approx(1.0, abs=1e-5)
    tracker.update(torch.tensor([float("nan")]))  # ignored
    assert tracker.mean == pytest.approx(6.0, abs=1e-6)


def test_training_forward_updates_the_running_statistics_and_eval_does_not():
    policy = VIBPolicy(make_config())
    batch = make_batch(policy.config)
    policy.eval().forward(batch)
    assert policy.rate_tracker.n_updates == 0
    policy.train().forward(batch)
    assert policy.rate_tracker.n_updates == 1
    assert policy.rate_mean() == pytest.approx(float(policy.last_rate.mean()), rel=1e-6)
    state = policy.state_dict()
    assert {"rate_tracker.ema_mean", "rate_tracker.ema_sq", "rate_tracker.n_updates"} <= set(state)


def test_threshold_precedence_explicit_then_calibrated_then_running():
    policy = VIBPolicy(make_config())
    policy.rate_tracker.update(torch.tensor([1.0, 3.0]))
    assert policy.stop_threshold() == pytest.approx(mean_plus_2std_gamma(2.0, 1.0)) == pytest.approx(2.0)
    policy.config.calibration.rate_mean, policy.config.calibration.rate_std = 4.0, 1.0
    assert policy.rate_mean() == 4.0 and policy.stop_threshold() == pytest.approx(1.5)
    policy.config.calibration.gamma = 1.7
    assert policy.stop_threshold() == 1.7
    policy.config.safety.gamma = 3.0
    assert policy.stop_threshold() == 3.0


def test_conformal_gamma_is_the_right_order_statistic():
    scores = torch.tensor([0.3, 2.0, 1.1, 0.9, 1.5, 0.2, 1.8, 0.7, 1.2])  # n = 9
    ordered = sorted(scores.tolist())
    # alpha = 0.2: k = ceil(10 * 0.8) = 8 -> the 8th smallest
    assert conformal_gamma(scores, 0.2) == ordered[7]
    # alpha = 0.1: k = ceil(10 * 0.9) = 9 -> the largest
    assert conformal_gamma(scores, 0.1) == ordered[8]
    with pytest.raises(ValueError, match="at least 19 held-out episodes"):
        conformal_gamma(scores, 0.05)  # k = 10 > n
    with pytest.raises(ValueError, match="alpha"):
        conformal_gamma(scores, 1.5)


def test_conformal_gamma_bounds_the_false_stop_rate():
    """Exchangeable scores: P(new score > gamma) <= alpha, and not much below (1 - alpha + 1/(n+1) coverage)."""
    torch.manual_seed(0)
    n, alpha, trials = 19, 0.1, 4000
    scores = torch.distributions.Gamma(2.0, 1.0).sample((trials, n + 1))  # skewed, like a KL rate
    exceed = [float(s[n] > conformal_gamma(s[:n], alpha)) for s in scores]
    rate = sum(exceed) / trials
    assert rate <= alpha + 3 * math.sqrt(alpha * (1 - alpha) / trials)
    assert rate >= alpha - 1 / (n + 1) - 3 * math.sqrt(alpha * (1 - alpha) / trials)


@pytest.fixture(scope="module")
def tiny_policy(tiny_dataset_root):
    meta = LeRobotDataset("local/tiny", root=tiny_dataset_root).meta
    features = dataset_to_policy_features(meta.features)
    config = VIBConfig(
        device="cpu",
        pretrained_backbone_weights=None,
        input_features={k: f for k, f in features.items() if k != "action"},
        output_features={"action": features["action"]},
        **SMALL,
    )
    policy = VIBPolicy(config, dataset_stats=meta.stats).eval()
    preprocessor, _ = make_vib_pre_post_processors(config, dataset_stats=meta.stats)
    return policy, preprocessor


def direct_rates(policy, preprocessor, root, episode: int) -> torch.Tensor:
    """The rate of every frame of one episode, one frame at a time."""
    frames = LeRobotDataset("local/tiny", root=root, episodes=[episode])
    rates = []
    with torch.no_grad():
        for i in range(len(frames)):
            obs = preprocessor({k: v for k, v in frames[i].items() if k.startswith("observation")})
            rates.append(float(policy._encode(obs)[1]))
    return torch.tensor(rates, dtype=torch.float64)


def test_calibration_statistics_equal_a_direct_computation(tiny_policy, tiny_dataset_root):
    policy, preprocessor = tiny_policy
    calibration = calibrate(policy, preprocessor, "local/tiny", root=tiny_dataset_root, episodes=[1], batch_size=7)
    rates = direct_rates(policy, preprocessor, tiny_dataset_root, 1)
    assert calibration.n_frames == len(rates) == 20 and calibration.episodes == [1]
    assert calibration.rate_mean == pytest.approx(float(rates.mean()), rel=1e-5)
    assert calibration.rate_std == pytest.approx(float(rates.std(unbiased=False)), rel=1e-4)
    assert calibration.rate_quantiles["0.9"] == pytest.approx(float(torch.quantile(rates, 0.9)), rel=1e-5)
    expected_gamma = 1 + 2 * float(rates.std(unbiased=False)) / float(rates.mean())
    assert calibration.gamma == pytest.approx(expected_gamma, rel=1e-4)
    assert calibration.gamma_method == "mean_plus_2std"
    u = rates / rates.mean()
    assert calibration.frames_above_gamma == pytest.approx(float((u > calibration.gamma).double().mean()))
    assert calibration.episodes_above_gamma == float(u.max() > calibration.gamma)  # one episode


def test_conformal_calibration_uses_the_held_out_episodes_maxima(tiny_policy, tiny_dataset_root):
    policy, preprocessor = tiny_policy
    calibration = calibrate(
        policy,
        preprocessor,
        "local/tiny",
        root=tiny_dataset_root,
        episodes=[0],
        conformal_alpha=0.5,
        conformal_episodes=[1],
    )
    r_bar = float(direct_rates(policy, preprocessor, tiny_dataset_root, 0).mean())
    held_out_max_u = float(direct_rates(policy, preprocessor, tiny_dataset_root, 1).max()) / r_bar
    # One held-out episode, alpha = 0.5: k = ceil(2 * 0.5) = 1, its max u against R_bar of episode 0.
    assert calibration.gamma_method == "conformal" and calibration.conformal_episodes == [1]
    assert calibration.gamma == pytest.approx(held_out_max_u, rel=1e-5)
    with pytest.raises(ValueError, match="must not be among the calibration episodes"):
        calibrate(
            policy,
            preprocessor,
            "local/tiny",
            root=tiny_dataset_root,
            episodes=[0, 1],
            conformal_alpha=0.5,
            conformal_episodes=[1],
        )


def test_a_dataset_without_the_policys_camera_is_refused(tiny_dataset_root):
    config = make_config(cameras={"wrist": (3, 48, 64)}, state_dim=14, action_dim=14)
    policy = VIBPolicy(config)
    preprocessor, _ = make_vib_pre_post_processors(config)
    with pytest.raises(KeyError, match=r"observation\.images\.wrist"):
        calibrate(policy, preprocessor, "local/tiny", root=tiny_dataset_root)


def test_calibrate_command_writes_the_statistics_into_the_checkpoint(tiny_checkpoint, tiny_dataset_root, tmp_path):
    ckpt = tiny_checkpoint
    trained = VIBPolicy.from_pretrained(ckpt)
    assert trained.rate_tracker.n_updates == 2 and math.isfinite(trained.rate_mean())  # usable out of the box

    calibrated_dir = tmp_path / "calibrated"
    log = run(
        [
            str(BIN / "lerobot-vib-calibrate"),
            f"--policy.path={ckpt}",
            "--dataset.repo_id=local/tiny",
            f"--dataset.root={tiny_dataset_root}",
            "--episodes=[0]",
            f"--output_dir={calibrated_dir}",
        ]
    )
    assert "R_bar=" in log
    saved = json.loads((calibrated_dir / "config.json").read_text())["calibration"]  # what a Hub push uploads
    loaded = VIBPolicy.from_pretrained(calibrated_dir)
    assert loaded.rate_mean() == saved["rate_mean"] and saved["episodes"] == [0] and saved["n_frames"] == 20
    assert loaded.stop_threshold() == saved["gamma"]
    assert (calibrated_dir / "policy_preprocessor.json").exists()  # the processors travel with it
    assert (
        "calibration" not in json.loads((ckpt / "config.json").read_text())
        or json.loads((ckpt / "config.json").read_text())["calibration"]["rate_mean"] is None
    )  # the source checkpoint is untouched


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--policy.path={missing}"], "No such checkpoint: {missing} is not a folder"),
        (["--episodes=[0,99]"], "`--episodes`: episode 99 is not in this dataset (it has 0-1)"),
        (["--conformal_alpha=1.5", "--conformal_episodes=[1]"], "`--conformal_alpha` must be in (0, 1), got 1.5"),
        (
            ["--conformal_alpha=0.05", "--conformal_episodes=[1]"],
            "needs at least 19 held-out episodes; `--conformal_episodes` has 1",
        ),
        (["--rollout_episodes=successes"], "`--rollout_episodes` chooses among rollouts: give `--rollouts=` too"),
        (["--rollout_episodes=failures"], "`--rollout_episodes` must be one of ('all', 'successes')"),
    ],
)
def test_calibrate_names_bad_arguments_before_any_work(args, message, tiny_checkpoint, tiny_dataset_root, tmp_path):
    import subprocess

    missing = str(tmp_path / "outputs" / "no_such_run" / "pretrained_model")
    args = [a.format(missing=missing) for a in args]
    if not any(a.startswith("--policy.path") for a in args):
        args.append(f"--policy.path={tiny_checkpoint}")
    proc = subprocess.run(
        [
            str(BIN / "lerobot-vib-calibrate"),
            "--dataset.repo_id=local/tiny",
            f"--dataset.root={tiny_dataset_root}",
            f"--output_dir={tmp_path / 'out'}",
            *args,
        ],
        capture_output=True,
        text=True,
        env={**os.environ, "HF_HUB_OFFLINE": "1"},
        timeout=300,
    )
    assert proc.returncode != 0
    assert message.format(missing=missing) in proc.stderr, proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr and "Loading weights" not in proc.stderr
    assert not (tmp_path / "out").exists()


def _calibrate(ckpt, dataset_root, *extra) -> str:
    return run(
        [
            str(BIN / "lerobot-vib-calibrate"),
            f"--policy.path={ckpt}",
            "--dataset.repo_id=local/tiny",
            f"--dataset.root={dataset_root}",
            *extra,
        ]
    )


def test_calibrate_writes_a_new_checkpoint_by_default_with_both_configs_calibrated(
    tiny_checkpoint, tiny_dataset_root, tmp_path
):
    import shutil

    ckpt = tmp_path / "pretrained_model"
    shutil.copytree(tiny_checkpoint, ckpt)
    source_files = {p.name: p.read_bytes() for p in ckpt.iterdir() if p.is_file()}
    _calibrate(ckpt, tiny_dataset_root)

    calibrated = tmp_path / "pretrained_model_calibrated"
    config = json.loads((calibrated / "config.json").read_text())["calibration"]
    train_config = json.loads((calibrated / "train_config.json").read_text())["policy"]["calibration"]
    assert config["rate_mean"] is not None and train_config == config  # what `lerobot-train --resume` reads
    assert {p.name: p.read_bytes() for p in ckpt.iterdir() if p.is_file()} == source_files  # untouched

    _calibrate(ckpt, tiny_dataset_root, "--in_place=true")
    config = json.loads((ckpt / "config.json").read_text())["calibration"]
    assert config["rate_mean"] is not None
    assert json.loads((ckpt / "train_config.json").read_text())["policy"]["calibration"] == config


def test_calibrate_never_writes_into_a_folder_it_did_not_make(tiny_checkpoint, tiny_dataset_root, tmp_path):
    import subprocess

    target = tmp_path / "mine"
    target.mkdir()
    (target / "notes.txt").write_text("x")
    proc = subprocess.run(
        [
            str(BIN / "lerobot-vib-calibrate"),
            f"--policy.path={tiny_checkpoint}",
            "--dataset.repo_id=local/tiny",
            f"--dataset.root={tiny_dataset_root}",
            f"--output_dir={target}",
        ],
        capture_output=True,
        text=True,
        env={**os.environ, "HF_HUB_OFFLINE": "1"},
        timeout=300,
    )
    assert proc.returncode != 0 and "is not a calibrated checkpoint" in proc.stderr, proc.stderr[-2000:]
    assert sorted(p.name for p in target.iterdir()) == ["notes.txt"]


CLEAN_ARM = {"type": "vib_arm", "task": "ArmGrasp-v0", "workspace": "near", "perturbation": {"noise_std": [0.0]}}


def _rollouts(u_max: list[float], rate_mean: float, safety: bool = False, env: dict | None = CLEAN_ARM) -> dict:
    """An uncertainty_info.json as lerobot-vib-eval writes it (the fields calibration reads)."""
    return {
        "rate_mean": rate_mean,
        "safety_enabled": safety,
        "per_episode": [{"seed": 100 + i, "u_max": u} for i, u in enumerate(u_max)],
        **({"env": env} if env is not None else {}),
    }


def test_a_windowed_threshold_is_set_on_the_windowed_u_of_the_clean_rollouts():
    from lerobot_vib.configuration_vib import CalibrationConfig
    from lerobot_vib.failure import windowed
    from lerobot_vib.scripts.calibrate import gamma_from_rollouts

    # 20 clean rollouts of 30 steps, u near 1, each with a one-step spike to 3: the spike sets a one-step
    # threshold, and a 5-step mean dilutes it to about 1.4
    rng = np.random.default_rng(0)
    traces = [np.r_[1 + 0.05 * rng.random(10), 3.0, 1 + 0.05 * rng.random(19)] for _ in range(20)]
    dataset = CalibrationConfig(dataset_repo_id="local/arm", n_frames=100, rate_mean=2.0, rate_std=0.5)
    info = _rollouts([float(t.max()) for t in traces], 2.0)
    one = gamma_from_rollouts(dataset, info, 0.1, "r.json", threshold="max", traces=traces)
    five = gamma_from_rollouts(dataset, info, 0.1, "r.json", threshold="max", traces=traces, window=5)
    assert one.window == 1 and one.gamma == pytest.approx(3.0)
    assert (five.window, five.window_aggregate) == (5, "mean")
    assert five.gamma == pytest.approx(conformal_gamma([windowed(t, 5).max() for t in traces], 0.1))
    assert five.gamma < 1.5
    with pytest.raises(VIBConfigError, match="per-step u of every rollout"):
        gamma_from_rollouts(dataset, info, 0.1, "r.json", threshold="max", window=5)


def test_an_and_of_scores_gets_each_members_threshold_from_the_same_clean_rollouts():
    from lerobot_vib.configuration_vib import CalibrationConfig
    from lerobot_vib.scripts.calibrate import gamma_from_rollouts

    rng = np.random.default_rng(1)
    traces = [1 + 0.1 * rng.random(30) for _ in range(20)]
    partner = [2 + rng.random(30) for _ in range(20)]
    dataset = CalibrationConfig(dataset_repo_id="local/arm", n_frames=100, rate_mean=2.0, rate_std=0.5,
                                score_means={"embedding_rnd": 4.0})  # fmt: skip
    info = {**_rollouts([float(t.max()) for t in traces], 2.0), "score_means": {"rate": 2.0, "embedding_rnd": 4.0}}
    both = gamma_from_rollouts(dataset, info, 0.1, "r.json", threshold="max", traces=traces,
                               and_traces={"embedding_rnd": partner})  # fmt: skip
    assert both.and_gammas == {"embedding_rnd": pytest.approx(conformal_gamma([p.max() for p in partner], 0.1))}
    assert both.gamma == pytest.approx(conformal_gamma([t.max() for t in traces], 0.1))
    other = {**info, "score_means": {"rate": 2.0, "embedding_rnd": 5.0}}
    with pytest.raises(VIBConfigError, match=r"normalized by 5\.0, this checkpoint's mean is 4\.0"):
        gamma_from_rollouts(dataset, other, 0.1, "r.json", threshold="max", traces=traces,
                            and_traces={"embedding_rnd": partner})  # fmt: skip
    with pytest.raises(VIBConfigError, match="repeats the stop's own score"):
        gamma_from_rollouts(dataset, info, 0.1, "r.json", threshold="max", traces=traces, and_traces={"rate": traces})


def test_an_or_of_scores_sets_every_threshold_gammas_included_at_alpha_over_k():
    from lerobot_vib.configuration_vib import CalibrationConfig
    from lerobot_vib.failure import windowed
    from lerobot_vib.scripts.calibrate import gamma_from_rollouts

    rng = np.random.default_rng(3)
    traces = [1 + 0.1 * rng.random(30) for _ in range(40)]
    partner = [2 + rng.random(30) for _ in range(40)]
    dataset = CalibrationConfig(dataset_repo_id="local/arm", n_frames=100, rate_mean=2.0, rate_std=0.5,
                                score_means={"embedding_rnd": 4.0, "chunk_disagreement": 0.5})  # fmt: skip
    means = {"rate": 2.0, "embedding_rnd": 4.0, "chunk_disagreement": 0.5}
    info = {**_rollouts([float(t.max()) for t in traces], 2.0), "score_means": means}
    either = gamma_from_rollouts(dataset, info, 0.1, "r.json", threshold="max", traces=traces,
                                 or_traces={"embedding_rnd": partner}, or_window=5)  # fmt: skip
    assert either.gamma == pytest.approx(conformal_gamma([t.max() for t in traces], 0.05))
    expected = conformal_gamma([windowed(p, 5).max() for p in partner], 0.05)
    assert either.or_gammas == {"embedding_rnd": pytest.approx(expected)} and either.or_window == 5
    assert either.and_gammas == {}
    with pytest.raises(VIBConfigError, match="AND and an OR"):
        gamma_from_rollouts(dataset, info, 0.1, "r.json", threshold="max", traces=traces,
                            or_traces={"embedding_rnd": partner}, and_traces={"embedding_rnd": partner})  # fmt: skip
    with pytest.raises(VIBConfigError, match="both set"):
        CalibrationConfig(and_gammas={"embedding_rnd": 2.0}, or_gammas={"state_rate": 2.0})
    wide = gamma_from_rollouts(dataset, info, 0.1, "r.json", threshold="max", traces=traces,
                               or_traces={"embedding_rnd": partner}, or_window=5, or_margin=3.0)  # fmt: skip
    # the partner's threshold at three times its conformal one, the stop's own gamma untouched
    assert wide.or_gammas == {"embedding_rnd": pytest.approx(3.0 * expected)} and wide.or_margin == 3.0
    assert wide.gamma == either.gamma and wide.episodes_above_gamma <= either.episodes_above_gamma
    with pytest.raises(VIBConfigError, match="or_margin` must be >= 1"):
        CalibrationConfig(or_gammas={"state_rate": 2.0}, or_margin=0.5)
    # an OR of three (the preset's shipped failure monitor): the score and both partners each at alpha / 3
    other = [3 + rng.random(30) for _ in range(40)]
    three = gamma_from_rollouts(dataset, info, 0.1, "r.json", threshold="max", traces=traces,
                                or_traces={"embedding_rnd": partner, "chunk_disagreement": other}, or_window=5,
                                or_margin=4.0)  # fmt: skip
    assert three.gamma == pytest.approx(conformal_gamma([t.max() for t in traces], 0.1 / 3))
    assert three.or_gammas == {
        "embedding_rnd": pytest.approx(4.0 * conformal_gamma([windowed(p, 5).max() for p in partner], 0.1 / 3)),
        "chunk_disagreement": pytest.approx(4.0 * conformal_gamma([windowed(p, 5).max() for p in other], 0.1 / 3)),
    }


def test_a_threshold_set_on_the_successful_rollouts_ignores_the_failures_and_their_traces():
    """As failure prediction calibrates (failure.py): a failing clean rollout's high u is not taken for normal."""
    from lerobot_vib.configuration_vib import CalibrationConfig
    from lerobot_vib.scripts.calibrate import gamma_from_rollouts

    rng = np.random.default_rng(2)
    ok = [1 + 0.1 * rng.random(30) for _ in range(20)]
    failed = [np.r_[np.ones(20), np.full(10, 5.0)] for _ in range(6)]
    traces = ok[:10] + failed + ok[10:]
    partner = [2 + rng.random(30) for _ in traces]
    dataset = CalibrationConfig(dataset_repo_id="local/arm", n_frames=100, rate_mean=2.0, rate_std=0.5,
                                score_means={"embedding_rnd": 4.0})  # fmt: skip
    info = {**_rollouts([float(t.max()) for t in traces], 2.0), "score_means": {"rate": 2.0, "embedding_rnd": 4.0}}
    for i, ep in enumerate(info["per_episode"]):
        ep["success"] = not 10 <= i < 16
    kw = dict(threshold="max", traces=traces, and_traces={"embedding_rnd": partner})
    every = gamma_from_rollouts(dataset, info, 0.1, "r.json", **kw)
    good = gamma_from_rollouts(dataset, info, 0.1, "r.json", **kw, episodes="successes")
    assert every.gamma == pytest.approx(5.0) and every.rollout_episodes == "all"
    assert good.gamma == pytest.approx(conformal_gamma([t.max() for t in ok], 0.1)) and good.gamma < 1.2
    kept = partner[:10] + partner[16:]
    assert good.and_gammas == {"embedding_rnd": pytest.approx(conformal_gamma([p.max() for p in kept], 0.1))}
    assert good.rollout_episodes == "successes" and len(good.rollout_seeds) == 26  # every rollout seen is named
    band = gamma_from_rollouts(dataset, info, 0.1, "r.json", threshold="time_band", traces=traces,
                               episodes="successes")  # fmt: skip
    assert max(band.gamma_band) < 1.5
    for ep in info["per_episode"][8:]:
        ep["success"] = False
    with pytest.raises(VIBConfigError, match=r"needs at least 9 successful rollouts; r\.json has 8"):
        gamma_from_rollouts(dataset, info, 0.1, "r.json", threshold="max", episodes="successes")
    del info["per_episode"][0]["success"]
    with pytest.raises(VIBConfigError, match="does not say which rollouts succeeded"):
        gamma_from_rollouts(dataset, info, 0.1, "r.json", threshold="max", episodes="successes")


def _perturbed(**perturbation) -> dict:
    return {**CLEAN_ARM, "perturbation": {"noise_std": [0.0], **perturbation}}


@pytest.mark.parametrize(
    ("env", "recording", "message"),
    [
        (_perturbed(black_images=True), None, r"the env was perturbed \(black_images=true\)"),
        (_perturbed(noise_std=[0.0, 0.05]), None, r"noise_std=\[0.0, 0.05\]"),
        (_perturbed(occlusion=True, camera_shake=0.02), None, r"camera_shake=0.02, occlusion=true"),
        ({**CLEAN_ARM, "workspace": "wide"}, {"task": "grasp_block", "workspace": "near"}, "workspace wide"),
        ({**CLEAN_ARM, "type": "aloha_fast"}, {"task": "grasp_block", "workspace": "near"}, "env type aloha_fast"),
        ({**CLEAN_ARM, "cameras": ["wrist"]}, None, r"cameras \['wrist'\] \(the policy reads \['top'\]\)"),
        ({**CLEAN_ARM, "observation_height": 96, "observation_width": 128}, None, "images of 96x128"),
        (None, None, "does not record the env"),
    ],
)
def test_gamma_is_set_only_on_clean_rollouts_in_the_env_the_policy_was_trained_for(env, recording, message):
    """Black-image rollouts once set gamma = 1.057 and were then called clean rollouts on the model card."""
    from helpers import make_config
    from lerobot_vib.configuration_vib import CalibrationConfig, VIBConfigError
    from lerobot_vib.scripts.calibrate import gamma_from_rollouts

    calibration = CalibrationConfig(rate_mean=2.0, rate_std=0.5)
    policy = make_config(cameras={"top": (3, 32, 32)})
    with pytest.raises(VIBConfigError, match=message):
        gamma_from_rollouts(
            calibration, _rollouts([1.0] * 10, 2.0, env=env), 0.1, "r.json", policy_config=policy, recording=recording
        )
    clean = gamma_from_rollouts(
        calibration, _rollouts([1.0] * 10, 2.0), 0.1, "r.json", policy_config=policy, recording=recording
    )
    assert clean.gamma_method == "conformal_rollouts"  # the same rollouts, clean and in the right env, are taken


def test_gamma_from_clean_rollouts_is_the_conformal_threshold_on_their_episode_maxima():
    from lerobot_vib.configuration_vib import CalibrationConfig
    from lerobot_vib.scripts.calibrate import gamma_from_rollouts

    dataset_calibration = CalibrationConfig(rate_mean=2.0, rate_std=0.5, gamma=1.5, gamma_method="mean_plus_2std")
    u_max = [3.0, 1.2, 2.2, 5.0, 1.9, 2.5, 1.1, 4.0, 2.8, 1.7]
    got = gamma_from_rollouts(dataset_calibration, _rollouts(u_max, 2.0), alpha=0.1, source="r.json")
    assert got.gamma == conformal_gamma(torch.tensor(u_max), 0.1) == 5.0  # ceil(11 * 0.9) = 10th of 10
    assert (got.gamma_method, got.conformal_alpha, got.rollout_seeds[:2]) == ("conformal_rollouts", 0.1, [100, 101])
    assert got.rate_mean == 2.0 and got.episodes_above_gamma == 0.0  # R_bar stays the dataset's
    assert dataset_calibration.gamma == 1.5  # a new record, not an edit


@pytest.mark.parametrize(
    ("rollouts", "calibrated", "message"),
    [
        (_rollouts([1.0] * 10, 2.0, safety=True), True, "safety stop on"),
        (_rollouts([1.0] * 10, 3.0), True, "R_bar=3.0, this checkpoint has R_bar=2"),
        (_rollouts([1.0] * 5, 2.0), True, "needs at least 9 rollouts"),
        (_rollouts([1.0] * 9 + [float("nan")], 2.0), True, r"without a finite max u \(seeds \[109\]\)"),
        (_rollouts([None] + [1.0] * 10, 2.0), True, r"without a finite max u \(seeds \[100\]\)"),
        (_rollouts([1.0] * 10, 2.0), False, "no R_bar: calibrate it on its dataset first"),
    ],
)
def test_gamma_from_rollouts_refuses_rollouts_that_are_not_clean_or_not_of_this_checkpoint(
    rollouts, calibrated, message
):
    from lerobot_vib.configuration_vib import CalibrationConfig, VIBConfigError
    from lerobot_vib.scripts.calibrate import gamma_from_rollouts

    calibration = CalibrationConfig(rate_mean=2.0, rate_std=0.5) if calibrated else CalibrationConfig()
    with pytest.raises(VIBConfigError, match=message):
        gamma_from_rollouts(calibration, rollouts, alpha=0.1, source="r.json")


def test_calibrate_command_sets_gamma_from_rollouts_in_both_configs(tiny_checkpoint, tiny_dataset_root, tmp_path):
    import shutil

    ckpt = tmp_path / "pretrained_model"
    shutil.copytree(tiny_checkpoint, ckpt)
    _calibrate(ckpt, tiny_dataset_root, "--in_place=true")
    r_bar = json.loads((ckpt / "config.json").read_text())["calibration"]["rate_mean"]
    info = tmp_path / "uncertainty_info.json"
    info.write_text(json.dumps(_rollouts([float(i) for i in range(1, 11)], r_bar)))
    log = run(
        [
            str(BIN / "lerobot-vib-calibrate"),
            f"--policy.path={ckpt}",
            f"--rollouts={info}",
            "--conformal_alpha=0.1",
            "--threshold=max",
            "--in_place=true",
        ]
    )
    assert "gamma=10.0000" in log
    config = json.loads((ckpt / "config.json").read_text())["calibration"]
    assert (config["gamma"], config["gamma_method"], config["rate_mean"]) == (10.0, "conformal_rollouts", r_bar)
    assert json.loads((ckpt / "train_config.json").read_text())["policy"]["calibration"] == config
    assert VIBPolicy.from_pretrained(ckpt).stop_threshold() == 10.0


@pytest.mark.parametrize("threshold", [None, "std_band"])
def test_calibrate_command_sets_a_time_indexed_band_from_the_rollouts_trace_by_default(
    tiny_checkpoint, tiny_dataset_root, tmp_path, threshold
):
    import shutil

    ckpt = tmp_path / "pretrained_model"
    shutil.copytree(tiny_checkpoint, ckpt)
    _calibrate(ckpt, tiny_dataset_root, "--in_place=true", "--rnd_steps=50")
    r_bar = json.loads((ckpt / "config.json").read_text())["calibration"]["rate_mean"]
    # 20 clean rollouts of 6 steps: u high at the first two steps, low after (lerobot-vib-eval's two files)
    traces = [[3.0 + 0.01 * i, 3.0, 1.0, 1.0 + 0.01 * i, 1.0, 1.0] for i in range(20)]
    info = tmp_path / "uncertainty_info.json"
    info.write_text(json.dumps(_rollouts([max(t) for t in traces], r_bar)))
    rows = ["episode,seed,step,rate,u,stopped,just_stopped"]
    rows += [
        f"{e},{100 + e},{t},{u * r_bar},{u},False,False" for e, trace in enumerate(traces) for t, u in enumerate(trace)
    ]
    (tmp_path / "uncertainty_trace.csv").write_text("\n".join(rows) + "\n")
    flag = [f"--threshold={threshold}"] if threshold else []
    log = run([str(BIN / "lerobot-vib-calibrate"), f"--policy.path={ckpt}", f"--rollouts={info}",
               "--conformal_alpha=0.1", "--in_place=true", *flag])  # fmt: skip
    assert "time-indexed band over 6 steps" in log
    config = json.loads((ckpt / "config.json").read_text())["calibration"]
    band = config["gamma_band"]
    assert config["gamma_method"] == f"{threshold or 'time_band'}_rollouts" and len(band) == 6
    assert band[0] > 3.0 and band[3] < 1.5  # a u of 2 stops late in a rollout, not at its start
    policy = VIBPolicy.from_pretrained(ckpt)
    assert [policy.stop_threshold(step=t) for t in (0, 3, 99)] == [band[0], band[3], band[5]]


def test_the_model_card_states_the_data_score_r_bar_gamma_its_method_and_the_measured_success(monkeypatch):
    from dataclasses import replace

    from huggingface_hub import ModelCard

    from helpers import make_config
    from lerobot_vib.configuration_vib import CalibrationConfig
    from lerobot_vib.scripts.calibrate import gamma_from_rollouts

    monkeypatch.setattr(ModelCard, "validate", lambda self, *a, **k: None)  # validation is an online call
    rollouts = _rollouts([float(i) for i in range(1, 11)], 2.0)
    for i, ep in enumerate(rollouts["per_episode"]):
        ep["success"] = i < 7
    rollouts["command"] = "lerobot-vib-eval --policy.path=ckpt --env.type=vib_arm --eval.n_episodes=10"
    dataset = CalibrationConfig(dataset_repo_id="local/arm", n_frames=5000, rate_mean=2.0, rate_std=0.5)
    calibration = gamma_from_rollouts(dataset, rollouts, alpha=0.1, source="r.json", threshold="max")
    policy = VIBPolicy(make_config(uncertainty_score="rate"))
    policy.config.calibration = replace(calibration)
    text = policy.generate_model_card("local/arm", "vib", None, None).text
    assert "Training data: `local/arm`" in text and "5000 frames" in text
    assert "Score: `rate`" in text and "R_bar (the rate's mean) = 2" in text
    assert "gamma = 10 on `rate`, set by split-conformal on the maximum u of 10 clean rollouts at alpha = 0.1" in text
    assert "Measured: 7/10 clean rollouts succeeded (`lerobot-vib-eval --policy.path=ckpt" in text
    # LeRobot's Evaluation section no longer says there is none, and the Hub's evaluation results hold it
    assert "No evaluation results have been provided" not in text
    assert "| clean rollouts in simulation (lerobot-vib-eval, seeds 100-109) | 10 | 7 | 70% |" in text
    card = policy.generate_model_card("local/arm", "vib", None, None)
    result = card.data.eval_results[0]
    assert (result.metric_type, result.metric_value, result.dataset_type) == ("success_rate", 0.7, "local/arm")
    bare = VIBPolicy(make_config(uncertainty_score="rate")).generate_model_card("local/arm", "vib", None, None).text
    assert "Not calibrated" in bare and "no evaluation is recorded" in bare
    assert "successful ones" not in text
    policy.config.calibration = gamma_from_rollouts(dataset, rollouts, 0.3, "r.json", threshold="max",
                                                    episodes="successes")  # fmt: skip
    text = policy.generate_model_card("local/arm", "vib", None, None).text
    assert "gamma = 6 on `rate`" in text and "Only the 7 successful ones among those rollouts set it" in text


def test_a_calibrated_checkpoint_reaches_the_hub_through_its_http_api(
    tiny_checkpoint, tiny_dataset_root, tmp_path, monkeypatch
):
    """push_calibrated (`lerobot-vib-calibrate --push_to_hub=true`) through LeRobot's push and huggingface_hub's
    HTTP client, against a Hub served on localhost (tests/local_hub.py): the calibrated weights, both configs,
    the card and the processors arrive as they are on disk."""
    import shutil

    import huggingface_hub
    from huggingface_hub import ModelCard

    from lerobot_vib.scripts.calibrate import push_calibrated
    from local_hub import LocalHub

    ckpt = tmp_path / "pretrained_model"
    shutil.copytree(tiny_checkpoint, ckpt)
    _calibrate(ckpt, tiny_dataset_root, "--in_place=true", "--rnd_steps=20")
    r_bar = json.loads((ckpt / "config.json").read_text())["calibration"]["rate_mean"]
    info = tmp_path / "uncertainty_info.json"
    info.write_text(json.dumps(_rollouts([float(i) for i in range(1, 11)], r_bar)))
    run([str(BIN / "lerobot-vib-calibrate"), f"--policy.path={ckpt}", f"--rollouts={info}", "--conformal_alpha=0.1",
         "--threshold=max", "--in_place=true"])  # fmt: skip

    with LocalHub() as hub:
        monkeypatch.setattr(huggingface_hub.constants, "ENDPOINT", hub.endpoint)
        monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_OFFLINE", False)
        monkeypatch.setenv("HF_TOKEN", "hf_local_test")

        def validate_here(card, repo_type=None):  # ModelCard.validate posts to huggingface.co whatever the endpoint
            response = huggingface_hub.utils.get_session().post(
                f"{hub.endpoint}/api/validate-yaml",
                json={"repoType": repo_type or "model", "content": str(card)},
                headers=huggingface_hub.utils.build_hf_headers(),
            )
            huggingface_hub.utils.hf_raise_for_status(response)

        monkeypatch.setattr(ModelCard, "validate", validate_here)
        push_calibrated(ckpt, "user/vib_local")
    assert hub.unknown == [] and hub.tokens == {"Bearer hf_local_test"}
    files = hub.repos["user/vib_local"]
    assert {"model.safetensors", "config.json", "train_config.json", "README.md"} <= set(files)
    assert {"policy_preprocessor.json", "policy_postprocessor.json"} <= set(files)
    pushed = json.loads(files["config.json"])["calibration"]
    assert (pushed["gamma"], pushed["gamma_method"], pushed["rate_mean"]) == (10.0, "conformal_rollouts", r_bar)
    assert json.loads(files["train_config.json"])["policy"]["calibration"]["gamma"] == 10.0
    from safetensors.torch import load

    sent, kept = load(files["model.safetensors"]), load((ckpt / "model.safetensors").read_bytes())
    assert sent.keys() == kept.keys() and all(torch.equal(sent[k], kept[k]) for k in kept)
    card = files["README.md"].decode()
    assert "gamma" in card and "not on PyPI" in card and "Measured: 6/10 clean rollouts" not in card


def test_an_or_margin_below_one_or_without_or_scores_is_refused_by_name(tmp_path):
    from lerobot_vib.scripts.calibrate import CalibrateConfig

    rollouts = tmp_path / "uncertainty_info.json"
    rollouts.write_text("{}")
    with pytest.raises(VIBConfigError, match="`--or_margin` must be >= 1"):
        CalibrateConfig(rollouts=rollouts, conformal_alpha=0.1, or_scores=["state_rate"], or_margin=0.9)
    with pytest.raises(VIBConfigError, match="give `--or_scores` too"):
        CalibrateConfig(rollouts=rollouts, conformal_alpha=0.1, or_margin=2.0)
    assert CalibrateConfig(rollouts=rollouts, conformal_alpha=0.1, or_scores=["state_rate"], or_margin=2.0)


def test_the_report_s_command_for_an_or_with_a_margin_sets_that_margin():
    from lerobot_vib.failure import AnyOf, Monitor
    from lerobot_vib.scripts.failure_report import ship_command

    monitor = AnyOf((Monitor(("image_rate",), 5), Monitor(("state_rate",), 5), Monitor(("embedding_rnd",), 5)), 2.0)
    command = ship_command(monitor, 0.1)
    assert "--or_scores='[state_rate,embedding_rnd]' --or_window=5 --or_margin=2" in command
    assert "--or_margin" not in ship_command(AnyOf(monitor.members[:2]), 0.1)
