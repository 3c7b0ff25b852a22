"""The rate is the closed-form KL between each token's posterior and the learnable marginal."""

import pytest
import torch
from torch.distributions import Normal, kl_divergence

from helpers import make_batch, make_config
from lerobot_vib.bottleneck import LOGVAR_MAX, LOGVAR_MIN, GaussianBottleneck, Posterior
from lerobot_vib.configuration_vib import VIBConfigError
from lerobot_vib.modeling_vib import VIBPolicy


def test_closed_form_rate_equals_torch_distributions_kl():
    torch.manual_seed(0)
    bottleneck = GaussianBottleneck(d_token=6, latent_dim=5).double()
    with torch.no_grad():
        bottleneck.marginal_mean.normal_()
        bottleneck.marginal_logvar.uniform_(-2, 2)
    posterior = bottleneck.posterior(torch.randn(7, 3, 6, dtype=torch.float64))

    expected = kl_divergence(
        Normal(posterior.mean, (0.5 * posterior.logvar).exp()),
        Normal(bottleneck.marginal_mean, (0.5 * bottleneck.marginal_logvar).exp()),
    )
    expected = expected.sum(-1).mean(-1)  # sum over latent dims, mean over tokens

    rate = bottleneck.rate(posterior)
    assert rate.shape == (7,)
    torch.testing.assert_close(rate, expected, rtol=1e-10, atol=1e-12)


def test_rate_is_zero_iff_posterior_equals_marginal():
    bottleneck = GaussianBottleneck(d_token=4, latent_dim=3)
    same = Posterior(
        mean=bottleneck.marginal_mean.detach().expand(2, 5, 3).clone(),
        logvar=bottleneck.marginal_logvar.detach().expand(2, 5, 3).clone(),
    )
    torch.testing.assert_close(bottleneck.rate(same), torch.zeros(2))
    shifted = Posterior(mean=same.mean + 1.0, logvar=same.logvar)
    # KL of unit-variance Gaussians 1 apart is 1/2 per dim: 3 dims -> 1.5 per token, mean over tokens.
    torch.testing.assert_close(bottleneck.rate(shifted), torch.full((2,), 1.5))


def test_rate_gradients_reach_the_marginal_parameters():
    policy = VIBPolicy(make_config(beta=1.0))
    policy.train()
    loss, _ = policy.forward(make_batch(policy.config))
    loss.backward()
    marginal = policy.model.bottleneck
    assert marginal.marginal_mean.grad is not None and marginal.marginal_mean.grad.abs().sum() > 0
    assert marginal.marginal_logvar.grad is not None and marginal.marginal_logvar.grad.abs().sum() > 0


def test_beta_zero_removes_the_rate_from_the_loss():
    policy = VIBPolicy(make_config(beta=0.0))
    policy.train()
    loss, info = policy.forward(make_batch(policy.config))
    assert info["rate"] > 0
    assert loss.item() == info["l1_loss"]
    loss.backward()
    # The marginal only enters through the rate: with beta = 0 it receives exactly zero gradient.
    assert torch.count_nonzero(policy.model.bottleneck.marginal_mean.grad) == 0
    assert torch.count_nonzero(policy.model.bottleneck.marginal_logvar.grad) == 0


def test_beta_weights_the_rate_in_the_loss():
    config = make_config(beta=0.25)
    policy = VIBPolicy(config)
    policy.eval()  # posterior mean: deterministic, so l1 and rate are those of this exact pass
    loss, info = policy.forward(make_batch(config))
    torch.testing.assert_close(loss.item(), info["l1_loss"] + 0.25 * info["rate"], rtol=1e-6, atol=1e-6)


def test_log_variance_is_clamped_so_the_rate_stays_finite():
    bottleneck = GaussianBottleneck(d_token=2, latent_dim=2)
    with torch.no_grad():
        bottleneck.posterior_head.weight.fill_(1e6)
    posterior = bottleneck.posterior(torch.ones(1, 1, 2))
    assert posterior.logvar.max() <= LOGVAR_MAX and posterior.logvar.min() >= LOGVAR_MIN
    assert torch.isfinite(bottleneck.rate(posterior)).all()


def test_a_head_started_narrow_gives_every_token_sigma_near_its_init_and_the_default_head_is_a_plain_linear():
    torch.manual_seed(0)
    tokens = torch.randn(8, 5, 16)
    narrow = GaussianBottleneck(16, 4, logvar_init=-6.0)
    sigma = torch.exp(0.5 * narrow.posterior(tokens).logvar)
    assert sigma.min() > 0.02 and sigma.max() < 0.15  # exp(-3) = 0.05, spread by the head's small weights
    torch.manual_seed(1)
    default = GaussianBottleneck(16, 4)
    torch.manual_seed(1)
    plain = torch.nn.Linear(16, 8)
    assert torch.equal(default.posterior_head.weight, plain.weight)
    assert torch.equal(default.posterior_head.bias, plain.bias)  # checkpoints trained before the field: unchanged


def test_posterior_logvar_init_reaches_both_networks_heads_and_is_refused_outside_the_clamp():
    for encoder in ("pooled", "tokens"):
        policy = VIBPolicy(make_config(encoder=encoder, posterior_logvar_init=-4.0))
        heads = [m for m in policy.modules() if isinstance(m, GaussianBottleneck)]
        assert heads and all(torch.all(h.posterior_head.bias[h.latent_dim :] == -4.0) for h in heads)
    with pytest.raises(VIBConfigError, match="posterior_logvar_init"):
        make_config(posterior_logvar_init=LOGVAR_MIN - 1)
    with pytest.raises(VIBConfigError, match="posterior_logvar_init"):
        make_config(posterior_logvar_init=LOGVAR_MAX + 1)
