"""How well a policy and its uncertainty score do: success intervals, AUROC, and the safety stop's error rates.

- Success of k out of n episodes with its 95% Wilson score interval (z = 1.96):

      (p + z^2/2n -+ z sqrt(p(1-p)/n + z^2/4n^2)) / (1 + z^2/n),   p = k/n.

- AUROC of a score separating negatives (e.g. clean frames) from positives (perturbed frames): the
  probability that a random positive scores higher than a random negative, ties counting one half
  (the Mann-Whitney U statistic over n_neg * n_pos).
- A stop threshold on a u trace (offline: traces recorded with the stop off): the episode stops at the first
  step t with u_t > gamma_t. A constant gamma is the paper's mean + 2 std or the per-episode split-conformal
  threshold (calibration.py); the time-indexed band gives one gamma_t per episode step:

      b_t    = mean over the shape episodes alive at step t of u_t           (the shape of a clean episode)
      s_i    = max_t u_{i,t} / b_t   over the held-out level episodes i     (one score per episode)
      gamma_t = q * b_t,   q = the split-conformal threshold of the s_i at level alpha

  so an in-distribution episode crosses the band with probability at most alpha (if exchangeable with the
  level episodes), while the band stays high where clean episodes are uncertain anyway (their first steps).
  Episodes longer than the band use its last value. Beyond the paper, as failure detectors do (FAIL-Detect).
  The standard-deviation band is FAIL-Detect's own modulation (functional conformal prediction):

      mu_t, s_t = mean and standard deviation over the shape episodes alive at step t of u_t
      z_i     = max_t (u_{i,t} - mu_t) / s_t   over the level episodes i
      gamma_t = mu_t + q s_t,   q = the split-conformal threshold of the z_i at level alpha

  It is tight where clean episodes agree and wide where they scatter (a grasp), where the proportional band
  is wide wherever clean u is high; steps fewer than two shape episodes reached keep the last mu_t and s_t,
  and s_t is floored at STD_FLOOR of the mean of mu so that a step where every shape episode agrees does not
  make any difference an alarm.
- False-stop rate: the fraction of clean episodes that stop. On occlusion episodes, a stop before the
  occluder enters is a false stop; otherwise the detection delay is the stop step minus the entry step.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from .calibration import conformal_gamma

Z95 = 1.959964


def wilson_interval(successes: int, n: int, z: float = Z95) -> tuple[float, float]:
    """95% Wilson score interval of a success rate (0, 1 for no episodes)."""
    if not 0 <= successes <= n:
        raise ValueError(f"Need 0 <= successes <= n, got {successes} of {n}.")
    if n == 0:
        return 0.0, 1.0
    p = successes / n
    center = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    # The interval always holds p; rounding at p = 0 or 1 (50 of 50) would otherwise put a bound a hair inside it.
    return max(min(center - half, p), 0.0), min(max(center + half, p), 1.0)


def auroc(negatives: Sequence[float], positives: Sequence[float]) -> float:
    """P(positive > negative) + P(tie) / 2 over all pairs."""
    neg, pos = _finite(negatives, "negatives"), _finite(positives, "positives")
    if not len(neg) or not len(pos):
        raise ValueError(f"AUROC needs negatives and positives; got {len(neg)} and {len(pos)}.")
    ranks = _ranks(np.concatenate([neg, pos]))  # average ranks: ties get the mean rank
    u_stat = ranks[len(neg) :].sum() - len(pos) * (len(pos) + 1) / 2
    return float(u_stat / (len(neg) * len(pos)))


def roc_curve(negatives: Sequence[float], positives: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    """False- and true-positive rates of `score > threshold` over every threshold, from (0, 0) to (1, 1)."""
    neg, pos = _finite(negatives, "negatives"), _finite(positives, "positives")
    thresholds = np.unique(np.concatenate([neg, pos]))[::-1]
    fpr = [0.0] + [float((neg >= t).mean()) for t in thresholds]
    tpr = [0.0] + [float((pos >= t).mean()) for t in thresholds]
    return np.array(fpr), np.array(tpr)


def _finite(values: Sequence[float], name: str) -> np.ndarray:
    array = np.asarray(values, dtype=np.float64).reshape(-1)
    if not np.isfinite(array).all():
        raise ValueError(f"AUROC {name} contain NaN or inf.")
    return array


def _ranks(values: np.ndarray) -> np.ndarray:
    order = np.argsort(values, kind="mergesort")
    ranks = np.empty(len(values))
    ranks[order] = np.arange(1, len(values) + 1)
    for v in np.unique(values):  # ties share their mean rank
        tied = values == v
        ranks[tied] = ranks[tied].mean()
    return ranks


def first_crossing(u: Sequence[float], gamma: float | Sequence[float]) -> int | None:
    """First step t with u_t > gamma_t (a non-finite u_t also stops: unknown means stop); None if never."""
    u = np.asarray(u, dtype=np.float64)
    if np.ndim(gamma) == 0:
        band = np.full(len(u), float(gamma))
    else:
        gamma = np.asarray(gamma, dtype=np.float64)
        if not len(gamma):
            raise ValueError("The threshold band is empty.")
        band = np.concatenate([gamma, np.full(max(len(u) - len(gamma), 0), gamma[-1])])[: len(u)]
    crossed = np.flatnonzero(~np.isfinite(u) | (u > band))
    return int(crossed[0]) if len(crossed) else None


def time_indexed_band(
    shape_traces: Sequence[Sequence[float]], level_traces: Sequence[Sequence[float]], alpha: float
) -> np.ndarray:
    """gamma_t = q * b_t (module docstring): b from the shape episodes, q conformal over the level episodes."""
    if not shape_traces or not level_traces:
        raise ValueError("The time-indexed band needs shape episodes and level episodes.")
    length = max(len(t) for t in [*shape_traces, *level_traces])
    sums, counts = np.zeros(length), np.zeros(length)
    for trace in shape_traces:
        trace = np.asarray(trace, dtype=np.float64)
        sums[: len(trace)] += trace
        counts[: len(trace)] += 1
    if counts[0] == 0:
        raise ValueError("The shape episodes are empty.")
    b = np.empty(length)
    for t in range(length):  # steps no shape episode reached keep the last known value
        b[t] = sums[t] / counts[t] if counts[t] else b[t - 1]
    if not (b > 0).all():
        raise ValueError("The band's shape must be positive (u is a ratio of non-negative scores).")
    scores = [float(np.max(np.asarray(t, dtype=np.float64) / b[: len(t)])) for t in level_traces]
    return conformal_gamma(np.array(scores), alpha) * b


STD_FLOOR = 1e-3  # std_band's least s_t, as a share of mu's mean over the steps


def std_band(
    shape_traces: Sequence[Sequence[float]], level_traces: Sequence[Sequence[float]], alpha: float
) -> np.ndarray:
    """gamma_t = mu_t + q * s_t (module docstring): mu and s from the shape episodes, q conformal over the level
    episodes. Raised if the band is not positive where a stop reads it (u is a ratio of non-negative scores)."""
    if len(shape_traces) < 2 or not level_traces:
        raise ValueError("The standard-deviation band needs two shape episodes or more, and level episodes.")
    length = max(len(t) for t in [*shape_traces, *level_traces])
    mu, sd = np.empty(length), np.empty(length)
    for t in range(length):
        alive = [float(trace[t]) for trace in shape_traces if len(trace) > t]
        if len(alive) >= 2:
            mu[t], sd[t] = np.mean(alive), np.std(alive, ddof=1)
        elif t == 0:
            raise ValueError("Fewer than two shape episodes have a first step.")
        else:
            mu[t], sd[t] = mu[t - 1], sd[t - 1]
    sd = np.maximum(sd, STD_FLOOR * abs(float(mu.mean())))
    if not (sd > 0).all():
        raise ValueError("The shape episodes' u is zero at every step: the band has no scale.")
    scores = [float(np.max((np.asarray(t, dtype=np.float64) - mu[: len(t)]) / sd[: len(t)])) for t in level_traces]
    band = mu + conformal_gamma(np.array(scores), alpha) * sd
    if not (band > 0).all():
        raise ValueError("The standard-deviation band falls to zero or below at some step: use the proportional band.")
    return band


BANDS = {"time_band": time_indexed_band, "std_band": std_band}  # a time-varying threshold's kinds, by flag


@dataclass
class StopMetrics:
    n_episodes: int
    stopped: int  # episodes with a stop (clean: false stops; occlusion: stops at or after the occluder's entry)
    early: int  # occlusion episodes stopped before the occluder entered (false stops); 0 on clean episodes
    delays: list[int]  # stop step - entry step, per detected occlusion episode

    @property
    def rate(self) -> float | None:
        return self.stopped / self.n_episodes if self.n_episodes else None

    @property
    def mean_delay(self) -> float | None:
        return float(np.mean(self.delays)) if self.delays else None


def stop_metrics(
    traces: Sequence[Sequence[float]], gamma: float | Sequence[float], onsets: Sequence[int | None] | None = None
) -> StopMetrics:
    """Stops of a threshold on u traces; with `onsets` (the occluder's entry step per episode), the delays.
    An occlusion episode that ended before its occluder entered is left out."""
    if onsets is not None and len(onsets) != len(traces):
        raise ValueError(f"{len(onsets)} onsets for {len(traces)} traces.")
    n = stopped = early = 0
    delays: list[int] = []
    for i, trace in enumerate(traces):
        onset = None if onsets is None else onsets[i]
        if onset is not None and onset >= len(trace):
            continue
        n += 1
        t = first_crossing(trace, gamma)
        if t is None:
            continue
        if onset is not None and t < onset:
            early += 1
            continue
        stopped += 1
        if onset is not None:
            delays.append(t - onset)
    return StopMetrics(n, stopped, early, delays)
