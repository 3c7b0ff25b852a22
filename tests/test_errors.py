"""Bad configs, bad features and bad batches fail early with an error that names the problem."""

import urllib.error

import pytest
import torch
from lerobot.configs.types import FeatureType, PolicyFeature

from helpers import make_batch, make_config, with_rate_statistics
from lerobot_vib.configuration_vib import VIBConfig, VIBConfigError
from lerobot_vib.modeling_vib import VIBPolicy


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (dict(n_action_steps=10, chunk_size=5), "n_action_steps"),
        (dict(vision_backbone="vit_b_16"), "vision_backbone"),
        (dict(image_pooling="max"), "image_pooling"),
        (dict(position_embedding="rotary"), "position_embedding"),
        (dict(n_obs_steps=2), "n_obs_steps"),
        (dict(n_state_tokens=0), "n_state_tokens"),
        (dict(dim_model=30, n_heads=4), "divisible"),
        (dict(beta=-1.0), "beta"),
    ],
)
def test_bad_config_values(overrides, message):
    with pytest.raises(VIBConfigError, match=message):
        make_config(**overrides)


def test_no_camera_and_no_state():
    config = make_config(cameras={}, state_dim=None)
    with pytest.raises(ValueError, match="at least one camera"):
        VIBPolicy(config)


def test_cameras_of_different_shapes():
    config = make_config(cameras={"top": (3, 32, 32), "wrist": (3, 24, 32)})
    with pytest.raises(ValueError, match=r"same .* shape.*top.*wrist"):
        VIBPolicy(config)


def test_no_action_output():
    config = make_config()
    config.output_features = {}
    with pytest.raises(ValueError, match="`action` output"):
        VIBPolicy(config)


def test_state_under_another_name():
    config = VIBConfig(
        device="cpu",
        input_features={"observation.joints": PolicyFeature(FeatureType.STATE, (5,))},
        output_features={"action": PolicyFeature(FeatureType.ACTION, (3,))},
    )
    with pytest.raises(ValueError, match="rename_map"):
        config.validate_features()


@pytest.fixture(scope="module")
def policy():
    return with_rate_statistics(VIBPolicy(make_config(cameras={"top": (3, 32, 32)}, state_dim=5)))


def test_missing_camera_in_observation_fails_before_any_action(policy):
    obs = make_batch(policy.config, with_action=False)
    del obs["observation.images.top"]
    policy.reset()
    with pytest.raises(KeyError, match=r"observation\.images\.top"):
        policy.select_action(obs)
    assert policy.last_step is None and policy.runtime.last_command is None


def test_wrong_image_shape_fails_before_any_action(policy):
    obs = make_batch(policy.config, with_action=False)
    obs["observation.images.top"] = torch.rand(2, 3, 64, 64)
    policy.reset()
    for call in (policy.select_action, policy.predict_action_chunk):
        with pytest.raises(ValueError, match=r"observation.images.top.*\(2, 3, 64, 64\).*\(batch, 3, 32, 32\)"):
            call(obs)
    assert policy.last_step is None and policy.runtime.last_command is None


def test_unbatched_state(policy):
    obs = make_batch(policy.config, with_action=False)
    obs["observation.state"] = torch.rand(5)
    with pytest.raises(ValueError, match=r"observation\.state"):
        policy.predict_action_chunk(obs)


def test_mismatched_batch_sizes(policy):
    obs = make_batch(policy.config, with_action=False)
    obs["observation.state"] = torch.rand(3, 5)
    with pytest.raises(ValueError, match="batch size"):
        policy.predict_action_chunk(obs)


def test_training_batch_without_action(policy):
    batch = make_batch(policy.config)
    del batch["action"]
    with pytest.raises(KeyError, match="action"):
        policy.forward(batch)


def test_training_batch_with_wrong_chunk_length(policy):
    batch = make_batch(policy.config)
    batch["action"] = batch["action"][:, :3]
    with pytest.raises(ValueError, match="chunk_size"):
        policy.forward(batch)


@pytest.mark.parametrize("key", ["observation.images.top", "observation.state", "action"])
def test_training_batch_with_nan(policy, key):
    batch = make_batch(policy.config)
    batch[key].view(-1)[0] = float("nan")
    with pytest.raises(ValueError, match=f"non-finite.*{key}"):
        policy.forward(batch)


def test_bad_reduction(policy):
    with pytest.raises(ValueError, match="reduction"):
        policy.forward(make_batch(policy.config), reduction="sum")


def test_offline_imagenet_weights_error_names_the_fix(monkeypatch):
    def offline(*args, **kwargs):
        raise urllib.error.URLError("no network")

    monkeypatch.setattr(torch.hub, "load_state_dict_from_url", offline)
    config = make_config(pretrained_backbone_weights="ResNet18_Weights.IMAGENET1K_V1")
    with pytest.raises(RuntimeError, match=r"--policy.pretrained_backbone_weights=null"):
        VIBPolicy(config)


