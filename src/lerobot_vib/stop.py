"""What VIBPolicy's safety stop reads and says at each step, per env (the decision itself is safety.py's).

At every step, in this order:

1. the threshold in force, gamma_t: one gamma, or a time-indexed band read at each env's own *progress*
   (the steps it ran; a stopped env does not advance, so the band cannot release a held arm by the clock);
2. what the stop compares with it, the stop value v_t:

       m_t = u over the env's last w steps (mean or sum; `calibration.window`, u itself for w = 1)
       v_t = m_t                                                 one score
       v_t = gamma_t * min(m_t / gamma_t, m_k,t / gamma_k ...)   an AND (`calibration.and_gammas`): above
                                                                 gamma_t exactly when every member is above its
                                                                 own threshold, below the resume threshold as
                                                                 soon as any member falls
3. safety.py's `SafetyMonitor` decides (stop, resume, halt) on v_t against gamma_t;
4. each stop, resume and halt is logged once, when it happens, with v_t and the threshold in force: what
   `lerobot-eval` and `lerobot-rollout` show of the stop.

`start` checks the stop's settings at the start of an episode and builds the monitor.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch
from lerobot.utils.constants import ACTION
from torch import Tensor

from .calibration import threshold_source
from .safety import RobotUnits, SafetyMonitor

logger = logging.getLogger(__name__)


@dataclass
class UncertaintyStep:
    """What `select_action` measured and decided at one step, per batch element."""

    rate: Tensor  # (B,) R of this step's observation
    u: Tensor  # (B,) R / R_bar
    gamma: float  # the stop threshold on u (reported even when the threshold stop is disabled)
    threshold_active: bool  # whether u > gamma stops the policy (`safety.enabled`)
    stopped: Tensor  # (B,) bool: the safety action was emitted
    just_stopped: Tensor  # (B,) bool: RUN -> STOP at this step
    resumed: Tensor  # (B,) bool: STOP -> RUN at this step
    halted: Tensor | None = None  # (B,) bool: the stop is terminal; only `policy.resume()` ends it
    score: str = "rate"  # the score u was read from (`VIBConfig.uncertainty_score`)
    scores: dict[str, Tensor] | None = None  # (B,) raw value of every score computed at this step, by name
    rate_map: Tensor | None = None  # (B, cameras, H', W') the image tokens' rates (token network only)
    # (B,) each env's threshold, where a time band is read at each env's progress (`gamma` is env 0's)
    thresholds: Tensor | None = None
    # (B,) what the stop compared with the threshold: u over the calibrated window (`calibration.window`; u
    # itself when it is 1)
    stop_value: Tensor | None = None
    # (B, D) the observation embedding "embedding_rnd" reads, kept while every score is traced
    # (`trace_all_scores`): an RND can then be fitted on rollouts as well as on the training frames
    embedding: Tensor | None = None

    def row(self, i: int = 0) -> dict[str, float | bool]:
        """Batch element i as plain numbers (for traces)."""
        return {
            "rate": float(self.rate[i]),
            "u": float(self.u[i]),
            "gamma": self.gamma,
            "stopped": bool(self.stopped[i]),
            "just_stopped": bool(self.just_stopped[i]),
            "resumed": bool(self.resumed[i]),
            "halted": bool(self.halted[i]) if self.halted is not None else False,
        }


class PolicyStop:
    """One episode's stop state: each env's progress, its last `window` steps of u per score, and which envs
    were halted, for the config of a VIBPolicy.

    Args:
        config: The policy's VIBConfig.
        score_mean: A score's training mean by name (u = s / s_bar), as the policy normalizes it.
        threshold_at: gamma at an episode step (calibration.stop_threshold).
    """

    def __init__(self, config: Any, score_mean: Callable[[str], float], threshold_at: Callable[[int], float]):
        self.config = config
        self.score_mean = score_mean
        self.threshold_at = threshold_at
        self.progress: Tensor | None = None  # (B,) steps each env ran, stopped ones not counted
        self.recent_u: dict[str, list[Tensor]] = {}  # per score the stop reads: its last `window` steps' u
        self.halted_before: Tensor | None = None

    def start(self, score: str, robot_units: RobotUnits, announce: bool) -> SafetyMonitor:
        """The episode's monitor, after checking the stop's settings; `announce` logs the threshold in force
        (once per policy, by the caller's choice)."""
        safety, calibration = self.config.safety, self.config.calibration
        stale_gamma = calibration.gamma is not None and (calibration.gamma_score or "rate") != score
        if safety.enabled and safety.gamma is None and stale_gamma:
            logger.warning(
                "The calibrated gamma was set on the %s score, but u is read from %s: the stop uses mean + 2 "
                "std of %s instead. Set gamma on this score (lerobot-vib-calibrate --rollouts=...).",
                calibration.gamma_score or "rate", score, score,
            )  # fmt: skip
        if (safety.action == "home" or safety.home_pose is not None) and not robot_units.known(ACTION):
            raise RuntimeError(
                "`safety.home_pose` is in robot units, but the policy lacks the action normalization statistics "
                "to convert it: build the policy with `dataset_stats` (lerobot-train does) or use `hold`."
            )
        gamma = self.threshold_at(0) if safety.enabled else None
        if gamma is not None and not math.isfinite(gamma):
            raise RuntimeError("The safety stop is enabled but its threshold gamma is unknown: set `safety.gamma`.")
        if gamma is not None and gamma < 1 and not calibration.gamma_band:
            logger.warning(
                "The safety stop's threshold gamma = %.3g is below 1, the mean u of the training data: most "
                "in-distribution steps will stop the policy. Check `safety.gamma` / `calibration.gamma`.",
                gamma,
            )
        resume = safety.resume_threshold if safety.resume_threshold is not None else gamma
        if resume is not None and gamma is not None and calibration.gamma_band:
            resume = min(resume, gamma)  # the band moves gamma every step; the hysteresis stays below it
        if safety.enabled and announce:
            logger.warning(
                "Safety stop on: u is %s over its training mean; the stop threshold in force is %s (gamma = %.4g "
                "at the first step).",
                score, threshold_source(self.config), gamma,
            )  # fmt: skip
        return SafetyMonitor(gamma, resume, safety.resume_steps, safety.max_hold_steps)

    def threshold(self, monitor: SafetyMonitor, step: int, u: Tensor) -> tuple[float, Tensor | None]:
        """(gamma, per-env thresholds or None) in force at this step, set on `monitor`: a band is read at each
        env's progress (`safety.band_index="progress"`) or at the episode step; `gamma` is env 0's."""
        gamma = self.threshold_at(step)
        if not (self.config.calibration.gamma_band and monitor.gamma is not None):
            return gamma, None
        resume = self.config.safety.resume_threshold
        if self.config.safety.band_index != "progress":
            monitor.set_threshold(gamma, resume)
            return gamma, None
        if self.progress is None:
            self.progress = torch.zeros(u.shape[0], dtype=torch.long, device=u.device)
        thresholds = torch.tensor([self.threshold_at(int(p)) for p in self.progress], dtype=u.dtype, device=u.device)
        monitor.set_threshold(thresholds, resume)
        return self.threshold_at(int(self.progress[0])), thresholds

    def advance(self, stopped: Tensor) -> None:
        """After the decision: an env that ran advances its progress; a stopped one holds still."""
        if self.progress is not None:
            self.progress += (~stopped.to(self.progress.device)).long()

    def windowed(self, u: Tensor, score: str = "", window: int | None = None) -> Tensor:
        """m_t of `score`'s u over `window` steps (default the calibrated one; module docstring); a non-finite u
        in the window stays unknown."""
        window = self.config.calibration.window if window is None else window
        if window == 1:
            return u
        recent = [*self.recent_u.get(score, [])[-(window - 1) :], u]
        self.recent_u[score] = recent
        total = torch.stack(recent).sum(dim=0)
        return total / len(recent) if self.config.calibration.window_aggregate == "mean" else total

    def value(self, u: Tensor, scores: dict[str, Tensor] | None, gamma: float | Tensor) -> Tensor:
        """v_t (module docstring). `scores`: the step's raw score values, which an AND's or an OR's members are
        read from."""
        m = self.windowed(u)
        c = self.config.calibration
        partners, combine = (c.and_gammas, torch.minimum) if c.and_gammas else (c.or_gammas, torch.maximum)
        if not partners:
            return m
        window = c.window if c.and_gammas else c.or_window
        threshold = torch.as_tensor(gamma, dtype=m.dtype, device=m.device).expand_as(m)
        ratio = m / threshold
        for name, g in partners.items():
            if scores is None or name not in scores:
                raise RuntimeError(f"The stop needs the {name!r} score at every step, and this step has none.")
            partner = self.windowed(scores[name] / self.score_mean(name), name, window)
            # unknown means stop: a non-finite member makes v_t non-finite in either combination
            ratio = torch.where(torch.isfinite(partner), combine(ratio, partner / g), partner)
        return ratio * threshold

    def quantity(self) -> str:
        """What the stop reads, in words."""
        c = self.config.calibration
        quantity = "u" if c.window == 1 else f"u's {c.window_aggregate} over {c.window} steps"
        if c.and_gammas:
            quantity += " (AND " + ", ".join(f"{k} above {g:.3g}" for k, g in c.and_gammas.items()) + ")"
        if c.or_gammas:
            over = "" if c.or_window == 1 else f" over {c.or_window} steps"
            quantity += " (OR " + ", ".join(f"{k}{over} above {g:.3g}" for k, g in c.or_gammas.items()) + ")"
        return quantity

    def log_events(
        self, decision, value: Tensor, gamma: float | Tensor, obs_finite: Tensor, step: int, monitor: SafetyMonitor
    ) -> None:
        """One line per stop, resume and halt, when it happens. `gamma`: one, or one per env."""
        for i in torch.nonzero(decision.just_stopped).flatten().tolist():
            g = float(gamma[i]) if isinstance(gamma, Tensor) else gamma
            if not bool(obs_finite[i]) or not math.isfinite(float(value[i])):
                cause = "the observation or u is not finite (unknown means stop)"
            else:
                cause = f"{self.quantity()} = {float(value[i]):.3f} > gamma = {g:.3f}, {threshold_source(self.config)}"
            logger.warning("Safety stop: env %d at episode step %d: %s.", i, step, cause)
        resume = monitor.resume_threshold
        for i in torch.nonzero(decision.resumed).flatten().tolist():
            below = float(resume[i]) if isinstance(resume, Tensor) else float(resume)
            logger.warning(
                "Safety stop ended: env %d resumes at episode step %d (%s = %.3f, below %.3f for %d steps).",
                i, step, self.quantity(), float(value[i]), below, self.config.safety.resume_steps,
            )  # fmt: skip
        if decision.halted is not None:
            halted_now = decision.halted & ~self.halted_before if self.halted_before is not None else decision.halted
            for i in torch.nonzero(halted_now).flatten().tolist():
                logger.warning(
                    "Safety stop halted: env %d at episode step %d, after %d stopped steps "
                    "(safety.max_hold_steps); only policy.resume() ends it.",
                    i, step, self.config.safety.max_hold_steps,
                )  # fmt: skip
            self.halted_before = decision.halted.clone()
