"""VIB through LeRobot's own entry points: plugin discovery, lerobot-train, from_pretrained, lerobot-eval,
multi-process training and the files a Hub push would upload."""

from __future__ import annotations

import json
import sys
import textwrap
from pathlib import Path

import pytest
import torch
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot.policies.factory import make_pre_post_processors
from safetensors.torch import load_file

from helpers import BIN, TRAIN_ARGS, make_batch, make_config, run
from lerobot_vib.modeling_vib import VIBPolicy
from tiny_dataset import write_tiny_dataset


@pytest.fixture(scope="module")
def aloha_like_dataset(tmp_path_factory) -> Path:
    """gym-aloha's features: one 480x640 `top` camera, 14-d state and action."""
    root = tmp_path_factory.mktemp("aloha_like") / "ds"
    write_tiny_dataset(
        root, repo_id="local/aloha_like", cameras={"top": (480, 640)}, n_episodes=1, frames_per_episode=16
    )
    return root


@pytest.fixture(scope="module")
def trained(aloha_like_dataset, tmp_path_factory) -> tuple[Path, str]:
    """A lerobot-train run of 3 steps; returns (checkpoint dir, its log)."""
    out_dir = tmp_path_factory.mktemp("train") / "run"
    log = run(
        [
            str(BIN / "lerobot-train"),
            *TRAIN_ARGS,
            "--dataset.repo_id=local/aloha_like",
            f"--dataset.root={aloha_like_dataset}",
            "--steps=3",
            "--save_freq=3",
            f"--output_dir={out_dir}",
        ]
    )
    return out_dir / "checkpoints" / "last" / "pretrained_model", log


def test_plugin_is_discovered_in_a_fresh_process():
    code = textwrap.dedent(
        """
        import torch
        from lerobot.configs.policies import PreTrainedConfig
        from lerobot.configs.types import FeatureType, PolicyFeature
        from lerobot.policies.factory import get_policy_class, make_policy_config, make_pre_post_processors
        from lerobot.processor import NormalizerProcessorStep, UnnormalizerProcessorStep
        from lerobot.utils.import_utils import register_third_party_plugins

        assert "vib" not in PreTrainedConfig.get_known_choices(), "vib registered before discovery"
        register_third_party_plugins()
        cls = get_policy_class("vib")
        from lerobot_vib.modeling_vib import VIBPolicy
        assert cls is VIBPolicy, cls
        cfg = make_policy_config(
            "vib", device="cpu",
            input_features={"observation.state": PolicyFeature(FeatureType.STATE, (4,))},
            output_features={"action": PolicyFeature(FeatureType.ACTION, (2,))},
        )
        stats = {"observation.state": {"mean": torch.zeros(4), "std": torch.ones(4)},
                 "action": {"mean": torch.zeros(2), "std": torch.ones(2)}}
        pre, post = make_pre_post_processors(cfg, dataset_stats=stats)
        assert any(isinstance(s, NormalizerProcessorStep) for s in pre.steps), pre.steps
        assert any(isinstance(s, UnnormalizerProcessorStep) for s in post.steps), post.steps
        print("OK", cls.__module__)
        """
    )
    out = run([sys.executable, "-c", code])
    assert "OK lerobot_vib.modeling_vib" in out


def test_lerobot_train_logs_l1_and_rate(trained):
    _, log = trained
    assert "l1_loss:" in log and "rate:" in log


