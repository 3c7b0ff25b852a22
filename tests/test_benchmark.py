"""`lerobot-vib-benchmark` end to end at a tiny budget, its resume, its variants and RND."""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from lerobot.configs.default import DatasetConfig
from lerobot.policies.act.configuration_act import ACTConfig
from lerobot.policies.act.modeling_act import ACTPolicy

from helpers import BIN, run
from lerobot_vib.configuration_vib import VIBConfigError
from lerobot_vib.rnd import RND, RNDConfig, train_rnd
from lerobot_vib.scripts import benchmark, benchmark_report
from lerobot_vib.scripts.benchmark import BenchmarkConfig, cell_path, planned_cells, run_benchmark
from lerobot_vib.sim.env_config import AlohaFastEnv, ArmGraspEnvConfig
from lerobot_vib.sim.recorder import RecordingSettings, record_scripted_dataset
from lerobot_vib.variants import ScoredChunkPolicy, act_with

REPO = "local/bench_arm"


@pytest.fixture(scope="module")
def arm_data(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("bench") / "arm"
    settings = RecordingSettings(
        task="grasp_block", image_height=48, image_width=64, cameras=["scene"], shadows=False, use_videos=False
    )
    record_scripted_dataset(root, REPO, settings, 3, progress=False)
    return root


def tiny_config(root: Path, out: Path, **overrides) -> BenchmarkConfig:
    fields = dict(
        dataset=DatasetConfig(repo_id=REPO, root=str(root)),
        env=ArmGraspEnvConfig(dataset_root=str(root)),
        output_dir=out,
        variants=["vib", "act"],
        conditions=["normal", "occlusion"],
        n_episodes=2,
        n_episodes_other=2,
        validation_episodes=2,
        steps=2,
        eval_batch_size=2,
        alpha=0.5,
        rnd_steps=20,
    )
    return BenchmarkConfig(**{**fields, **overrides})


def test_tiny_benchmark_trains_evaluates_reports_and_resumes_without_repeating_a_cell(arm_data, tmp_path, monkeypatch):
    cfg = tiny_config(arm_data, tmp_path / "bench")
    real_run_cell, ran = benchmark.run_cell, []

    def interrupted(cfg, variant, condition, *args):
        if len(ran) == 2:
            raise KeyboardInterrupt  # Ctrl-C during the third cell
        ran.append((variant, condition))
        return real_run_cell(cfg, variant, condition, *args)

    monkeypatch.setattr(benchmark, "run_cell", interrupted)
    with pytest.raises(KeyboardInterrupt):
        run_benchmark(cfg)
    saved = [
        p
        for folder in ("validation", "validation_perturbed", "cells")
        for p in (cfg.output_dir / folder).rglob("*.json")
    ]
    assert len(saved) == 2
    assert (cfg.output_dir / "train/vib/seed_1000/checkpoints/000002/pretrained_model").exists()

    first_run, ran[:] = list(ran), []

    def counting(cfg, variant, condition, *args):
        ran.append((variant, condition))
        return real_run_cell(cfg, variant, condition, *args)

    def no_training(*args, **kwargs):
        raise AssertionError("the trained checkpoints must be reused")

    # matplotlib's first import in a fresh environment builds its font cache with a subprocess: not a training
    import matplotlib.pyplot  # noqa: F401

    monkeypatch.setattr(benchmark, "run_cell", counting)
    monkeypatch.setattr(benchmark.subprocess, "run", no_training)
    results = run_benchmark(cfg)
    planned = [(v, c) for v, c, _, _ in planned_cells(cfg)]
    assert sorted(ran + first_run) == sorted(planned) and len(ran) == len(planned) - 2

    # the same test seeds for every row of a condition, u for the scored row only
    normal = {v: json.loads(cell_path(cfg, v, "normal", 1000).read_text()) for v in ("vib", "act")}
    assert normal["vib"]["seeds"] == normal["act"]["seeds"] == [600_000, 600_001]
    assert normal["act"]["u"] is None and len(normal["vib"]["u"][0]) == normal["vib"]["steps"][0]
    # the VIB network was calibrated first, so its cells hold every score per step, as u, and the missed grasps
    assert (cfg.output_dir / "calibrated/vib/seed_1000/config.json").exists()
    scores = normal["vib"]["scores"]
    assert {"rate", "image_rate", "embedding_rnd", "chunk_disagreement"} <= set(scores)
    assert all(len(scores[name][0]) == normal["vib"]["steps"][0] for name in scores)
    assert normal["vib"]["grasp_missed_at"] == [None, None] or all(
        m is None or 0 <= m < normal["vib"]["steps"][i] for i, m in enumerate(normal["vib"]["grasp_missed_at"])
    )
    assert normal["act"]["scores"] is None
    # beside each traced VIB cell, its rollouts' observation embeddings per step (an RND fitted on rollouts)
    from lerobot_vib.scripts.eval_uncertainty import read_embeddings

    embeddings = read_embeddings(benchmark.embeddings_path(cell_path(cfg, "vib", "normal", 1000)), 2)
    assert [len(e) for e in embeddings] == normal["vib"]["steps"] and embeddings[0].shape[1] > 0
    assert not benchmark.embeddings_path(cell_path(cfg, "act", "normal", 1000)).exists()
    assert json.loads(cell_path(cfg, "vib", "validation", 1000, "eq6:0.01").read_text())["seeds"] == [400_000, 400_001]
    for v in ("vib", "act"):
        s = results["success"][v]["normal"]
        assert s["n"] == 2 and 0 <= s["low"] <= s["pc"] <= s["high"] <= 100
    u = results["uncertainty"]["vib"]["1000"]
    assert set(u["auroc"]) == {"occlusion"} and 0 <= u["auroc"]["occlusion"]["frames"] <= 1
    assert u["thresholds"]["conformal"] is not None and len(u["thresholds"]["band"]) >= 1
    assert "occlusion_episodes" in u["stops"]["mean_2std"]
    report = (cfg.output_dir / "report.md").read_text()
    assert "lerobot-vib-benchmark" in report and "| VIB (Eq. 6) |" in report and "| ACT |" in report
    assert "test seeds 600000-600001" in report and "1 training seed(s)" in report
    assert (cfg.output_dir / "success.png").exists() and (cfg.output_dir / "traces.png").exists()
    assert json.loads((cfg.output_dir / "results.json").read_text())["success"]["act"]["occlusion"]["n"] == 2

    # a rerun with other settings refuses to mix its cells with these
    with pytest.raises(VIBConfigError, match="other episode seeds"):
        run_benchmark(tiny_config(arm_data, cfg.output_dir, n_episodes=3))
    with pytest.raises(VIBConfigError, match="other steps"):
        run_benchmark(tiny_config(arm_data, cfg.output_dir, steps=3))


def test_failure_prediction_adds_perturbed_validation_cells_for_scored_vib_rows_on_validation_seeds(arm_data, tmp_path):
    cfg = tiny_config(arm_data, tmp_path / "bench", n_episodes_other=3, validation_episodes=2)
    cells = planned_cells(cfg)
    perturbed = [c for c in cells if c[1].startswith("validation:")]
    assert perturbed == [("vib", "validation:occlusion", 1000, None)]  # the scored VIB row only, not ACT
    # after every test cell: a run cut short has its success numbers first
    assert cells.index(perturbed[0]) > max(cells.index(c) for c in cells if c[1] in ("normal", "occlusion"))
    assert benchmark.cell_seeds(cfg, "vib", "validation:occlusion") == [400_000, 400_001]  # validation seeds
    assert benchmark.env_condition("validation:occlusion") == "occlusion"
    assert "validation_perturbed/occlusion/vib/seed_1000.json" in cell_path(cfg, *perturbed[0]).as_posix()
    assert not [c for c in planned_cells(tiny_config(arm_data, tmp_path, failure_validation=False))
                if c[1].startswith("validation:")]  # fmt: skip


def test_two_training_seeds_choose_each_run_time_on_validation_and_report_the_spread(arm_data, tmp_path):
    """The comparison rows at two training seeds: every network trained per seed, each row's run time chosen
    on validation episodes only, test cells on the test seeds, success pooled and per seed."""
    cfg = tiny_config(
        arm_data,
        tmp_path / "bench",
        variants=["act_like_vib", "vib_chosen"],
        conditions=["normal", "gaussian"],
        train_seeds=[1000, 2000],
        runtimes=["queue", "act:0.3"],
    )
    results = run_benchmark(cfg)
    out = cfg.output_dir
    for net in ("act_like_vib", "vib"):
        for seed in (1000, 2000):
            assert (out / f"train/{net}/seed_{seed}/checkpoints/000002/pretrained_model").exists()
            command = (out / f"train/{net}/seed_{seed}_command.txt").read_text()
            assert f"--seed={seed}" in command and command.startswith("lerobot-train ")  # as a user types it
    assert "--policy.type=act_like_vib" in (out / "train/act_like_vib/seed_1000_command.txt").read_text()
    saved = json.loads(
        (out / "train/act_like_vib/seed_1000/checkpoints/000002/pretrained_model/config.json").read_text()
    )
    assert (saved["type"], saved["backbone_norm"], saved["backbone_layer"], saved["ema_decay"]) == (
        "act_like_vib", "group_norm", "layer2", 0.999,
    )  # fmt: skip

    choices = json.loads((out / "choices.json").read_text())
    for v in ("act_like_vib", "vib_chosen"):
        for seed in (1000, 2000):
            choice = choices[v][str(seed)]
            validation = {
                rt: json.loads(cell_path(cfg, v, "validation", seed, rt).read_text()) for rt in ("queue", "act:0.3")
            }
            wins = {rt: sum(c["success"]) for rt, c in validation.items()}
            assert choice["chosen_on"] == {rt: [wins[rt], 2] for rt in wins}
            assert choice["runtime"] == ("act:0.3" if wins["act:0.3"] > wins["queue"] else "queue")
            assert all(c["seeds"] == [400_000, 400_001] for c in validation.values())
            for condition in ("normal", "gaussian"):
                test = json.loads(cell_path(cfg, v, condition, seed).read_text())
                assert test["runtime"] == choice["runtime"] and test["train_seed"] == seed
                assert test["seeds"] == [600_000, 600_001]

    normal = results["success"]["vib_chosen"]["normal"]
    per_seed = [normal["per_seed"][s] for s in ("1000", "2000")]
    assert normal["n"] == 4 and normal["k"] == sum(p["k"] for p in per_seed)
    assert normal["n_seeds"] == 2 and normal["min_pc"] <= normal["mean_pc"] <= normal["max_pc"]
    assert normal["mean_pc"] == pytest.approx(sum(p["pc"] for p in per_seed) / 2)
    assert set(results["uncertainty"]["vib_chosen"]) == {"1000", "2000"}
    report = (out / "report.md").read_text()
    assert "| ACT + VIB's trunk, EMA, floor |" in report and "Run times chosen on validation" in report
    assert "seed 2000" in report and "2 training seed(s)" in report and "VIOLATION" not in report

    # the report finds a choice that saw test episodes (here: an edited choices.json)
    choices["vib_chosen"]["2000"]["validation_seeds"] = [600_001]
    (out / "choices.json").write_text(json.dumps(choices))
    run_benchmark(cfg, report_only=True)
    assert (
        "VIOLATION: VIB (arm preset)'s run time at training seed 2000 was chosen on 1 test episodes"
        in (out / "report.md").read_text()
    )

    # seeds run in folders apart, merged by copying their cells: the report chooses the run times again on the
    # validation cells, as the runs did, rather than leaving out every row's uncertainty without a word
    choices["vib_chosen"]["2000"]["validation_seeds"] = cfg.validation_seeds()
    (out / "choices.json").write_text(json.dumps(choices))
    run_benchmark(cfg, report_only=True)
    merged = tmp_path / "merged"
    for part in ("cells", "validation", "scores"):
        shutil.copytree(out / part, merged / part)
    merged_cfg = dataclasses.replace(cfg, output_dir=merged)
    run_benchmark(merged_cfg, report_only=True)
    assert json.loads((merged / "choices.json").read_text()) == choices
    assert json.loads((merged / "config.json").read_text())["train_seeds"] == [1000, 2000]
    assert set(json.loads((merged / "results.json").read_text())["uncertainty"]["vib_chosen"]) == {"1000", "2000"}


def test_a_run_that_would_choose_on_test_seeds_is_refused_before_any_work(arm_data, tmp_path):
    with pytest.raises(VIBConfigError, match="overlap the test seeds"):
        tiny_config(arm_data, tmp_path / "a", validation_seed=600_001)
    with pytest.raises(VIBConfigError, match="overlap the test seeds"):
        tiny_config(arm_data, tmp_path / "b", test_seed=399_999, validation_seed=400_000)
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()
    # a given checkpoint whose stop threshold was set on rollouts of the test seeds
    checkpoint = tmp_path / "ckpt"
    checkpoint.mkdir()
    (checkpoint / "config.json").write_text(json.dumps({"type": "vib", "calibration": {"rollout_seeds": [600_001]}}))
    cfg = tiny_config(arm_data, tmp_path / "c", variants=["vib"], vib_checkpoint=checkpoint)
    with pytest.raises(VIBConfigError, match="test seeds"):
        run_benchmark(cfg)
    with pytest.raises(VIBConfigError, match="single --train_seeds"):
        tiny_config(arm_data, tmp_path / "d", vib_checkpoint=checkpoint, train_seeds=[1, 2])
    with pytest.raises(VIBConfigError, match="runtimes"):
        tiny_config(arm_data, tmp_path / "e", runtimes=["act:-1"])
    with pytest.raises(VIBConfigError, match=r"Eq\. 6 needs a u"):
        tiny_config(arm_data, tmp_path / "f", variants=["comparison"], runtimes=["eq6:0.3"])


def test_a_given_checkpoint_changed_in_place_between_invocations_is_refused_by_name(arm_data, tmp_path):
    """Recalibrated in place, it once gave new cells u over another R_bar than the saved ones, silently."""
    checkpoint = tmp_path / "ckpt"
    checkpoint.mkdir()
    config = {"type": "vib", "calibration": {"rate_mean": 0.1665}}
    (checkpoint / "config.json").write_text(json.dumps(config))
    (checkpoint / "model.safetensors").write_bytes(b"weights")
    cfg = tiny_config(arm_data, tmp_path / "out", variants=["vib"], vib_checkpoint=checkpoint)
    cfg.output_dir.mkdir()
    benchmark._save_config_record(cfg)
    benchmark.check_resumable(cfg)  # the same checkpoint resumes
    config["calibration"]["rate_mean"] = 0.1605
    (checkpoint / "config.json").write_text(json.dumps(config))
    with pytest.raises(VIBConfigError, match=r"--vib_checkpoint=.*ckpt is not the checkpoint .*config or weights"):
        benchmark.check_resumable(cfg)
    config["calibration"]["rate_mean"] = 0.1665
    (checkpoint / "config.json").write_text(json.dumps(config))
    (checkpoint / "model.safetensors").write_bytes(b"retrained")
    with pytest.raises(VIBConfigError, match="changed since"):
        benchmark.check_resumable(cfg)


def test_the_command_line_refuses_scene_conditions_off_the_arm_and_unknown_rows(tmp_path):
    with pytest.raises(VIBConfigError, match="simulated arm"):
        BenchmarkConfig(
            dataset=DatasetConfig(repo_id="x"), env=AlohaFastEnv(), output_dir=tmp_path, conditions=["occlusion"]
        )
    with pytest.raises(VIBConfigError, match="Unknown variants"):
        BenchmarkConfig(dataset=DatasetConfig(repo_id="x"), env=ArmGraspEnvConfig(), variants=["diffusion"])
    out = run([str(BIN / "lerobot-vib-benchmark"), "--help"])
    assert "--profile" in out and "--n_episodes_other" in out


def test_each_env_gets_its_own_cpu_preset_and_a_profile_without_one_is_refused(tmp_path):
    arm = BenchmarkConfig(dataset=DatasetConfig(repo_id="x"), env=ArmGraspEnvConfig(), output_dir=tmp_path)
    aloha = BenchmarkConfig(dataset=DatasetConfig(repo_id="x"), env=AlohaFastEnv(), output_dir=tmp_path)
    insertion = BenchmarkConfig(
        dataset=DatasetConfig(repo_id="x"), env=AlohaFastEnv(task="AlohaInsertion-v0"), profile="gpu"
    )
    assert (arm.preset.name, aloha.preset.name, insertion.preset.name) == (
        "vib_arm_sim.json",
        "vib_cpu.json",
        "vib_aloha_insertion.json",
    )
    assert aloha.steps == json.loads(aloha.preset.read_text())["steps"]
    with pytest.raises(VIBConfigError, match="no preset for"):
        BenchmarkConfig(dataset=DatasetConfig(repo_id="x"), env=benchmark.envs.PushtEnv(), output_dir=tmp_path)


def test_the_learning_curve_is_read_exactly_from_lerobot_trains_log_including_a_resumed_run():
    def line(step: int, shown: str, l1: float, rate: str = "") -> str:
        bar = f"Training:  50%|#####     | {step}/3000 [01:04<37:25,  1.74step/s]"
        return f"{bar}\rINFO 2026-11-22 21:30:05 ot_train.py:641 step:{shown} smpl:2K loss:{l1} l1_loss:{l1}{rate}\n"

    log = (
        line(100, "100", 0.65, " rate:1.5")
        + line(1000, "1K", 0.2, " rate:9.0")
        + "Training:  1%| | 1049/3000 [00:01<00:01]\r"
        + line(1100, "1K", 0.19, " rate:9.5")  # the bar was redrawn at 1100 before the line: kept
        + line(1150, "2K", 0.5)  # a bar count that contradicts the line's step: dropped, not guessed
        + line(1100, "1K", 0.18, " rate:9.4")  # resumed from step 1000: the later value wins
    )
    curve = benchmark_report.training_curve(log)
    assert [(p["step"], p["l1"], p["rate"]) for p in curve] == [(100, 0.65, 1.5), (1000, 0.2, 9.0), (1100, 0.18, 9.4)]
    assert benchmark_report.training_curve("no loss lines") == []
    # LeRobot 0.6's resumed bar counts from its checkpoint: resumed at 1000 of 3000, its 1000th step is step 2000
    resumed = line(1000, "1K", 0.2) + line(1000, "2K", 0.1).replace("1000/3000", "1000/2000")
    curve = benchmark_report.training_curve(resumed, steps=3000)
    assert [(p["step"], p["l1"]) for p in curve] == [(1000, 0.2), (2000, 0.1)]


def test_act_with_eq6_and_u_equal_to_one_is_acts_own_ensembling():
    torch.manual_seed(0)
    from lerobot.configs.types import FeatureType, PolicyFeature

    cfg = ACTConfig(
        device="cpu", chunk_size=5, n_action_steps=5, dim_model=32, n_heads=2, dim_feedforward=64, n_encoder_layers=1,
        n_decoder_layers=1, pretrained_backbone_weights=None, use_vae=False,
        input_features={"observation.state": PolicyFeature(FeatureType.STATE, (3,)),
                        "observation.environment_state": PolicyFeature(FeatureType.ENV, (2,))},
        output_features={"action": PolicyFeature(FeatureType.ACTION, (3,))},
    )  # fmt: skip
    act = ACTPolicy(cfg).eval()
    ours = ScoredChunkPolicy(act_with(act, "none"), lambda b: (torch.ones(2), torch.ones(2)), "uncertainty")
    lerobots = act_with(act, "act")
    ours.reset(), lerobots.reset()
    g = torch.Generator().manual_seed(1)
    for _ in range(7):
        batch = {
            "observation.state": torch.randn(2, 3, generator=g),
            "observation.environment_state": torch.randn(2, 2, generator=g),
        }
        torch.testing.assert_close(ours.select_action(batch), lerobots.select_action(batch))
    assert ours.last_step.u.tolist() == [1.0, 1.0]


def _images(n: int, bright: bool, seed: int) -> torch.Tensor:
    """Dark frames with a bright square at a random place (training) or uniform noise (unseen)."""
    g = torch.Generator().manual_seed(seed)
    if bright:
        return torch.rand(n, 3, 16, 16, generator=g) * 2
    x = torch.zeros(n, 3, 16, 16)
    for i, (r, c) in enumerate(torch.randint(0, 12, (n, 2), generator=g).tolist()):
        x[i, :, r : r + 4, c : c + 4] = 1.0
    return x


def test_rnd_error_is_higher_on_unseen_images_after_training_and_survives_a_save(tmp_path):
    cfg = RNDConfig(image_keys=["observation.images.top"], image_shape=[3, 16, 16], state_key=None, steps=150, lr=1e-3)
    rnd = RND(cfg)

    def batches():
        for i in range(10):
            yield {"observation.images.top": _images(16, False, seed=i), "episode_index": torch.zeros(16)}

    losses = train_rnd(rnd, batches, batches())
    assert losses[-1] < losses[0] / 2
    seen = rnd.u({"observation.images.top": _images(64, False, seed=99)})
    unseen = rnd.u({"observation.images.top": _images(64, True, seed=99)})
    assert unseen.mean() > 2 * seen.mean() and rnd.threshold() > 1
    rnd.save(tmp_path / "rnd")
    loaded = RND.load(tmp_path / "rnd")
    torch.testing.assert_close(
        loaded.u({"observation.images.top": _images(4, True, 5)}),
        rnd.u({"observation.images.top": _images(4, True, 5)}),
    )
    with pytest.raises(ValueError, match="shape"):
        rnd.error({"observation.images.top": torch.zeros(1, 3, 8, 8)})


def test_a_score_without_training_statistics_is_refused_before_any_rollout():
    from lerobot_vib.variants import rnd_score

    rnd = RND(RNDConfig(image_keys=[], state_key="observation.state", state_dim=3))  # never trained: e_bar NaN
    with pytest.raises(RuntimeError, match="no training statistics"):
        rnd_score(rnd)


def test_act_is_trained_with_the_vib_presets_augmentation_and_schedule(tmp_path):
    """ACT beside VIB sees the same images and learning rates: the preset's `dataset.image_transforms` and its
    warmup-and-cosine schedule reach ACT's training config, as `lerobot-train` parses both."""
    import draccus
    from lerobot.configs.train import TrainPipelineConfig

    preset = json.loads((Path(benchmark.__file__).parents[3] / "configs/policy/vib_arm_sim.json").read_text())
    preset["dataset"]["image_transforms"] = {
        "enable": True,
        "max_num_transforms": 1,
        "tfs": {"shift": {"weight": 1.0, "type": "RandomAffine", "kwargs": {"degrees": 0.0, "translate": [0.1, 0.1]}}},
    }
    preset["policy"].update(scheduler_warmup_steps=25, optimizer_lr=3e-4)
    (tmp_path / "preset.json").write_text(json.dumps(preset))
    vib = draccus.parse(TrainPipelineConfig, config_path=tmp_path / "preset.json", args=[])
    vib.optimizer, vib.scheduler = vib.policy.get_optimizer_preset(), vib.policy.get_scheduler_preset()
    flags = benchmark.act_recipe_flags(preset)
    act = draccus.parse(TrainPipelineConfig, args=["--policy.type=act", "--dataset.repo_id=local/x", *flags])

    assert act.dataset.image_transforms == vib.dataset.image_transforms
    assert act.dataset.image_transforms.tfs["shift"].kwargs["translate"] == [0.1, 0.1]
    assert not act.use_policy_training_preset
    assert act.optimizer == vib.optimizer and act.scheduler == vib.scheduler
    assert act.scheduler.num_warmup_steps == 25 and act.optimizer.lr == 3e-4
    assert act.policy.n_encoder_layers == preset["policy"]["n_layers"] and act.policy.chunk_size == 20


def test_queue_rows_keep_half_a_chunk_when_the_preset_ensembles():
    """The arm preset acts with ACT's ensembling (n_action_steps 1): the benchmark's queue rows still execute
    10 of 20 actions per chunk, as they did, for ACT and for VIB."""
    from helpers import make_config
    from lerobot_vib.modeling_vib import VIBPolicy
    from lerobot_vib.variants import vib_with

    preset = json.loads((Path(benchmark.__file__).parents[3] / "configs/policy/vib_arm_sim.json").read_text())
    assert (preset["policy"]["temporal_ensemble"], preset["policy"]["n_action_steps"]) == ("act", 1)
    assert "--policy.n_action_steps=10" in benchmark.act_recipe_flags(preset)
    policy = VIBPolicy(make_config(chunk_size=20, n_action_steps=1, temporal_ensemble="act"))
    assert vib_with(policy, "none").config.n_action_steps == 10
    assert vib_with(policy, "uncertainty").config.n_action_steps == 1


def test_a_sample_run_time_decodes_a_posterior_sample_and_is_offered_to_vib_rows_only(tmp_path):
    """ "act:0.3+sample": the VIB network decodes a posterior sample (its training input) at every step, so
    two calls on one observation differ; the posterior mean's do not, and an ACT row never gets the suffix."""
    from helpers import make_batch, make_config
    from lerobot_vib.modeling_vib import VIBPolicy
    from lerobot_vib.variants import build_variant, parse_runtime, split_runtime

    assert split_runtime("act:0.3+sample") == ("act:0.3", True) and split_runtime("queue") == ("queue", False)
    assert parse_runtime("act:0.3+sample") == ("act", 0.3)
    torch.manual_seed(0)
    network = VIBPolicy(make_config(encoder="tokens", chunk_size=4, n_action_steps=1))
    obs = make_batch(network.config, with_action=False)
    chunks = {}
    for runtime in ("act:0.3", "act:0.3+sample"):
        policy = build_variant("vib_tokens", {"vib_tokens": network}, runtime=runtime)
        chunks[runtime] = [policy.predict_action_chunk(obs) for _ in range(2)]
    assert torch.equal(*chunks["act:0.3"])
    assert not torch.allclose(*chunks["act:0.3+sample"])
    assert not network.config.sample_latent_at_inference  # the shared network is not changed

    cfg = BenchmarkConfig(
        dataset=DatasetConfig(repo_id="x"),
        env=ArmGraspEnvConfig(),
        output_dir=tmp_path,
        variants=["act_chosen", "vib_tokens"],
        runtimes=["act:0.3", "act:0.3+sample"],
    )
    assert cfg.validated("vib_tokens") == ["act:0.3", "act:0.3+sample"]
    assert cfg.validated("act_chosen") == ["act:0.3"]
    with pytest.raises(ValueError, match="chunks come from ACT"):
        build_variant("act_chosen", {"act": None}, runtime="act:0.3+sample")


def test_wall_time_counts_every_invocation_a_killed_one_included(tmp_path):
    import signal
    import subprocess
    import sys
    import time

    path = tmp_path / "wall_time.json"
    path.write_text(json.dumps({"seconds": 5.0}))  # finished invocations of an older version
    script = (
        "import sys, time; from pathlib import Path; from lerobot_vib.scripts.benchmark import WallClock\n"
        "WallClock(Path(sys.argv[1]), beat=0.05).__enter__(); time.sleep(600)\n"
    )
    proc = subprocess.Popen([sys.executable, "-c", script, str(path)])
    deadline = time.time() + 120
    while time.time() < deadline:
        record = json.loads(path.read_text())
        if record.get("invocations") and record["invocations"][-1]["end"] - record["invocations"][-1]["start"] > 1.0:
            break
        time.sleep(0.1)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    killed = benchmark.WallClock.total(path)
    assert killed >= 6.0  # 5 s from before, and the killed run up to its last beat

    with benchmark.WallClock(path, beat=0.05):
        time.sleep(0.3)
        running = json.loads(path.read_text())["invocations"][-1]
        assert running["end"] > running["start"] and not running["finished"]  # kept current while it runs
    record = json.loads(path.read_text())
    assert [i["finished"] for i in record["invocations"]] == [False, True]
    assert benchmark.WallClock.total(path) >= killed + 0.3


def test_the_token_comparison_trains_the_token_network_beside_the_same_act_rows_and_the_pooled_preset(tmp_path):
    cfg = BenchmarkConfig(
        dataset=DatasetConfig(repo_id="x"), env=ArmGraspEnvConfig(), output_dir=tmp_path, variants=["tokens"]
    )
    assert cfg.variants == [
        "act_chosen", "act_like_vib", "act_like_vib_nofloor", "vib_tokens_beta0", "vib_tokens", "vib_tokens_narrow",
        "vib_tokens_narrow_beta0", "vib_tokens_narrow_act_trunk", "vib_tokens_narrow_act_trunk_l3",
        "vib_tokens_narrow_act_trunk_l2", "vib_tokens_narrow_l3", "vib_tokens_narrow_act_trunk_l2_colour",
        "act_colour", "vib_chosen",
    ]  # fmt: skip
    networks = {
        "act", "act_like_vib", "act_like_vib_nofloor", "vib_tokens_beta0", "vib_tokens", "vib_tokens_narrow",
        "vib_tokens_narrow_beta0", "vib_tokens_narrow_act_trunk", "vib_tokens_narrow_act_trunk_l3",
        "vib_tokens_narrow_act_trunk_l2", "vib_tokens_narrow_l3", "vib_tokens_narrow_act_trunk_l2_colour",
        "act_colour", "vib",
    }  # fmt: skip
    assert set(cfg.networks()) == networks
    # the control: ACT + VIB's trunk and weight average with the normalization floor off, and only that
    like = benchmark.train_command("act_like_vib", cfg, tmp_path / "l", seed=1000)
    nofloor = benchmark.train_command("act_like_vib_nofloor", cfg, tmp_path / "l", seed=1000)
    assert "--policy.normalization_floor=null" in nofloor and "--policy.type=act_like_vib" in nofloor
    assert [a for a in like if "normalization_floor" not in a] == [a for a in nofloor if "normalization_floor" not in a]
    tokens = benchmark.train_command("vib_tokens", cfg, tmp_path / "t", seed=1000)
    beta0 = benchmark.train_command("vib_tokens_beta0", cfg, tmp_path / "t0", seed=1000)
    pooled = benchmark.train_command("vib", cfg, tmp_path / "p", seed=1000)
    assert "--policy.encoder=tokens" in tokens and "--policy.beta=0" not in tokens
    assert "--policy.encoder=tokens" in beta0 and "--policy.beta=0" in beta0
    assert not any("encoder" in a for a in pooled)
    assert cfg.episodes("vib_tokens", "normal") == cfg.n_episodes
    # the narrow start is the token preset with one flag more, and a row of its own when asked for
    narrow = benchmark.train_command("vib_tokens_narrow", cfg, tmp_path / "t", seed=1000)
    assert [a for a in narrow if "posterior_logvar_init" not in a] == tokens
    assert "--policy.posterior_logvar_init=-6.0" in narrow
    # its control: the same start with no pressure on the rate, and nothing else changed
    narrow0 = benchmark.train_command("vib_tokens_narrow_beta0", cfg, tmp_path / "t", seed=1000)
    assert [a for a in narrow0 if a != "--policy.beta=0"] == narrow and "--policy.beta=0" in narrow0
    # and the same start on ACT's trunk: the two trunk flags that make VIB's ResNet LeRobot ACT's, nothing else
    trunk = benchmark.train_command("vib_tokens_narrow_act_trunk", cfg, tmp_path / "t", seed=1000)
    flags = ["--policy.backbone_norm=frozen_bn", "--policy.backbone_layer=layer4"]
    assert [a for a in trunk if a not in flags] == narrow and all(f in trunk for f in flags)
    # and that trunk one stage shorter: the layer flag alone differs
    trunk3 = benchmark.train_command("vib_tokens_narrow_act_trunk_l3", cfg, tmp_path / "t", seed=1000)
    assert [a.replace("layer3", "layer4") for a in trunk3] == trunk
    # and at VIB's depth: again the layer flag alone
    trunk2 = benchmark.train_command("vib_tokens_narrow_act_trunk_l2", cfg, tmp_path / "t", seed=1000)
    assert [a.replace("layer2", "layer4") for a in trunk2] == trunk
    # the layer2 row on colour-randomized frames: the same flags plus LeRobot's image transforms, hue over the circle
    colour = benchmark.train_command("vib_tokens_narrow_act_trunk_l2_colour", cfg, tmp_path / "t", seed=1000)
    assert [a for a in colour if not a.startswith("--dataset.image_transforms.")] == trunk2
    assert "--dataset.image_transforms.enable=true" in colour
    (tfs,) = [a for a in colour if a.startswith("--dataset.image_transforms.tfs=")]
    assert json.loads(tfs.split("=", 1)[1])["hue"]["kwargs"]["hue"] == [-0.5, 0.5]
    # its control: LeRobot's ACT as the comparison trains it, plus the very same transform flags, nothing else
    act = benchmark.train_command("act", cfg, tmp_path / "a", seed=1000)
    act_colour = benchmark.train_command("act_colour", cfg, tmp_path / "a", seed=1000)
    transforms = [a for a in colour if a.startswith("--dataset.image_transforms.")]
    assert [a for a in act_colour if a not in transforms] == act and all(t in act_colour for t in transforms)
    assert "--policy.type=act" in act_colour
    # VIB's own trunk one stage deeper: the narrow start plus the layer flag, its normalization left as the preset's
    deeper = benchmark.train_command("vib_tokens_narrow_l3", cfg, tmp_path / "t", seed=1000)
    assert [a for a in deeper if a != "--policy.backbone_layer=layer3"] == narrow
    assert "--policy.backbone_layer=layer3" in deeper and not any("backbone_norm" in a for a in deeper)
    asked = BenchmarkConfig(
        dataset=DatasetConfig(repo_id="x"), env=ArmGraspEnvConfig(), output_dir=tmp_path, variants=["vib_tokens_narrow"]
    )
    assert asked.networks() == ["vib_tokens_narrow"]
    assert asked.episodes("vib_tokens_narrow", "normal") == asked.n_episodes  # a claim's row: the most episodes


def test_comparison_rows_train_their_own_networks_and_run_the_run_time_they_are_given(tmp_path):
    """vib_beta0 is the preset with beta = 0; act_like_vib copies the preset's trunk, average and floor; a row
    whose run time is chosen runs exactly the one it is given, and refuses to run without one."""
    from helpers import make_config
    from lerobot_vib.modeling_vib import VIBPolicy
    from lerobot_vib.variants import build_variant

    cfg = BenchmarkConfig(
        dataset=DatasetConfig(repo_id="x"), env=ArmGraspEnvConfig(), output_dir=tmp_path, variants=["comparison"]
    )
    assert cfg.variants == ["act_chosen", "act_like_vib", "vib_beta0", "vib_chosen"]
    assert cfg.networks() == ["vib", "vib_beta0", "act", "act_like_vib"]
    preset = json.loads(cfg.preset.read_text())["policy"]
    beta0 = benchmark.train_command("vib_beta0", cfg, tmp_path / "b", 2000)
    assert "--policy.beta=0" in beta0 and "--seed=2000" in beta0 and f"--config_path={cfg.preset}" in beta0
    like = benchmark.train_command("act_like_vib", cfg, tmp_path / "a", 1000)
    for field in ("backbone_norm", "backbone_layer", "ema_decay", "normalization_floor"):
        assert f"--policy.{field}={preset[field]}" in like
    assert "--policy.type=act_like_vib" in like and "--policy.type=act" in benchmark.train_command(
        "act", cfg, tmp_path, 1
    )

    vib = VIBPolicy(make_config(chunk_size=20, n_action_steps=1, temporal_ensemble="act"))
    with pytest.raises(ValueError, match="chosen on validation"):
        build_variant("vib_chosen", {"vib": vib})
    ensembling = build_variant("vib_chosen", {"vib": vib}, runtime="act:0.3")
    assert (ensembling.config.temporal_ensemble, ensembling.config.temporal_ensemble_coeff) == ("act", 0.3)
    queue = build_variant("vib_chosen", {"vib": vib}, runtime="queue")
    assert (queue.config.temporal_ensemble, queue.config.n_action_steps) == ("none", 10)
    with pytest.raises(ValueError, match="needs the VIB_BETA0"):
        build_variant("vib_beta0", {"vib": vib}, runtime="queue")


def test_invocations_side_by_side_each_keep_their_own_wall_time_record(tmp_path):
    """Two invocations on one output dir (say, one per group of rows) rewrite only their own records."""
    import threading
    import time

    path = tmp_path / "wall_time.json"
    done = threading.Event()

    def other():
        with benchmark.WallClock(path, beat=0.01):
            done.wait(5)

    thread = threading.Thread(target=other)
    with benchmark.WallClock(path, beat=0.01):
        thread.start()
        time.sleep(0.3)
        done.set()
        thread.join()
    record = json.loads(path.read_text())
    assert len(record["invocations"]) == 2 and all(i["finished"] for i in record["invocations"])
    assert all(i["end"] - i["start"] >= 0.25 for i in record["invocations"])


def test_invocations_side_by_side_train_a_network_once(tmp_path, monkeypatch):
    """Two invocations that need the same network: the second waits for the first's training and reuses it."""
    import subprocess
    import threading
    import time

    cfg = BenchmarkConfig(dataset=DatasetConfig(repo_id="x"), env=ArmGraspEnvConfig(), output_dir=tmp_path, steps=2)
    trainings = []

    def fake_training(cmd, **kwargs):
        trainings.append(cmd)
        time.sleep(0.3)  # long enough for the other invocation to arrive meanwhile
        out = Path(next(a for a in cmd if a.startswith("--output_dir=")).split("=", 1)[1])
        (out / "checkpoints/000002/pretrained_model").mkdir(parents=True)
        return subprocess.CompletedProcess(cmd, 0)

    monkeypatch.setattr(benchmark.subprocess, "run", fake_training)
    paths = []
    threads = [threading.Thread(target=lambda: paths.append(benchmark.train("vib", cfg, 1000))) for _ in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(trainings) == 1 and len(paths) == 2 and paths[0] == paths[1]


def test_an_invocation_on_act_rows_alone_keeps_the_score_statistics_vib_rows_wrote(tmp_path):
    """Invocations side by side on one seed each record their networks' scores; none erases another's."""
    path = tmp_path / "scores" / "seed_1000.json"
    benchmark._merge_json(path, {"vib": {"mean": 1.0}}, tmp_path)
    benchmark._merge_json(path, {}, tmp_path)  # ACT's rows: no score
    benchmark._merge_json(path, {"vib_beta0": {"mean": 2.0}}, tmp_path)
    assert json.loads(path.read_text()) == {"vib": {"mean": 1.0}, "vib_beta0": {"mean": 2.0}}


def test_every_scores_auroc_reads_the_occluders_own_steps_and_counts_an_unknown_u_as_highest():
    from lerobot_vib.sim.perturbations import CONDITIONS, draw_scene_episode

    seeds = [600000, 600001, 600002]
    windows = [draw_scene_episode(CONDITIONS["occlusion"], s).occluded_steps for s in seeds]
    clean = [[1.0] * 100 for _ in seeds]
    # u rises only while the board is in view: over the whole episode it would be diluted by clean frames
    occluded = [[2.0 if t in w else 1.0 for t in range(100)] for w in windows]
    black = [[float("nan")] * 100 for _ in seeds]
    cells = {
        "normal": {"seeds": seeds, "scores": {"low_map_score": clean}},
        "occlusion": {"seeds": seeds, "scores": {"low_map_score": occluded}},
        "black": {"seeds": seeds, "scores": {"low_map_score": black}},
    }
    every = benchmark_report.score_aurocs(cells)["low_map_score"]
    assert every == {"occlusion": 1.0, "black": 1.0}


def test_each_traced_score_gets_its_own_offline_stop_and_only_the_one_that_rises_under_the_board_stops_it():
    from lerobot_vib.sim.perturbations import CONDITIONS, draw_scene_episode

    rng = np.random.default_rng(0)
    seeds = list(range(600000, 600020))
    windows = [draw_scene_episode(CONDITIONS["occlusion"], s).occluded_steps for s in seeds]

    def clean() -> list[list[float]]:
        return (1.0 + 0.05 * rng.random((len(seeds), 100))).tolist()

    occluded = [[3.0 if t in w else 1.0 for t in range(100)] for w in windows]
    cells = {
        "normal": {"seeds": seeds, "u": clean(), "scores": {"rises": clean(), "blind": clean()}},
        "occlusion": {"seeds": seeds, "u": clean(), "scores": {"rises": occluded, "blind": clean()}},
    }
    calibration = {"u": clean(), "scores": {"rises": clean(), "blind": clean()}}
    stops = benchmark_report.score_stops(cells, calibration, alpha=0.1)
    entered = sum(w.start < 100 for w in windows)
    assert stops["rises"]["conformal"]["in_time"] == stops["rises"]["conformal"]["occlusion_stops"] == entered
    assert stops["rises"]["conformal"]["delays"] == [0] * entered
    assert stops["blind"]["conformal"]["in_time"] == 0
    assert set(stops["rises"]) == {"conformal", "band", "std_band"}  # 20 rollouts: enough for both bands at alpha 0.1
    lines = benchmark_report.score_stop_table({"vib_tokens": {"1000": {"score_stops": stops}}}, 0.1)
    assert any("| rises | conformal |" in line for line in lines)


def test_the_score_is_chosen_on_validation_and_one_that_stops_clean_rollouts_too_often_is_passed_over():
    from lerobot_vib.sim.perturbations import CONDITIONS, draw_scene_episode

    rng = np.random.default_rng(1)
    clean_seeds, occluded_seeds = list(range(400000, 400040)), list(range(400000, 400020))
    windows = [draw_scene_episode(CONDITIONS["occlusion"], s).occluded_steps for s in occluded_seeds]
    quiet = (1.0 + 0.05 * rng.random((40, 100))).tolist()
    # "jumpy" catches every occlusion but its clean rollouts in the judged half spike above anything it was set on
    jumpy = [[5.0 if i >= 20 and i % 3 == 0 and t == 50 else x for t, x in enumerate(row)] for i, row in
             enumerate(quiet)]  # fmt: skip
    board = [[3.0 if t in w else 1.0 for t in range(100)] for w in windows]
    late = [[3.0 if t in w and t >= w.start + 8 else 1.0 for t in range(100)] for w in windows]  # never in time
    calibration = {"seeds": clean_seeds, "u": quiet, "scores": {"jumpy": jumpy, "steady": quiet}}
    occluded = {"seeds": occluded_seeds, "u": board, "scores": {"jumpy": board, "steady": late}}
    choice = benchmark_report.choose_score_on_validation(calibration, occluded, alpha=0.1)
    assert choice["score"] == "steady" and (choice["n_set"], choice["n_judged"]) == (20, 20)
    assert benchmark_report.choose_score_on_validation(calibration, None, alpha=0.1) is None


def test_a_score_that_is_zero_at_some_step_has_no_band_and_says_so():
    calibration = {"u": [[0.0, 1.0, 1.0]] * 40}
    gammas = benchmark_report.thresholds(calibration, None, 0.1)
    assert gammas["band"] is None and gammas["std_band"] is None and gammas["conformal"] == 1.0
    assert any("no band" in note for note in gammas["notes"])
    assert any("no std band" in note for note in gammas["notes"])


def test_the_shipped_checkpoint_stops_as_the_report_measured_and_its_card_says_what_it_predicted(
    arm_data, tmp_path, monkeypatch
):
    """The report's monitor goes into a checkpoint through lerobot-vib-calibrate's own threshold code, on the
    successful clean validation rollouts; its test TPR / TNR land in the calibration and the model card."""
    import numpy as np

    from lerobot_vib.failure import AnyOf, Monitor, calibrate_monitor, evaluate
    from lerobot_vib.modeling_vib import VIBPolicy
    from lerobot_vib.scripts.failure_report import cell_episodes

    cfg = tiny_config(arm_data, tmp_path / "bench", variants=["vib"], alpha=0.1)
    source = benchmark.calibrated("vib", cfg, 1000, benchmark.train("vib", cfg, 1000))
    rng = np.random.default_rng(0)

    def cell(condition: str, seeds: range, success: list[bool]) -> dict:
        def trace(ok: bool) -> list[float]:
            return (np.r_[np.ones(10), np.full(10, 1.0 if ok else 3.0)] + 0.1 * rng.random(20)).tolist()

        return {"condition": condition, "seeds": list(seeds), "success": success,
                "scores": {"rate": [trace(ok) for ok in success], "embedding_rnd": [trace(ok) for ok in success]},
                "grasp_missed_at": [None if ok else 15 for ok in success]}  # fmt: skip

    validation = cell("validation", range(400_000, 400_030), [i % 3 != 0 for i in range(30)])
    tests = {"normal": cell("normal", range(600_000, 600_010), [i % 2 == 0 for i in range(10)]),
             "occlusion": cell("occlusion", range(600_000, 600_010), [False] * 10)}  # fmt: skip
    cells = {("vib", "validation", 1000, "eq6:0.01"): validation}
    cells.update({("vib", c, 1000, None): x for c, x in tests.items()})
    monitor = Monitor(("rate", "embedding_rnd"), window=5)
    results = {"failure_prediction": {"vib": {"shipped": {"monitor": monitor.as_dict()}}}}
    [out] = benchmark.ship_checkpoints(cfg, cells, results)

    assert out == cfg.output_dir / "shipped" / "vib" / "seed_1000"
    policy = VIBPolicy.from_pretrained(out)
    c = policy.config.calibration
    report = calibrate_monitor(monitor, cell_episodes(validation), 0.1)  # the report's own calibration
    assert policy.config.uncertainty_score == "rate" and c.gamma_score == "rate" and c.rollout_episodes == "successes"
    assert (c.window, c.window_aggregate) == (5, "mean") and c.gamma_band is None
    assert c.gamma == pytest.approx(report.thresholds["rate"])
    assert c.and_gammas == {"embedding_rnd": pytest.approx(report.thresholds["embedding_rnd"])}
    assert c.rollout_successes == 20 and len(c.rollout_seeds) == 30
    measured = evaluate(report, [e for x in tests.values() for e in cell_episodes(x)])
    assert c.monitor_metrics["tpr"] == measured.tpr == 1.0 and c.monitor_metrics["n_failed"] == 15
    assert c.monitor_metrics["tnr"] == measured.tnr and "test seeds 600000-600009" in c.monitor_measured_on
    assert (policy.config.temporal_ensemble, policy.config.safety.enabled) == ("uncertainty", False)  # eq6:0.01
    from huggingface_hub import ModelCard

    monkeypatch.setattr(ModelCard, "validate", lambda self, *a, **k: None)  # validation is an online call
    card = policy.generate_model_card("local/arm", "vib", None, None).text
    assert "As a failure predictor" in card and "TPR 1.00" in card
    assert benchmark.ship_checkpoints(cfg, cells, results) == [out]  # its own output is rewritten
    # an OR ships the same way: its first member is the stop's own score, the others its OR partners
    either = AnyOf((Monitor(("rate",), window=5), Monitor(("embedding_rnd",))))  # 20 successes: 19 at alpha / 2
    or_results = {"failure_prediction": {"vib": {"shipped": {"monitor": either.as_dict()}}}}
    assert benchmark.ship_checkpoints(cfg, cells, or_results) == [out]
    c = VIBPolicy.from_pretrained(out).config.calibration
    report = calibrate_monitor(either, cell_episodes(validation), 0.1)
    assert c.gamma == pytest.approx(report.members[0].thresholds["rate"]) and c.window == 5
    assert c.and_gammas == {} and c.or_window == 1
    assert c.or_gammas == {"embedding_rnd": pytest.approx(report.members[1].thresholds["embedding_rnd"])}
    assert c.monitor_metrics["tpr"] == evaluate(report, [e for x in tests.values() for e in cell_episodes(x)]).tpr
    benchmark.ship_checkpoints(cfg, cells, results)
    (out / "config.json").write_text("{}")  # not a checkpoint it shipped: left alone, said so
    with pytest.raises(VIBConfigError, match="not a checkpoint this benchmark shipped"):
        benchmark.ship_checkpoints(cfg, cells, results)
    assert (out / "config.json").read_text() == "{}"
    source_config = json.loads((source / "config.json").read_text())["calibration"]
    assert source_config["monitor_metrics"] == {} and source_config["gamma"] != c.gamma  # the source is untouched
