"""Whether a VIB checkpoint can act on u, asked twice: when it loads and when an episode starts.

u = s / s_bar needs the score's training mean, and some scores need more, all filled by
`lerobot-vib-calibrate`: the token network's map scores each image cell's rate statistics, the pooled
network's image scores the state path's training mean, `embedding_rnd` a fitted RND. In this order:

1. at load (`check_ready_to_act_on_u`), where something reads u (the stop, Eq. 6): refuse a checkpoint with
   no R_bar or an uncalibrated score, then, with the stop on, one without a finite gamma or whose resume
   threshold lies above gamma; a refusal names the fix;
2. at an episode's first step (`episode_score`): no R_bar is always an error (every step would stop); an
   uncalibrated score is one when something acts on u, and otherwise u is the paper's rate, with a warning.
"""

from __future__ import annotations

import logging
import math

import torch
from torch import nn

from .configuration_vib import VIBConfigError
from .scores import MAP_SCORES

logger = logging.getLogger(__name__)

CALIBRATE = "`lerobot-vib-calibrate --policy.path=<checkpoint> --dataset.repo_id=<its training data>`"


def missing_score_parts(policy: nn.Module, score: str) -> list[str]:
    """What `score` needs that this checkpoint (a VIBPolicy) lacks."""
    missing = []
    if score != "rate" and not math.isfinite(policy.score_mean(score)):
        missing.append("its mean over the training frames")
    if policy.config.encoder == "tokens":
        if score in MAP_SCORES and not torch.isfinite(policy.map_cell_mean).all():
            missing.append("each image cell's rate statistics")
    elif score in ("image_rate", "low_image_rate") and not torch.isfinite(policy.state_embedding_mean).all():
        missing.append("the state path's training mean")
    if score == "embedding_rnd" and not policy.embedding_rnd.fitted:
        missing.append("a fitted RND")
    return missing


def _acts_on_u(policy: nn.Module) -> bool:
    return policy.config.safety.enabled or policy.config.temporal_ensemble == "uncertainty"


def check_ready_to_act_on_u(policy: nn.Module, source: str = "This checkpoint") -> None:
    """Step 1: refuse, when the policy loads and not at a robot's first step, a stop or Eq. 6 that could not
    work."""
    problems = []
    r_bar = policy.rate_mean()
    if not (math.isfinite(r_bar) and r_bar > 0):
        problems.append("it has no rate statistics (R_bar)")
    score = policy.config.uncertainty_score
    if missing := missing_score_parts(policy, score):
        problems.append(f"`uncertainty_score={score}` needs {' and '.join(missing)}")
    if problems:
        raise VIBConfigError(
            f"{source} cannot act on u ({'; '.join(problems)}): run {CALIBRATE} and load the calibrated "
            "checkpoint, or turn off what reads u (`--policy.safety.enabled=false`, `--policy.temporal_ensemble=act`)."
        )
    if not policy.config.safety.enabled:
        return
    gamma = policy.stop_threshold(step=0)
    if not math.isfinite(gamma):
        raise VIBConfigError(f"{source}: the safety stop is enabled but its threshold gamma is unknown.")
    resume = policy.config.safety.resume_threshold
    if resume is not None and not policy.config.calibration.gamma_band and resume > gamma:
        raise VIBConfigError(
            f"{source}: `safety.resume_threshold` ({resume}) must not exceed gamma ({gamma:.4g}): a u between "
            "them would resume and stop again at once."
        )


def episode_score(policy: nn.Module) -> str:
    """Step 2: the score u is read from in the episode that starts."""
    r_bar = policy.rate_mean()
    if not (math.isfinite(r_bar) and r_bar > 0):
        raise RuntimeError(
            "This VIB policy has no rate statistics (R_bar), so its uncertainty u = R / R_bar is unknown and "
            "every step would be a safety stop. Train it with lerobot-train (which keeps running statistics) "
            "or run `lerobot-vib-calibrate` on its training data."
        )
    score = policy.config.uncertainty_score
    missing = missing_score_parts(policy, score)
    if not missing:
        return score
    message = (
        f"`uncertainty_score={score}` needs {' and '.join(missing)}, which this checkpoint lacks: run {CALIBRATE} "
        "(it computes every score's statistics and fits the RND), or use `--policy.uncertainty_score=rate`."
    )
    if _acts_on_u(policy):
        raise RuntimeError(message)
    # Nothing acts on u: trace the paper's rate, which training already normalizes, rather than refuse.
    logger.warning("%s Until then u is the rate's.", message)
    return "rate"
