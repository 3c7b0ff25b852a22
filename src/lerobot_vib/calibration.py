"""Dataset-normalized uncertainty and its thresholds (paper Sec. III-E, last paragraph; DESIGN.md section 2).

    u = R / R_bar,   R_bar = mean rate over the training data (eval mode).

- During training `RateTracker` keeps exponential moving averages of the rate's first and second moments
  (debiased), saved with the model, so a checkpoint from `lerobot-train` has a sensible R_bar.
- `rate_statistics` recomputes the statistics exactly over a dataset (`lerobot-vib-calibrate`).
- Thresholds on u: the paper's gamma = mean(u) + 2 std(u) = 1 + 2 std(R) / R_bar, or a split-conformal
  gamma. For the conformal one, each held-out in-distribution episode i gets the score s_i = max_t u_t (a
  stop happens in an episode iff its score exceeds gamma), and with n scores

      gamma = s_(k),  k = ceil((n + 1) * (1 - alpha)),   s_(1) <= ... <= s_(n)  (order statistics).

  If the held-out episodes and a new in-distribution episode are exchangeable, the new episode is stopped
  (a false stop) with probability at most alpha (Vovk et al.; Angelopoulos & Bates, 2021). The guarantee is
  marginal over calibration sets and holds for episodes like the held-out ones: rollouts of the policy
  itself drift from the demonstrations, so measure the false-stop rate on them too.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass

import torch
from torch import Tensor, nn

QUANTILE_LEVELS = (0.5, 0.9, 0.95, 0.99)


class RateTracker(nn.Module):
    """Running (EMA) mean and second moment of the rate over training batches, as buffers."""

    def __init__(self, momentum: float = 0.01):
        super().__init__()
        self.momentum = momentum
        self.register_buffer("ema_mean", torch.zeros((), dtype=torch.float64))
        self.register_buffer("ema_sq", torch.zeros((), dtype=torch.float64))
        self.register_buffer("n_updates", torch.zeros((), dtype=torch.long))

    @torch.no_grad()
    def update(self, rate: Tensor) -> None:
        rate = rate.detach().to(torch.float64)
        if not torch.isfinite(rate).all():
            return  # a non-finite training batch must not poison R_bar
        self.ema_mean.lerp_(rate.mean(), self.momentum)
        self.ema_sq.lerp_((rate**2).mean(), self.momentum)
        self.n_updates += 1

    def _debias(self) -> float:
        return 1.0 - (1.0 - self.momentum) ** int(self.n_updates)

    @property
    def mean(self) -> float:
        """Debiased running mean; NaN before the first update."""
        return float(self.ema_mean) / self._debias() if self.n_updates > 0 else math.nan

    @property
    def std(self) -> float:
        if self.n_updates == 0:
            return math.nan
        var = float(self.ema_sq) / self._debias() - self.mean**2
        return math.sqrt(max(var, 0.0))


def mean_plus_2std_gamma(rate_mean: float, rate_std: float) -> float:
    """The paper's threshold on u = R / R_bar: mean(u) + 2 std(u) = 1 + 2 std(R) / R_bar."""
    return 1.0 + 2.0 * rate_std / rate_mean


def conformal_min_scores(alpha: float) -> int:
    """The fewest scores n with ceil((n + 1)(1 - alpha)) <= n, below which no conformal threshold exists."""
    if not 0 < alpha < 1:
        raise ValueError(f"alpha must be in (0, 1), got {alpha}.")
    n = max(math.ceil(1 / alpha) - 2, 1)
    while math.ceil((n + 1) * (1 - alpha)) > n:
        n += 1
    return n


def conformal_gamma(scores: Tensor, alpha: float) -> float:
    """Split-conformal threshold: the ceil((n + 1)(1 - alpha))-th smallest of the n scores."""
    needed = conformal_min_scores(alpha)
    scores = torch.as_tensor(scores, dtype=torch.float64).flatten()
    n = scores.numel()
    k = math.ceil((n + 1) * (1 - alpha))
    if n < needed:
        raise ValueError(f"A conformal threshold at alpha={alpha} needs at least {needed} held-out episodes; got {n}.")
    if not torch.isfinite(scores).all():
        raise ValueError("Conformal scores contain NaN or inf: check the held-out episodes' observations.")
    return float(torch.sort(scores).values[k - 1])