def test_from_pretrained_does_not_fetch_imagenet_weights(monkeypatch, tmp_path):
    """The checkpoint holds the trained backbone: loading it must work offline with the ImageNet default."""
    config = make_config(backbone_norm="frozen_bn")
    policy = VIBPolicy(config).eval()
    policy.config.pretrained_backbone_weights = "ResNet18_Weights.IMAGENET1K_V1"
    policy.save_pretrained(tmp_path)

    def offline(*args, **kwargs):
        raise urllib.error.URLError("no network")

    monkeypatch.setattr(torch.hub, "load_state_dict_from_url", offline)
    loaded = VIBPolicy.from_pretrained(tmp_path)
    assert loaded.config.pretrained_backbone_weights == "ResNet18_Weights.IMAGENET1K_V1"
    obs = make_batch(config, with_action=False)
    torch.testing.assert_close(loaded.predict_action_chunk(obs), policy.predict_action_chunk(obs))


@pytest.mark.parametrize(
    ("flag", "message"),
    [
        ("--policy.beta=-1", "`beta` must be >= 0, got -1"),
        ("--policy.temporal_ensemble=bogus", "`temporal_ensemble` must be one of ('none', 'act', 'uncertainty')"),
        ("--policy.safety.action=bogus", "`safety.action` must be one of ('hold', 'home')"),
        ("--policy.calibration.gamma=-1", "`calibration.gamma` must be a positive finite number"),
    ],
)
def test_bad_values_are_named_on_the_command_line(flag, message, tmp_path):
    """draccus would otherwise print only "Couldn't instantiate class VIBConfig"."""
    import subprocess

    from helpers import BIN

    proc = subprocess.run(
        [
            str(BIN / "lerobot-train"),
            "--policy.type=vib",
            flag,
            "--dataset.repo_id=local/x",
            f"--output_dir={tmp_path}",
        ],
        capture_output=True,
        text=True,
        env={**__import__("os").environ, "HF_HUB_OFFLINE": "1"},
        timeout=300,
    )
    assert proc.returncode != 0 and message in proc.stderr, proc.stderr[-2000:]


@pytest.mark.parametrize("dtype", [torch.uint8, torch.float64])
def test_observations_of_the_wrong_dtype_name_key_and_dtype(policy, dtype):
    obs = make_batch(policy.config, with_action=False)
    obs["observation.images.top"] = (obs["observation.images.top"] * 255).to(dtype)
    with pytest.raises(
        TypeError, match=rf"`observation.images.top` has dtype {dtype}; the policy expects torch.float32"
    ):
        policy.select_action(obs)


@pytest.mark.parametrize("every_step", [True, False])
def test_a_batch_size_change_without_reset_is_an_error(every_step):
    """It used to return the old batch's queued (2, action_dim) action for a batch of 1."""
    policy = with_rate_statistics(VIBPolicy(make_config(uncertainty_every_step=every_step)))
    policy.select_action(make_batch(policy.config, batch_size=2, with_action=False))
    with pytest.raises(ValueError, match=r"batch size changed from 2 to 1.*reset"):
        policy.select_action(make_batch(policy.config, batch_size=1, with_action=False))
    policy.reset()
    assert policy.select_action(make_batch(policy.config, batch_size=1, with_action=False)).shape == (1, 3)


@pytest.mark.parametrize("gamma", [-1.0, 0.0, float("nan"), float("inf")])
def test_a_threshold_that_could_never_resume_is_refused(gamma):
    from lerobot_vib.configuration_vib import CalibrationConfig, SafetyConfig

    with pytest.raises(VIBConfigError, match=r"calibration\.gamma"):
        CalibrationConfig(gamma=gamma)
    with pytest.raises(VIBConfigError, match=r"safety\.gamma"):
        SafetyConfig(enabled=True, gamma=gamma)


def test_a_threshold_below_the_training_mean_warns_at_episode_start(caplog):
    config = make_config()
    config.safety.enabled, config.safety.gamma = True, 0.5
    policy = with_rate_statistics(VIBPolicy(config))
    with caplog.at_level("WARNING"):
        policy._start_episode()  # what the first `select_action` of an episode does
    assert "gamma = 0.5 is below 1" in caplog.text


def test_a_truncated_checkpoint_names_the_file_and_the_cause(tmp_path):
    policy = VIBPolicy(make_config()).eval()
    policy.save_pretrained(tmp_path)
    weights = tmp_path / "model.safetensors"
    weights.write_bytes(weights.read_bytes()[: weights.stat().st_size // 3])
    with pytest.raises(VIBConfigError, match=r"model\.safetensors: the file is damaged or only partly downloaded"):
        VIBPolicy.from_pretrained(tmp_path)
