"""The normalization floor: a feature the demonstrations never vary cannot blow up the inputs or u."""

import logging

import numpy as np
import pytest
import torch
from lerobot.configs.types import NormalizationMode
from lerobot.utils.constants import ACTION, OBS_STATE

from helpers import make_config
from lerobot_vib.configuration_vib import SafetyConfig
from lerobot_vib.modeling_vib import VIBPolicy
from lerobot_vib.normalization import floor_stats, near_constant_vectors, scale_floor
from lerobot_vib.processor_vib import make_vib_pre_post_processors

# The arm's recording: joint 3 never moves (std 0.00015 rad); the other joints move 0.1-0.3 rad.
ARM_STATE_STD = [0.095, 0.179, 0.159, 0.000147, 0.195, 0.292, 0.216]


def arm_stats(n: int = 7) -> dict:
    std = np.array(ARM_STATE_STD[:n], dtype=np.float32)
    vec = {"mean": np.zeros(n, np.float32), "std": std, "min": -3 * std, "max": 3 * std}
    image = {
        "mean": np.full((3, 1, 1), 0.4, np.float32),
        "std": np.full((3, 1, 1), 0.2, np.float32),
        "min": np.zeros((3, 1, 1), np.float32),
        "max": np.ones((3, 1, 1), np.float32),
    }
    return {OBS_STATE: dict(vec), ACTION: dict(vec), "observation.images.top": image}


def test_the_floor_lifts_only_the_never_moved_joint():
    floored = scale_floor(torch.tensor(ARM_STATE_STD, dtype=torch.float64), 0.1)
    median = float(np.median(ARM_STATE_STD))
    assert floored[3] == pytest.approx(0.1 * median)
    others = [i for i in range(7) if i != 3]
    assert torch.equal(floored[others], torch.tensor(ARM_STATE_STD, dtype=torch.float64)[others])


def test_a_feature_with_no_spread_at_all_is_centred_not_scaled():
    assert torch.equal(scale_floor(torch.zeros(4), 0.1), torch.ones(4))
    assert torch.equal(scale_floor(torch.tensor([1e-9]), 0.1), torch.tensor([1e-9]))  # 1-d: nothing to compare


def test_min_max_ranges_widen_about_their_midpoints():
    config = make_config(
        state_dim=7, normalization_mapping={"VISUAL": "MEAN_STD", "STATE": "MIN_MAX", "ACTION": "MEAN_STD"}
    )
    stats, changed = floor_stats(arm_stats(), config.input_features, config.normalization_mapping, 0.1)
    low, high = stats[OBS_STATE]["min"], stats[OBS_STATE]["max"]
    ranges = 6 * np.array(ARM_STATE_STD)
    assert high[3] - low[3] == pytest.approx(0.1 * np.median(ranges), rel=1e-5)
    assert (high[3] + low[3]) / 2 == pytest.approx(0.0, abs=1e-7)
    assert [c.key for c in changed] == [OBS_STATE] and changed[0].dims == [3]


def test_a_tiny_deviation_of_a_never_moved_joint_stays_a_small_input_with_the_floor():
    config = make_config(state_dim=7, action_dim=7, cameras={"top": (3, 32, 32)})
    deviated = {OBS_STATE: torch.zeros(1, 7), "observation.images.top": torch.rand(1, 3, 32, 32)}
    deviated[OBS_STATE][0, 3] = 0.01  # 0.6 degrees
    pre, _ = make_vib_pre_post_processors(config, arm_stats())
    z = pre(dict(deviated))[OBS_STATE][0, 3]
    assert abs(float(z)) < 1.0
    config.normalization_floor = None  # LeRobot's statistics as they are
    pre_raw, _ = make_vib_pre_post_processors(config, arm_stats())
    assert abs(float(pre_raw(dict(deviated))[OBS_STATE][0, 3])) > 50


def test_training_names_the_near_constant_features(caplog):
    config = make_config(state_dim=7, action_dim=7)
    with caplog.at_level(logging.WARNING):
        make_vib_pre_post_processors(config, arm_stats())
    assert "near-constant" in caplog.text and "`observation.state` [3]" in caplog.text and "`action` [3]" in caplog.text


def test_a_recording_names_its_near_constant_vectors():
    changed = near_constant_vectors({k: {kk: vv.tolist() for kk, vv in v.items()} for k, v in arm_stats().items()})
    assert sorted(c.key for c in changed) == [ACTION, OBS_STATE]