@dataclass
class RateStatistics:
    rates: Tensor  # (N,) rate per frame
    episode_index: Tensor  # (N,) episode of each frame

    @property
    def mean(self) -> float:
        return float(self.rates.mean())

    @property
    def std(self) -> float:
        return float(self.rates.std(unbiased=False))

    def quantiles(self, levels: Iterable[float] = QUANTILE_LEVELS) -> dict[str, float]:
        levels = list(levels)
        values = torch.quantile(self.rates, torch.tensor(levels, dtype=self.rates.dtype))
        return {str(level): float(v) for level, v in zip(levels, values, strict=True)}

    def episode_max(self, scale: float = 1.0) -> Tensor:
        """max over each episode's frames of rate / scale, one score per episode (sorted by episode)."""
        episodes = torch.unique(self.episode_index)
        return torch.stack([(self.rates[self.episode_index == e] / scale).max() for e in episodes])


@torch.no_grad()
def rate_statistics(
    encode_rate: Callable[[dict], Tensor], batches: Iterable[dict], episode_key: str = "episode_index"
) -> RateStatistics:
    """Collect the rate of every frame. `encode_rate(batch) -> (B,)`; batches carry `episode_index`."""
    rates, episodes = [], []
    for batch in batches:
        r = encode_rate(batch).detach().to("cpu", torch.float64).reshape(-1)
        if not torch.isfinite(r).all():
            raise ValueError(
                "Non-finite rate on calibration frames (episodes "
                f"{sorted(set(batch[episode_key].reshape(-1).tolist()))}): check the dataset for NaN values."
            )
        rates.append(r)
        episodes.append(torch.as_tensor(batch[episode_key]).reshape(-1).cpu())
    if not rates:
        raise ValueError("No frames to calibrate on.")
    return RateStatistics(torch.cat(rates), torch.cat(episodes))


def stop_threshold(config, running: RateTracker, step: int) -> float:
    """gamma at episode step `step` for a VIBConfig `config`, in this order: `safety.gamma`; else the
    calibrated threshold if it was set on the configured score (a time-indexed band's value at that step);
    else mean(u) + 2 std(u) of that score over the calibration frames (for the rate: from training, `running`).
    NaN when none is known."""
    if config.safety.gamma is not None:
        return config.safety.gamma
    calibration = config.calibration
    score = config.uncertainty_score
    if calibration.gamma is not None and (calibration.gamma_score or "rate") == score:
        if calibration.gamma_band:
            return calibration.gamma_band[min(step, len(calibration.gamma_band) - 1)]
        return calibration.gamma
    if score != "rate":
        mean, std = calibration.score_means.get(score), calibration.score_stds.get(score)
        return mean_plus_2std_gamma(mean, std) if mean is not None and std is not None else math.nan
    if calibration.rate_mean is not None and calibration.rate_std is not None:
        return mean_plus_2std_gamma(calibration.rate_mean, calibration.rate_std)
    return mean_plus_2std_gamma(running.mean, running.std)


def threshold_source(config) -> str:
    """Where `stop_threshold` takes gamma from for `config`, in words: the one place that says which of
    `safety.gamma`, `calibration.gamma` / `calibration.gamma_band` and the statistics is in force."""
    if config.safety.gamma is not None:
        return "safety.gamma (set by hand; it overrides the calibration)"
    calibration = config.calibration
    score = config.uncertainty_score
    if calibration.gamma is not None and (calibration.gamma_score or "rate") == score:
        if calibration.gamma_band:
            return (
                f"calibration.gamma_band, a time-indexed band of {len(calibration.gamma_band)} steps "
                f"({calibration.gamma_method})"
            )
        return f"calibration.gamma ({calibration.gamma_method})"
    if score != "rate":
        return f"mean + 2 std of {score} over the calibration frames"
    if calibration.rate_mean is not None and calibration.rate_std is not None:
        return "mean + 2 std of the rate over the calibration frames"
    return "mean + 2 std of the rate's running statistics from training"