def test_from_pretrained_loads_every_tensor_of_the_checkpoint(trained, aloha_like_dataset):
    ckpt, _ = trained
    loaded = VIBPolicy.from_pretrained(ckpt, strict=True)  # strict: a missing or extra key fails
    assert not loaded.training
    saved = load_file(ckpt / "model.safetensors")
    state = loaded.state_dict()
    assert set(saved) == set(state)
    for key, value in saved.items():  # NaN marks what is not fitted yet (the scores before calibration)
        assert torch.equal(state[key].isnan(), value.isnan()), key
        assert torch.equal(state[key].nan_to_num(), value.nan_to_num()), key

    # The checkpoint's own processors normalize a dataset frame; the policy acts on it.
    pre, post = make_pre_post_processors(loaded.config, pretrained_path=str(ckpt))
    frame = LeRobotDataset("local/aloha_like", root=aloha_like_dataset)[0]
    obs = pre({k: v for k, v in frame.items() if k.startswith("observation")})
    action = post(loaded.select_action(obs))
    assert action.shape == (1, 14) and torch.isfinite(action).all()


def test_save_then_from_pretrained_gives_identical_actions(tmp_path):
    """Train a few steps in process, then compare the trained policy with its reloaded copy."""
    config = make_config(cameras={"top": (3, 32, 32), "wrist": (3, 32, 32)})
    policy = VIBPolicy(config)
    optimizer = torch.optim.AdamW(policy.get_optim_params(), lr=1e-3)
    policy.train()
    for step in range(3):
        loss, _ = policy.forward(make_batch(config, batch_size=4, seed=step))
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    policy.eval()
    obs = make_batch(config, batch_size=3, with_action=False, seed=99)
    expected = policy.predict_action_chunk(obs)
    expected_rate = policy.last_rate

    policy.save_pretrained(tmp_path)
    loaded = VIBPolicy.from_pretrained(tmp_path, strict=True)
    assert torch.equal(loaded.predict_action_chunk(obs), expected)
    assert torch.equal(loaded.last_rate, expected_rate)
    assert not torch.equal(VIBPolicy(config).eval().predict_action_chunk(obs), expected)  # the test can fail


@pytest.mark.parametrize(
    "flags",
    [
        ["--env.type=aloha", "--eval.n_episodes=1", "--eval.batch_size=1"],
        # a batch of two subprocess envs, as LeRobot's eval defaults to on a machine with several cores
        ["--env.type=aloha_fast", "--eval.n_episodes=2", "--eval.batch_size=2", "--eval.use_async_envs=true"],
    ],
)
def test_lerobot_eval_runs_aloha_episodes(flags, trained, tmp_path):
    ckpt, _ = trained
    out = tmp_path / "eval"
    run(
        [
            str(BIN / "lerobot-eval"),
            f"--policy.path={ckpt}",
            "--policy.device=cpu",
            "--env.task=AlohaTransferCube-v0",
            "--env.episode_length=3",
            *flags,
            f"--output_dir={out}",
        ]
    )
    info = json.loads((out / "eval_info.json").read_text())
    assert info["overall"]["n_episodes"] == int(flags[1].split("=")[1])


def test_two_process_ddp_training(tiny_dataset_root, tmp_path):
    """LeRobot's multi-process path (Accelerate on a torchrun launch, gloo on CPU) trains VIB."""
    out_dir = tmp_path / "ddp"
    log = run(
        [
            str(BIN / "torchrun"),
            "--nproc_per_node=2",
            str(BIN / "lerobot-train"),
            *TRAIN_ARGS,
            "--dataset.repo_id=local/tiny",
            f"--dataset.root={tiny_dataset_root}",
            "--steps=2",
            "--save_freq=2",
            f"--output_dir={out_dir}",
        ]
    )
    assert "Effective batch size: 2 x 2 = 4" in log
    assert (out_dir / "checkpoints" / "last" / "pretrained_model" / "model.safetensors").exists()