def test_the_policy_converts_a_home_pose_with_the_same_floored_statistics_as_its_processors():
    config = make_config(state_dim=7, action_dim=7, safety=SafetyConfig(action="home", home_pose=[0.0] * 7))
    policy = VIBPolicy(config, dataset_stats=arm_stats())
    _, post = make_vib_pre_post_processors(config, arm_stats())
    normalized = torch.zeros(1, 7)
    normalized[0, 3] = 1.0
    assert torch.allclose(policy.robot_units.to_robot(ACTION, normalized), post(normalized))


def test_a_checkpoint_saves_the_floored_statistics_and_loads_them(tmp_path):
    config = make_config(state_dim=7, action_dim=7)
    pre, _ = make_vib_pre_post_processors(config, arm_stats())
    pre.save_pretrained(tmp_path)
    from lerobot.processor import PolicyProcessorPipeline

    loaded = PolicyProcessorPipeline.from_pretrained(tmp_path, config_filename="policy_preprocessor.json")
    state = {OBS_STATE: torch.zeros(1, 7), "observation.images.top": torch.rand(1, 3, 32, 32)}
    state[OBS_STATE][0, 3] = 0.05
    assert torch.allclose(loaded(dict(state))[OBS_STATE], pre(dict(state))[OBS_STATE])
    assert abs(float(loaded(dict(state))[OBS_STATE][0, 3])) < 5


def test_checkpoints_without_the_field_keep_their_saved_statistics(tmp_path):
    """A checkpoint from before the floor: its processors were saved unfloored and load unfloored."""
    config = make_config(state_dim=7, action_dim=7, normalization_floor=None)
    pre, _ = make_vib_pre_post_processors(config, arm_stats())
    pre.save_pretrained(tmp_path)
    from lerobot.processor import PolicyProcessorPipeline

    loaded = PolicyProcessorPipeline.from_pretrained(tmp_path, config_filename="policy_preprocessor.json")
    state = {OBS_STATE: torch.zeros(1, 7), "observation.images.top": torch.rand(1, 3, 32, 32)}
    state[OBS_STATE][0, 3] = 0.01
    assert abs(float(loaded(state)[OBS_STATE][0, 3])) > 50


def test_the_floor_must_be_a_fraction():
    from lerobot_vib.configuration_vib import VIBConfigError

    with pytest.raises(VIBConfigError, match="normalization_floor"):
        make_config(normalization_floor=0.0)


def test_identity_features_are_left_alone():
    config = make_config(
        state_dim=7, normalization_mapping={"VISUAL": "IDENTITY", "STATE": "IDENTITY", "ACTION": "MEAN_STD"}
    )
    _, changed = floor_stats(arm_stats(), config.input_features, config.normalization_mapping, 0.1)
    assert changed == []
    assert NormalizationMode("IDENTITY") is NormalizationMode.IDENTITY


def _rate_after_deviation(floor, deviation: float) -> float:
    config = make_config(state_dim=7, action_dim=7, normalization_floor=floor)
    torch.manual_seed(0)
    policy = VIBPolicy(config).eval()
    pre, _ = make_vib_pre_post_processors(config, arm_stats())
    g = torch.Generator().manual_seed(1)
    raw = {OBS_STATE: torch.randn(16, 7, generator=g) * torch.tensor(ARM_STATE_STD)}
    raw["observation.images.top"] = torch.rand(16, 3, 32, 32, generator=g)
    raw[OBS_STATE][:, 3] = 0.0
    with torch.no_grad():
        base = policy.observation_scores(pre(dict(raw)))[1]["rate"]
        raw[OBS_STATE][:, 3] = deviation
        moved = policy.observation_scores(pre(dict(raw)))[1]["rate"]
    return float((moved / base).median())


def test_a_never_moved_joint_cannot_blow_up_the_rate():
    assert _rate_after_deviation(0.1, 0.01) < 1.5  # 0.6 degrees: an ordinary rollout wobble
    assert _rate_after_deviation(None, 0.01) > 10 * _rate_after_deviation(0.1, 0.01)  # the test can fail


@pytest.mark.parametrize(
    ("scope", "state_floored", "action_floored"),
    [("all", True, True), ("state", True, False), ("action", False, True)],
)
def test_the_floor_applies_to_the_features_its_scope_names(scope, state_floored, action_floored):
    """The floor on the state only keeps the action's twitch of the never-moved joint, and the other way round."""
    from lerobot_vib.processor_vib import vib_dataset_stats

    config = make_config(state_dim=7, action_dim=7, normalization_floor_features=scope)
    stats = vib_dataset_stats(config, arm_stats())
    assert (float(stats[OBS_STATE]["std"][3]) > ARM_STATE_STD[3]) == state_floored
    assert (float(stats[ACTION]["std"][3]) > ARM_STATE_STD[3]) == action_floored
    with pytest.raises(Exception, match="normalization_floor_features"):
        make_config(normalization_floor_features="images")
