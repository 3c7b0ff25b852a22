"""The uncertainty scores (scores.py): exact splits of the rate, each score's defining property, and a
checkpoint that keeps its scores."""

import pytest
import torch

from helpers import make_batch, make_config, with_rate_statistics
from lerobot_vib.configuration_vib import SafetyConfig
from lerobot_vib.modeling_vib import VIBPolicy
from lerobot_vib.scores import SCORES, TOKEN_SCORES, ChunkDisagreement, EmbeddingRND, fit_embedding_rnd, rate_terms
from lerobot_vib.scripts.calibrate import record_frames


def identity(batch):
    return batch


def dataset_batches(config, n_batches: int = 6, batch_size: int = 8, episode_len: int = 12):
    """Frames as a dataset loader gives them: observations plus episode and frame indices, in time order."""
    out = []
    for b in range(n_batches):
        batch = make_batch(config, batch_size=batch_size, with_action=False, seed=b)
        index = torch.arange(b * batch_size, (b + 1) * batch_size)
        batch["episode_index"] = index // episode_len
        batch["frame_index"] = index % episode_len
        out.append(batch)
    return out


def calibrated_policy(config, **calibration) -> VIBPolicy:
    """A policy whose every score is fitted and normalized on its 'training' frames, as lerobot-vib-calibrate does."""
    policy = with_rate_statistics(VIBPolicy(config))
    records = record_frames(policy, identity, dataset_batches(config))
    records.fit(policy, rnd_steps=300)
    values = records.scores(policy)
    policy.config.calibration.score_means = {k: float(v.mean()) for k, v in values.items() if k != "rate"}
    policy.config.calibration.score_stds = {k: float(v.std()) for k, v in values.items() if k != "rate"}
    policy.config.calibration.rate_mean = float(values["rate"].mean())
    for key, value in calibration.items():
        setattr(policy.config.calibration, key, value)
    return policy.eval()


def test_the_mean_and_variance_terms_add_up_to_the_rate():
    policy = VIBPolicy(make_config()).eval()
    with torch.no_grad():
        posterior = policy.model.encode(make_batch(policy.config, with_action=False))
        mean_term, var_term = rate_terms(
            posterior, policy.model.bottleneck.marginal_mean, policy.model.bottleneck.marginal_logvar
        )
        rate = policy.model.bottleneck.rate(posterior)
    assert torch.allclose((mean_term + var_term).mean(-1), rate, rtol=1e-5)


def test_the_image_rate_does_not_move_with_the_state():
    policy = calibrated_policy(make_config())
    a = make_batch(policy.config, with_action=False, seed=1)
    b = {**a, "observation.state": a["observation.state"] + 3.0}
    with torch.no_grad():
        _, sa = policy.observation_scores(a)
        _, sb = policy.observation_scores(b)
    assert torch.allclose(sa["image_rate"], sb["image_rate"])
    assert not torch.allclose(sa["rate"], sb["rate"])


def test_without_a_state_the_image_rate_is_the_rate():
    policy = VIBPolicy(make_config(state_dim=None)).eval()
    with torch.no_grad():
        _, scores = policy.observation_scores(make_batch(policy.config, with_action=False))
    assert torch.equal(scores["image_rate"], scores["rate"])


def test_chunk_disagreement_is_zero_when_the_chunks_agree_and_their_spread_otherwise():
    tracker = ChunkDisagreement(chunk_size=3)
    plan = torch.arange(6.0).view(1, 3, 2)
    assert float(tracker.update(plan)) == 0.0  # one candidate: no evidence
    shifted = torch.cat([plan[:, 1:], plan[:, -1:]], dim=1)  # the same plan, one step on
    assert float(tracker.update(shifted)) == 0.0
    tracker.reset()
    tracker.update(torch.zeros(1, 3, 2))
    other = torch.full((1, 3, 2), 2.0)
    assert float(tracker.update(other)) == pytest.approx(1.0)  # candidates 0 and 2: std 1