def fake_hub(monkeypatch, repo_id: str) -> list[dict[str, str]]:
    """Offline: the Hub client intercepted; returns the folders it was asked to upload, file name -> text."""
    from huggingface_hub import HfApi, ModelCard

    uploads: list[dict[str, str]] = []

    class Repo:
        pass

    Repo.repo_id = repo_id

    def fake_upload_folder(self, *, folder_path, **kwargs):
        files = {p.name: p for p in Path(folder_path).iterdir() if p.is_file()}
        uploads.append({name: (p.read_text() if p.suffix in (".md", ".json") else "") for name, p in files.items()})

        class Info:
            class repo_url:  # noqa: N801
                url = f"https://huggingface.co/{repo_id}"

        return Info()

    monkeypatch.setattr(HfApi, "create_repo", lambda self, *a, **k: Repo())
    monkeypatch.setattr(HfApi, "upload_folder", fake_upload_folder)
    monkeypatch.setattr(ModelCard, "validate", lambda self, *a, **k: None)  # validation is an online call
    return uploads


def test_hub_push_uploads_weights_config_processors_and_a_model_card(trained, monkeypatch):
    """Offline: intercept the Hub client and check the folder LeRobot would upload."""
    from lerobot.configs.train import TrainPipelineConfig

    ckpt, _ = trained
    uploads = fake_hub(monkeypatch, "user/vib_test")

    policy = VIBPolicy.from_pretrained(ckpt)
    policy.config.repo_id = "user/vib_test"
    cfg = TrainPipelineConfig.from_pretrained(ckpt)
    policy.push_model_to_hub(cfg)
    pre, post = make_pre_post_processors(policy.config, pretrained_path=str(ckpt))
    pre.push_to_hub("user/vib_test")
    post.push_to_hub("user/vib_test")

    model_files = uploads[0]
    assert {"model.safetensors", "config.json", "train_config.json", "README.md"} <= set(model_files)
    assert json.loads(model_files["config.json"])["type"] == "vib"
    card = model_files["README.md"]
    assert "vib" in card and "not on PyPI" in card and "Information Bottleneck" in card
    assert "pip install lerobot_policy_vib" not in card  # no registry has it
    processor_files = set(uploads[1]) | set(uploads[2])
    assert {"policy_preprocessor.json", "policy_postprocessor.json"} <= processor_files


def test_a_calibrated_checkpoint_is_pushed_with_its_card_and_measured_success(trained, monkeypatch, tmp_path):
    """lerobot-train pushes the uncalibrated model; `lerobot-vib-calibrate --push_to_hub=true` the calibrated one."""
    import shutil

    from lerobot_vib.scripts.calibrate import push_calibrated

    ckpt = tmp_path / "pretrained_model_calibrated"
    shutil.copytree(trained[0], ckpt)
    config = json.loads((ckpt / "config.json").read_text())
    config["calibration"].update(
        rate_mean=2.0, rate_std=0.5, gamma=1.3, gamma_method="conformal_rollouts", conformal_alpha=0.1,
        rollout_seeds=list(range(500, 520)), rollout_successes=15,
    )  # fmt: skip
    (ckpt / "config.json").write_text(json.dumps(config))
    uploads = fake_hub(monkeypatch, "user/vib_calibrated")
    push_calibrated(ckpt, "user/vib_calibrated")
    model = uploads[0]
    assert json.loads(model["config.json"])["calibration"]["gamma"] == 1.3
    card = model["README.md"]
    assert "| 20 | 15 | 75% |" in card and "success_rate" in card and "Measured: 15/20 clean rollouts" in card
    assert {"policy_preprocessor.json", "policy_postprocessor.json"} <= set(uploads[1]) | set(uploads[2])


def test_calibrate_refuses_to_push_offline_before_any_work(tmp_path):
    import subprocess

    proc = subprocess.run(
        [str(BIN / "lerobot-vib-calibrate"), f"--policy.path={tmp_path}", "--rollouts=x.json",
         "--conformal_alpha=0.1", "--push_to_hub=true", "--repo_id=user/name"],
        capture_output=True, text=True, timeout=300, env={**__import__("os").environ, "HF_HUB_OFFLINE": "1"},
    )  # fmt: skip
    assert proc.returncode != 0 and "Traceback" not in proc.stderr
    assert "the Hub is offline" in proc.stderr.strip().splitlines()[-1]
