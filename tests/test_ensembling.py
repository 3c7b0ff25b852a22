"""Uncertainty-weighted temporal ensembling, paper Eq. 6: w_j ∝ exp(-m * u_j * j), j = 0 the oldest."""

import math

import pytest
import torch
from lerobot.policies.act.modeling_act import ACTTemporalEnsembler

from helpers import make_batch, make_config, with_rate_statistics
from lerobot_vib.configuration_vib import VIBConfigError
from lerobot_vib.ensembling import UncertaintyWeightedEnsembler
from lerobot_vib.modeling_vib import VIBPolicy


@pytest.mark.parametrize("coeff", [0.01, 0.1, -0.05])
def test_u_equal_one_reduces_to_acts_ensembler(coeff):
    torch.manual_seed(0)
    chunk_size, batch, action_dim = 8, 3, 4
    act = ACTTemporalEnsembler(coeff, chunk_size)
    ours = UncertaintyWeightedEnsembler(coeff, chunk_size)
    for _ in range(3 * chunk_size):  # past the point where the history is full
        chunk = torch.randn(batch, chunk_size, action_dim)
        expected = act.update(chunk.clone())
        got = ours.update(chunk.clone(), torch.ones(batch))
        torch.testing.assert_close(got, expected, rtol=1e-6, atol=1e-6)  # equal to float32 rounding


def test_weights_follow_the_equation():
    m, chunk_size = 0.3, 4
    ens = UncertaintyWeightedEnsembler(m, chunk_size)
    u_values = [0.5, 2.0, 1.0, 4.0]
    # Chunk i predicts the constant value i for every future step, so the output is sum_j w_j * j.
    for i, u in enumerate(u_values):
        out = ens.update(torch.full((1, chunk_size, 1), float(i)), torch.tensor([u]))
    weights = torch.tensor([math.exp(-m * u * j) for j, u in enumerate(u_values)], dtype=torch.float64)
    weights /= weights.sum()
    expected = float((weights * torch.arange(4, dtype=torch.float64)).sum())
    assert out.item() == pytest.approx(expected, rel=1e-6)


def test_a_high_u_newer_chunk_gets_less_weight_than_under_act():
    chunk_size, m = 5, 0.1
    act = ACTTemporalEnsembler(m, chunk_size)
    ours = UncertaintyWeightedEnsembler(m, chunk_size)
    old = torch.zeros(1, chunk_size, 1)  # reliable past predictions: 0
    for _ in range(chunk_size - 1):
        act.update(old.clone())
        ours.update(old.clone(), torch.ones(1))
    new = torch.ones(1, chunk_size, 1)  # an unreliable recent one: 1, predicted under u = 10
    a_act = act.update(new.clone()).item()
    a_ours = ours.update(new.clone(), torch.tensor([10.0])).item()
    assert 0 < a_ours < a_act  # pulled less towards the uncertain prediction


def test_non_finite_u_gets_no_weight_and_all_non_finite_gives_nan():
    ens = UncertaintyWeightedEnsembler(0.1, 3)
    ens.update(torch.zeros(1, 3, 2), torch.ones(1))
    out = ens.update(torch.full((1, 3, 2), float("nan")), torch.tensor([float("nan")]))
    torch.testing.assert_close(out, torch.zeros(1, 2))  # the NaN chunk is ignored, not multiplied by 0
    ens.reset()
    assert torch.isnan(ens.update(torch.zeros(1, 3, 2), torch.tensor([float("inf")]))).all()


def test_policy_act_mode_is_lerobots_ensembler_and_uncertainty_mode_uses_u():
    config = make_config(chunk_size=5, n_action_steps=1, temporal_ensemble="act", temporal_ensemble_coeff=0.2)
    policy = with_rate_statistics(VIBPolicy(config))
    reference = ACTTemporalEnsembler(0.2, 5)
    for step in range(7):
        obs = make_batch(config, batch_size=2, with_action=False, seed=step)
        expected = reference.update(policy.predict_action_chunk(obs))
        torch.testing.assert_close(policy.select_action(obs), expected)

    policy.config.temporal_ensemble = "uncertainty"
    policy.reset()
    reference = UncertaintyWeightedEnsembler(0.2, 5)
    for step in range(7):
        obs = make_batch(config, batch_size=2, with_action=False, seed=step)
        chunk = policy.predict_action_chunk(obs)
        expected = reference.update(chunk, policy.last_rate / policy.rate_mean())
        torch.testing.assert_close(policy.select_action(obs), expected)


def test_ensembling_needs_one_action_step():
    with pytest.raises(VIBConfigError, match="n_action_steps=1"):
        make_config(chunk_size=5, n_action_steps=5, temporal_ensemble="uncertainty")