def test_rnd_flags_embeddings_unlike_those_it_was_fitted_on():
    g = torch.Generator().manual_seed(0)
    train = torch.randn(2000, 16, generator=g) * 0.5 + 1.0
    rnd = EmbeddingRND(16, hidden_dim=64, out_dim=16)
    fit_embedding_rnd(rnd, train, steps=1500)
    with torch.no_grad():
        seen = rnd.error(torch.randn(500, 16, generator=g) * 0.5 + 1.0)
        unseen = rnd.error(torch.randn(500, 16, generator=g) * 0.5 - 2.0)
    assert rnd.fitted
    assert unseen.median() > 5 * seen.median()


def test_the_rnd_is_not_trained_by_the_policy_optimizer():
    policy = VIBPolicy(make_config())
    optimized = {id(p) for group in policy.get_optim_params() for p in group["params"]}
    assert not any(id(p) in optimized for p in policy.embedding_rnd.parameters())


@pytest.mark.parametrize("score", [s for s in SCORES if s not in TOKEN_SCORES])  # tokens': test_token_network.py
def test_a_checkpoint_round_trips_with_each_score(score, tmp_path):
    policy = calibrated_policy(make_config(uncertainty_score=score, chunk_size=4, n_action_steps=4))
    policy.save_pretrained(tmp_path)
    loaded = VIBPolicy.from_pretrained(tmp_path).eval()
    us = []
    for p in (policy, loaded):
        p.reset()
        us.append(torch.stack([_u(p, make_batch(p.config, with_action=False, seed=s)) for s in range(5)]))
    assert torch.isfinite(us[0]).all()
    assert torch.allclose(us[0], us[1], rtol=1e-5)
    assert loaded.last_step.score == score


def _u(policy, batch):
    with torch.no_grad():
        policy.select_action(batch)
    return policy.last_step.u


@pytest.mark.parametrize("score", ["image_rate", "low_image_rate", "embedding_rnd", "chunk_disagreement"])
def test_an_uncalibrated_score_refuses_to_drive_the_stop_and_names_the_command(score):
    policy = with_rate_statistics(VIBPolicy(make_config(uncertainty_score=score, safety=SafetyConfig(enabled=True))))
    with pytest.raises(RuntimeError, match="lerobot-vib-calibrate"):
        policy.select_action(make_batch(policy.config, with_action=False))


def test_an_uncalibrated_score_that_nothing_acts_on_traces_the_rate_and_says_so(caplog):
    policy = with_rate_statistics(VIBPolicy(make_config(uncertainty_score="low_image_rate")))
    with caplog.at_level("WARNING"):
        u = _u(policy, make_batch(policy.config, with_action=False))
    assert "lerobot-vib-calibrate" in caplog.text
    assert policy.last_step.score == "rate"
    assert torch.allclose(u, policy.last_step.rate / policy.rate_mean())


def test_a_black_image_raises_the_embedding_rnd_score():
    # The trunk's channel means see the image's level; keypoints alone do not (an untrained trunk's keypoints
    # sit in a corner whatever the image).
    config = make_config(uncertainty_score="embedding_rnd", image_pooling="spatial_softmax_avg")
    policy = calibrated_policy(config)
    gamma = policy.stop_threshold()
    batch = make_batch(config, with_action=False, seed=99)
    black = {**batch, "observation.images.top": torch.zeros_like(batch["observation.images.top"])}
    clean_u, black_u = _u(policy.reset() or policy, batch), _u(policy.reset() or policy, black)
    assert (black_u > clean_u).all()
    assert (black_u > gamma).all()


def test_the_stop_threshold_belongs_to_the_score_it_was_set_on(caplog):
    policy = calibrated_policy(make_config(uncertainty_score="embedding_rnd"), gamma=50.0, gamma_score="rate")
    cal = policy.config.calibration
    expected = 1 + 2 * cal.score_stds["embedding_rnd"] / cal.score_means["embedding_rnd"]
    assert policy.stop_threshold() == pytest.approx(expected)
    policy.config.calibration.gamma_score = "embedding_rnd"
    assert policy.stop_threshold() == 50.0


def test_every_score_is_traced_when_asked():
    policy = calibrated_policy(make_config())
    policy.trace_all_scores = True
    _u(policy, make_batch(policy.config, with_action=False))
    assert set(policy.last_step.scores) == set(SCORES) - set(TOKEN_SCORES)  # the pooled network


