"""VIBConfig: the shipped preset lists the defaults, and nested run-time settings survive save and load."""

import itertools
import json
from pathlib import Path

import draccus
import pytest
import torch
from lerobot.configs.policies import PreTrainedConfig

from helpers import make_config
from lerobot_vib.configuration_vib import VIBConfig, VIBConfigError

CONFIG_JSON = Path(__file__).parents[1] / "configs" / "policy" / "vib.json"


def test_shipped_preset_lists_every_default():
    """vib.json is a whole train config whose policy is VIBConfig's defaults, on a GPU and kept off the Hub."""
    shipped = json.loads(CONFIG_JSON.read_text())["policy"]
    defaults = draccus.encode(VIBConfig(device="cpu"), PreTrainedConfig)
    defaults.update(device="cuda", push_to_hub=False, backbone_norm=None)  # None: the norm follows the weights
    assert shipped == defaults


def test_safety_and_calibration_survive_save_and_load_with_cli_overrides(tmp_path):
    config = make_config(temporal_ensemble="uncertainty", n_action_steps=1)
    config.calibration.rate_mean, config.calibration.episodes = 0.25, [0, 3]
    config.safety.home_pose = [0.0, 1.0, 2.0]
    config._save_pretrained(tmp_path)
    loaded = PreTrainedConfig.from_pretrained(
        tmp_path, cli_overrides=["--safety.enabled=true", "--safety.gamma=2.5", "--safety.action=home"]
    )
    assert isinstance(loaded, VIBConfig)
    assert loaded.calibration.rate_mean == 0.25 and loaded.calibration.episodes == [0, 3]
    assert loaded.safety.enabled and loaded.safety.gamma == 2.5 and loaded.safety.action == "home"
    assert loaded.safety.home_pose == [0.0, 1.0, 2.0] and loaded.temporal_ensemble == "uncertainty"


@pytest.mark.parametrize(
    ("safety", "message"),
    [
        (dict(action="brake"), "safety.action"),
        (dict(action="home"), "home_pose"),
        (dict(resume_steps=0), "resume_steps"),
        (dict(gamma=-1.0), "safety.gamma"),
        (dict(home_max_step=0.0), "home_max_step"),
    ],
)
def test_bad_safety_settings(safety, message):
    from lerobot_vib.configuration_vib import SafetyConfig

    with pytest.raises(VIBConfigError, match=message):
        SafetyConfig(**safety)


def test_home_pose_must_match_the_action_size():
    config = make_config(action_dim=3)
    config.safety.home_pose = [0.0, 0.0]
    with pytest.raises(VIBConfigError, match="home_pose"):
        config.validate_features()


def test_warmup_steps_give_lerobots_cosine_schedule_that_ends_at_zero():
    """`scheduler_warmup_steps`: linear warmup to the learning rate, then a cosine decay to zero at the last
    step; unset, the learning rate is constant (ACT's preset)."""
    assert make_config().get_scheduler_preset() is None
    config = make_config(scheduler_warmup_steps=10, optimizer_lr=3e-4)
    optimizer = torch.optim.AdamW([torch.nn.Parameter(torch.zeros(1))], lr=config.optimizer_lr)
    scheduler = config.get_scheduler_preset().build(optimizer, num_training_steps=110)
    lrs = []
    for _ in range(110):
        lrs.append(optimizer.param_groups[0]["lr"])
        optimizer.step()
        scheduler.step()
    assert lrs[0] == 0.0 and lrs[5] == pytest.approx(1.5e-4) and lrs[10] == pytest.approx(3e-4)
    assert lrs[60] == pytest.approx(1.5e-4) and lrs[-1] < 1e-6
    assert all(a >= b for a, b in itertools.pairwise(lrs[10:]))


def test_negative_warmup_is_refused():
    with pytest.raises(VIBConfigError, match="scheduler_warmup_steps"):
        make_config(scheduler_warmup_steps=-1)
