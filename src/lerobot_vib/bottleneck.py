"""The Variational Information Bottleneck on state tokens (paper Sec. III-B to III-D).

Each of the K state tokens t_k (a slice of the fused observation feature) gets a diagonal Gaussian
posterior p(z_k | s) = N(mu_k, diag(sigma_k^2)). The marginal m(z) = N(mu_m, diag(sigma_m^2)) is
learnable and shared by all tokens. The *rate* of an observation is

    R(s) = 1/K * sum_k sum_d KL( N(mu_kd, sigma_kd^2) || N(mu_m,d, sigma_m,d^2) )

with the closed form, per latent dimension,

    KL = 1/2 * [ log sigma_m^2 - log sigma^2 + (sigma^2 + (mu - mu_m)^2) / sigma_m^2 - 1 ].

R needs the observation only, so it is available at run time as an epistemic-uncertainty score.

Where the posteriors start matters. A default linear head starts every token at sigma ~ 1, while the token
network's image cells carry means far smaller than that: the decoder's first inputs from the camera are mostly
noise, the robot state is not, and a decoder can settle on the state alone. `logvar_init` starts the head's
log-variance at a chosen value instead (Alemi et al.'s deep VIB starts sigma near 0.007 the same way, with
softplus(x - 5)), so that training begins as ACT does and the rate's pressure adds the noise.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

# Why clamp: exp(logvar) overflows or underflows for untrained or adversarial inputs, which would
# turn the rate (a safety signal) into inf/NaN for reasons unrelated to the observation.
LOGVAR_MIN = -10.0
LOGVAR_MAX = 6.0


@dataclass
class Posterior:
    """Per-token Gaussian posterior parameters, each of shape (B, K, D)."""

    mean: Tensor
    logvar: Tensor

    def sample(self) -> Tensor:
        """Reparameterized sample z = mu + sigma * eps."""
        return self.mean + torch.exp(0.5 * self.logvar) * torch.randn_like(self.mean)


@dataclass
class VIBOutput:
    """What a VIB network's forward pass returns (either network: pooled_network's or token_network's)."""

    actions: Tensor  # (B, chunk_size, action_dim)
    posterior: Posterior  # (B, K, latent_dim) each
    rate: Tensor  # (B,)
    token_rates: Tensor | None = None  # (B, K) the token network's per-token rates


def gaussian_kl(mean: Tensor, logvar: Tensor, prior_mean: Tensor, prior_logvar: Tensor) -> Tensor:
    """Element-wise KL(N(mean, exp(logvar)) || N(prior_mean, exp(prior_logvar))), broadcasting."""
    return 0.5 * (
        prior_logvar - logvar + (torch.exp(logvar) + (mean - prior_mean) ** 2) * torch.exp(-prior_logvar) - 1.0
    )


class GaussianBottleneck(nn.Module):
    """Posterior head for K state tokens plus the learnable marginal; computes the rate per sample.

    Args:
        d_token: size of one state token (the slice of the fused feature it sees).
        latent_dim: size D of each token's latent z_k.
        n_marginals: 1 (the paper's): one marginal shared by all tokens; K: one marginal per token position
            (the token network's per-cell option), each token's KL taken against its own.
        logvar_init: None: the head's log-variance starts where a default linear layer puts it (about 0). A
            number: the log-variance half of the head's bias starts there, so sigma ~ exp(logvar_init / 2).
    """

    def __init__(self, d_token: int, latent_dim: int, n_marginals: int = 1, logvar_init: float | None = None):
        super().__init__()
        self.latent_dim = latent_dim
        # One head shared by all tokens: tokens differ by the slice of the fused feature they carry.
        self.posterior_head = nn.Linear(d_token, 2 * latent_dim)
        if logvar_init is not None:
            with torch.no_grad():
                self.posterior_head.bias[latent_dim:].fill_(logvar_init)
        shape = (latent_dim,) if n_marginals == 1 else (n_marginals, latent_dim)
        self.marginal_mean = nn.Parameter(torch.zeros(shape))
        self.marginal_logvar = nn.Parameter(torch.zeros(shape))

    def posterior(self, tokens: Tensor) -> Posterior:
        """tokens: (B, K, d_token) -> Posterior with (B, K, latent_dim) mean and log-variance."""
        mean, logvar = self.posterior_head(tokens).chunk(2, dim=-1)
        return Posterior(mean=mean, logvar=logvar.clamp(LOGVAR_MIN, LOGVAR_MAX))

    def token_rates(self, posterior: Posterior) -> Tensor:
        """Each token's rate, shape (B, K): its KL summed over latent dims."""
        kl = gaussian_kl(posterior.mean, posterior.logvar, self.marginal_mean, self.marginal_logvar)
        return kl.sum(dim=-1)

    def rate(self, posterior: Posterior) -> Tensor:
        """R per sample, shape (B,): KL summed over latent dims, averaged over tokens."""
        return self.token_rates(posterior).mean(dim=-1)