@pytest.mark.parametrize(
    ("band_index", "gammas", "stopped"),
    [
        # read at the episode's step: the band moves on during the stop and releases it where it is high
        ("episode_step", [100.0, 1e-6, 100.0, 100.0], [False, True, False, False]),
        # read at the env's progress: it stands still while the env is stopped
        ("progress", [100.0, 1e-6, 1e-6, 1e-6], [False, True, True, True]),
    ],
)
def test_a_time_indexed_band_moves_the_stop_threshold_as_the_episode_runs(band_index, gammas, stopped):
    policy = calibrated_policy(
        make_config(uncertainty_score="rate", safety=SafetyConfig(enabled=True, resume_steps=1, band_index=band_index)),
        gamma=100.0,
        gamma_band=[100.0, 1e-6, 100.0],
        gamma_score="rate",
    )
    policy.reset()
    batch = make_batch(policy.config, with_action=False)
    seen_stopped, seen_gammas = [], []
    for _ in range(4):
        with torch.no_grad():
            policy.select_action(batch)
        seen_stopped.append(bool(policy.last_step.stopped[0]))
        seen_gammas.append(policy.last_step.gamma)
    assert seen_gammas == gammas  # the last value holds after the band ends
    assert seen_stopped == stopped


def test_a_band_is_set_from_rollouts_per_step_and_refuses_too_few():
    import numpy as np

    from lerobot_vib.configuration_vib import CalibrationConfig, VIBConfigError
    from lerobot_vib.scripts.calibrate import gamma_from_rollouts

    rng = np.random.default_rng(0)
    # u is high in the first steps of every rollout and low later: one threshold cannot serve both phases
    traces = [np.concatenate([3 + rng.random(5), 1 + 0.1 * rng.random(15)]) for _ in range(20)]
    info = {
        "rate_mean": 2.0,
        "score": "rate",
        "per_episode": [{"u_max": float(t.max()), "seed": i} for i, t in enumerate(traces)],
        "env": {"type": "vib_arm", "perturbation": {"noise_std": [0.0]}},
    }
    base = CalibrationConfig(rate_mean=2.0)
    band = gamma_from_rollouts(base, info, 0.1, "rollouts", threshold="time_band", traces=traces)
    assert len(band.gamma_band) == 20 and band.gamma_method == "time_band_rollouts"
    assert min(band.gamma_band[:5]) > 3 and max(band.gamma_band[5:]) < 2  # low where u is low: a late u of 2.5 stops
    flat = gamma_from_rollouts(base, info, 0.1, "rollouts")
    assert flat.gamma_band is None and flat.gamma > 3  # the per-episode max: a u of 2.5 never stops
    short = {**info, "per_episode": info["per_episode"][:10]}
    with pytest.raises(VIBConfigError, match="at least 18 rollouts"):
        gamma_from_rollouts(base, short, 0.1, "rollouts", threshold="time_band", traces=traces[:10])


def test_the_default_score_reads_the_camera_when_there_is_one():
    with_camera = VIBPolicy(make_config(uncertainty_score=None))
    without = VIBPolicy(make_config(uncertainty_score=None, cameras={}))
    assert with_camera.config.uncertainty_score == "low_image_rate"
    assert without.config.uncertainty_score == "rate"


def test_a_camera_score_without_a_camera_is_refused():
    with pytest.raises(ValueError, match="no camera"):
        VIBPolicy(make_config(uncertainty_score="low_image_rate", cameras={}))


def test_calibration_decodes_the_chunks_the_policy_acts_on_a_sample_when_it_samples():
    """Chunk disagreement's training statistics come from the chunks the policy will decode: the posterior mean's
    by default (the same on every pass), a posterior sample's with `sample_latent_at_inference`."""
    config = make_config(encoder="tokens")
    policy = VIBPolicy(config)
    batches = dataset_batches(config, n_batches=2)
    torch.manual_seed(0)
    assert torch.equal(record_frames(policy, identity, batches).chunks, record_frames(policy, identity, batches).chunks)
    policy.config.sample_latent_at_inference = True
    first, second = (record_frames(policy, identity, batches).chunks for _ in range(2))
    assert not torch.allclose(first, second)
