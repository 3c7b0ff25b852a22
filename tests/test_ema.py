"""The moving average of the weights (`ema.py`): its recursion, and a policy that acts, saves and loads with it."""

from __future__ import annotations

import pytest
import torch
from safetensors.torch import load_file
from torch import nn

from helpers import BIN, TRAIN_ARGS, make_batch, make_config, run
from lerobot_vib.configuration_vib import VIBConfigError
from lerobot_vib.ema import ema_decay_at, make_ema
from lerobot_vib.modeling_vib import VIBPolicy


def test_the_average_follows_its_recursion_by_hand():
    decay = 0.6
    layer = nn.Linear(2, 1)
    ema = make_ema(layer, decay)
    history = [torch.tensor([[1.0, -2.0]]), torch.tensor([[3.0, 0.0]]), torch.tensor([[-1.0, 5.0]])]
    expected = None
    for t, weight in enumerate(history, start=1):
        with torch.no_grad():
            layer.weight.copy_(weight)
        ema.update_parameters(layer)
        d = min(decay, (1 + t) / (10 + t))
        expected = weight.clone() if t == 1 else d * expected + (1 - d) * weight
    assert torch.allclose(ema.module.weight, expected)
    assert not ema.module.weight.requires_grad


def test_the_decay_warms_up_to_its_cap():
    assert ema_decay_at(1, 0.999) == pytest.approx(2 / 11)
    assert ema_decay_at(90, 0.999) == pytest.approx(91 / 100)
    assert ema_decay_at(100_000, 0.999) == 0.999


@pytest.mark.parametrize("decay", [0.0, 1.0, -0.5, 1.5])
def test_a_decay_outside_the_open_unit_interval_is_refused(decay):
    with pytest.raises(VIBConfigError, match="ema_decay"):
        make_config(ema_decay=decay)


def _trained_a_little(policy: VIBPolicy, steps: int = 3) -> VIBPolicy:
    optimizer = torch.optim.AdamW([g for group in policy.get_optim_params() for g in group["params"]], lr=1e-2)
    policy.train()
    for step in range(steps):
        loss, _ = policy.forward(make_batch(policy.config, batch_size=4, seed=step))
        loss.backward()
        optimizer.step()
        optimizer.zero_grad()
        policy.update()
    return policy


def test_the_policy_acts_with_the_average_and_trains_the_raw_weights():
    torch.manual_seed(0)
    policy = _trained_a_little(VIBPolicy(make_config(ema_decay=0.9)))
    batch = make_batch(policy.config, batch_size=2, with_action=False, seed=7)
    acted = policy.predict_action_chunk(batch)
    assert torch.equal(acted, policy.ema.module(batch, sample=False).actions)
    assert not torch.allclose(acted, policy.model(batch, sample=False).actions)
    policy.train()
    assert policy.network is policy.model
    assert int(policy.ema.n_averaged) == 3


def test_the_optimizer_never_sees_the_averaged_weights():
    policy = VIBPolicy(make_config(ema_decay=0.9))
    optimized = {id(p) for group in policy.get_optim_params() for p in group["params"]}
    assert optimized == {id(p) for p in policy.model.parameters()}


def test_without_a_decay_there_is_no_average():
    policy = VIBPolicy(make_config())
    assert policy.ema is None and policy.eval().network is policy.model
    assert not any(key.startswith("ema.") for key in policy.state_dict())


def test_a_saved_policy_loads_with_its_average(tmp_path):
    torch.manual_seed(0)
    policy = _trained_a_little(VIBPolicy(make_config(ema_decay=0.9)))
    batch = make_batch(policy.config, batch_size=2, with_action=False, seed=7)
    expected = policy.predict_action_chunk(batch)
    policy.save_pretrained(tmp_path)
    loaded = VIBPolicy.from_pretrained(tmp_path)
    assert loaded.config.ema_decay == 0.9
    assert int(loaded.ema.n_averaged) == 3
    assert torch.allclose(loaded.predict_action_chunk(batch), expected)


def test_lerobot_train_updates_the_average_after_every_step(tiny_dataset_root, tmp_path):
    out = tmp_path / "run"
    run(
        [
            str(BIN / "lerobot-train"),
            *TRAIN_ARGS,
            "--policy.ema_decay=0.99",
            "--dataset.repo_id=local/tiny",
            f"--dataset.root={tiny_dataset_root}",
            "--steps=3",
            "--save_freq=3",
            f"--output_dir={out}",
        ]
    )
    weights = load_file(out / "checkpoints" / "last" / "pretrained_model" / "model.safetensors")
    assert int(weights["ema.n_averaged"]) == 3
    raw, averaged = weights["model.decoder.action_head.weight"], weights["ema.module.decoder.action_head.weight"]
    assert not torch.equal(raw, averaged)
