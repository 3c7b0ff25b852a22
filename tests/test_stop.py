"""What the safety stop reads (stop.py): the windowed u, the AND of scores, the band read at each env's progress."""

from __future__ import annotations

import pytest
import torch

from helpers import make_config
from lerobot_vib.safety import SafetyMonitor
from lerobot_vib.stop import PolicyStop


def stop_for(**calibration) -> PolicyStop:
    config = make_config()
    for name, value in calibration.items():
        setattr(config.calibration, name, value)
    return PolicyStop(config, score_mean=lambda name: 2.0, threshold_at=lambda step: 1.5 + 0.1 * step)


def test_an_and_stop_value_is_above_gamma_exactly_when_every_member_is_above_its_own_threshold():
    stop = stop_for(and_gammas={"state_rate": 3.0})
    u = torch.tensor([2.0, 2.0, 1.0, 1.0])  # against gamma 1.5: above, above, below, below
    partner_u = torch.tensor([4.0, 2.0, 4.0, 2.0])  # against 3.0: above, below, above, below
    value = stop.value(u, {"state_rate": 2.0 * partner_u}, 1.5)  # raw scores, over their mean of 2
    assert (value > 1.5).tolist() == [True, False, False, False]
    torch.testing.assert_close(value, torch.minimum(u / 1.5, partner_u / 3.0) * 1.5)


def test_an_or_stop_value_is_above_gamma_as_soon_as_any_member_is_above_its_own_threshold():
    stop = stop_for(or_gammas={"embedding_rnd": 3.0})
    u = torch.tensor([2.0, 2.0, 1.0, 1.0, 1.0])  # against gamma 1.5: above, above, below, below, below
    partner_u = torch.tensor([4.0, 2.0, 4.0, 2.0, float("nan")])  # against 3.0: above, below, above, below, unknown
    value = stop.value(u, {"embedding_rnd": 2.0 * partner_u}, 1.5)
    assert (value[:4] > 1.5).tolist() == [True, True, True, False]
    assert torch.isnan(value[4])  # an unknown member leaves the stop value unknown: the stop fires
    torch.testing.assert_close(value[:4], torch.maximum(u / 1.5, partner_u / 3.0)[:4] * 1.5)
    assert "OR embedding_rnd above 3" in stop.quantity()


def test_an_or_partner_is_read_over_its_own_window():
    stop = stop_for(or_gammas={"embedding_rnd": 3.0}, or_window=2)
    raw = [2.0 * x for x in (2.0, 5.0, 5.0)]  # u 2, 5, 5: its 2-step mean 2, 3.5, 5
    values = [float(stop.value(torch.tensor([0.1]), {"embedding_rnd": torch.tensor([r])}, 1.5)) for r in raw]
    assert values == pytest.approx([2.0 / 3.0 * 1.5, 3.5 / 3.0 * 1.5, 5.0 / 3.0 * 1.5])


def test_the_windowed_u_is_the_mean_of_the_last_w_steps_and_an_unknown_step_stays_unknown():
    stop = stop_for(window=3)
    values = [stop.windowed(torch.tensor([x]), "u") for x in (1.0, 3.0, 5.0, 7.0)]
    assert [float(v) for v in values] == [1.0, 2.0, 3.0, 5.0]
    assert torch.isnan(stop.windowed(torch.tensor([float("nan")]), "u")).all()


def test_a_band_is_read_at_each_envs_progress_and_a_stopped_env_does_not_advance():
    stop = stop_for(gamma=1.5, gamma_band=[1.5, 1.6, 1.7, 1.8])  # threshold_at reads it: 1.5 + 0.1 step
    monitor = SafetyMonitor(1.5, 1.5)
    u = torch.ones(2)
    for stopped in ([False, False], [False, True], [False, True]):
        gamma, thresholds = stop.threshold(monitor, 0, u)
        stop.advance(torch.tensor(stopped))
    assert stop.progress.tolist() == [3, 1]  # env 1 held for two steps
    gamma, thresholds = stop.threshold(monitor, 3, u)
    torch.testing.assert_close(thresholds, torch.tensor([1.8, 1.6]))
    assert gamma == pytest.approx(1.8)  # env 0's, as calibrated
