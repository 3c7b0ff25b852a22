"""Failure prediction per episode: will this episode fail, and how early is it known?

Ground truth. An episode fails when it is not solved by its end. Failed episodes are the positives and
successful ones the negatives, perturbed successes included: an alarm on an episode the policy handles is a
false alarm, however strange its images. Where the simulator shows it, the *failure moment* is the first
missed grasp (`info["grasp_missed"]`, arm_env.py), and the lead time is measured against it.

Monitor. One score's u_t per step (u = s / s_bar, as the stop reads it), smoothed over a window of w steps:

    m_t = mean(u_{t-w+1..t})   or   sum(u_{t-w+1..t})        (only the steps so far in the episode's first w)

It alarms at its first step with m_t > tau_t, a non-finite m_t included (unknown means stop). Combinations:

    AND   alarms at the first step at which every member is above its own threshold (FIPER's AND of two scores)
    OR    (`AnyOf`) alarms at the first step at which any member monitor alarms, each with its own window and
          threshold: one score that sees a scene the policy never saw (an RND on the embedding) beside one that
          sees the arm go astray (the state tokens' rate) alarms early where either failure shows first

Calibration, by split-conformal prediction on successful clean rollouts only, at a false-alarm level alpha:

    constant   tau   = the ceil((n + 1)(1 - alpha))-th smallest of max_t m_t over the n calibration episodes
    band       tau_t = q b_t: b_t the mean of m_t over the first half of the calibration episodes (the
               shape), q the conformal threshold of max_t m_t / b_t over the second half
               (metrics.time_indexed_band); the halves `lerobot-vib-calibrate --rollouts` takes, so that the
               stop it sets is the one measured here
    std_band   tau_t = mu_t + q s_t: the mean and standard deviation of m_t over the first half, q the
               conformal threshold of max_t (m_t - mu_t) / s_t over the second (metrics.std_band), the band
               FAIL-Detect calibrates: tight in the steps where successful episodes agree, so a scene that is
               wrong from the start can alarm at once

so that a successful clean episode exchangeable with the calibration ones alarms with probability at most
alpha. The members of an AND are each calibrated at alpha; the AND alarms no more often than any of them. The
k members of an OR are each calibrated at alpha / k: by the union bound the OR alarms with probability at most
alpha. An OR may hold its partners (every member but the first) at a margin c >= 1 times their conformal
threshold: a threshold above the conformal one alarms on a clean episode no more often, so the guarantee
stands, and the partner then fires only on what lies far outside the clean rollouts (a black camera, not a
noisy one). c is chosen on validation rollouts like the rest of the monitor.

Metrics over a set of episodes: TPR (failures alarmed), TNR (successes not alarmed), accuracy, balanced
accuracy (TPR + TNR) / 2; detection time, the first alarm's step over the episode's length, in alarmed
failures; lead time, the failure moment minus the first alarm's step (positive: the alarm came first), in
alarmed failures that have a failure moment.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from .calibration import conformal_gamma, conformal_min_scores
from .metrics import BANDS

AGGREGATES = ("mean", "sum")
THRESHOLDS = ("constant", "band", "std_band")
BAND_FLAGS = {"constant": "max", "band": "time_band", "std_band": "std_band"}  # as `lerobot-vib-calibrate --threshold`
CLEAN = "normal"


class CalibrationError(ValueError):
    """A monitor cannot be calibrated on the given rollouts (too few successful clean ones, a missing score)."""


@dataclass(frozen=True)
class Monitor:
    """What raises an alarm: the scores (one, or several joined by AND), the window and how it aggregates,
    and the kind of threshold."""

    scores: tuple[str, ...]
    window: int = 1
    aggregate: str = "mean"
    threshold: str = "constant"

    def __post_init__(self):
        if not self.scores or len(set(self.scores)) != len(self.scores):
            raise ValueError(f"A monitor needs distinct scores, got {self.scores}.")
        if self.window < 1:
            raise ValueError(f"A monitor's window must be >= 1 step, got {self.window}.")
        if self.aggregate not in AGGREGATES:
            raise ValueError(f"aggregate must be one of {AGGREGATES}, got {self.aggregate!r}.")
        if self.threshold not in THRESHOLDS:
            raise ValueError(f"threshold must be one of {THRESHOLDS}, got {self.threshold!r}.")

    @property
    def name(self) -> str:
        return f"{' & '.join(self.scores)}, w={self.window} {self.aggregate}, {self.threshold}"

    def as_dict(self) -> dict:
        return {"scores": list(self.scores), "window": self.window, "aggregate": self.aggregate,
                "threshold": self.threshold}  # fmt: skip

    @staticmethod
    def from_dict(d: dict) -> Monitor:
        return Monitor(tuple(d["scores"]), int(d["window"]), d["aggregate"], d["threshold"])


@dataclass(frozen=True)
class AnyOf:
    """An OR of monitors: it alarms when any member does. Each member keeps its own window and threshold and is
    calibrated at alpha / k (the module docstring)."""

    members: tuple[Monitor, ...]
    margin: float = 1.0  # the partners' thresholds: this many times their conformal ones (the module docstring)

    def __post_init__(self):
        if len(self.members) < 2 or not all(isinstance(m, Monitor) for m in self.members):
            raise ValueError(f"An OR needs at least two monitors, got {self.members}.")
        if len(set(self.scores)) != len(self.scores):
            raise ValueError(f"An OR's members must read distinct scores, got {self.scores}.")
        if not (math.isfinite(self.margin) and self.margin >= 1):
            raise ValueError(f"An OR's margin must be >= 1 (a lower one would break alpha), got {self.margin}.")

    @property
    def scores(self) -> tuple[str, ...]:
        return tuple(s for m in self.members for s in m.scores)

    @property
    def threshold(self) -> str:
        return self.members[0].threshold

    @property
    def name(self) -> str:
        partners = " OR ".join(f"({m.name})" for m in self.members[1:])
        if self.margin != 1:
            partners = f"{self.margin:g} x [{partners}]"
        return f"({self.members[0].name}) OR {partners}"

    def as_dict(self) -> dict:
        return {"any_of": [m.as_dict() for m in self.members], **({"margin": self.margin} if self.margin != 1 else {})}


def monitor_from_dict(d: dict) -> Monitor | AnyOf:
    """A monitor as `as_dict` wrote it, an OR included."""
    if "any_of" in d:
        return AnyOf(tuple(Monitor.from_dict(m) for m in d["any_of"]), float(d.get("margin", 1.0)))
    return Monitor.from_dict(d)


@dataclass
class Episode:
    """What failure prediction reads of one rollout (recorded with the stop off)."""

    success: bool
    scores: dict[str, np.ndarray]  # u per step, by score
    condition: str = CLEAN
    failure_moment: int | None = None  # the first missed grasp's step; None: none, or not measurable
    seed: int | None = None
    # Scores fitted on this very rollout (an RND fitted on clean rollouts): they read it in-sample, so it
    # neither sets nor judges their thresholds
    fitted_on: frozenset[str] = frozenset()

    @property
    def length(self) -> int:
        return max((len(v) for v in self.scores.values()), default=0)


def windowed(u: Sequence[float], window: int, aggregate: str = "mean") -> np.ndarray:
    """m_t over the last `window` steps of `u` (the module docstring); a non-finite u_t makes m_t non-finite."""
    u = np.asarray(u, dtype=np.float64)
    if window == 1:
        return u.copy()
    csum = np.concatenate([[0.0], np.cumsum(u)])
    t = np.arange(1, len(u) + 1)
    start = np.maximum(t - window, 0)
    total = csum[t] - csum[start]
    return total / (t - start) if aggregate == "mean" else total


def candidate_monitors(
    scores: Sequence[str],
    windows: Sequence[int] = (1, 5, 10),
    aggregates: Sequence[str] = AGGREGATES,
    thresholds: Sequence[str] = THRESHOLDS,
    pairs: bool = True,
) -> list[Monitor]:
    """Every single score and, with `pairs`, every AND of two, at every window, aggregate and threshold (a
    window of 1 aggregates one way only)."""
    groups = [(s,) for s in scores] + (list(itertools.combinations(scores, 2)) if pairs else [])
    out = []
    for group in groups:
        for w in windows:
            for agg in aggregates if w > 1 else ("mean",):
                out += [Monitor(tuple(group), w, agg, th) for th in thresholds]
    return out


def or_candidates(
    scores: Sequence[str],
    windows: Sequence[int] = (1, 5, 10),
    thresholds: Sequence[str] = THRESHOLDS,
    sizes: Sequence[int] = (2,),
    margins: Sequence[float] = (1.0,),
) -> list[AnyOf]:
    """Every OR of `sizes` scores as the policy's stop runs one: the first score at every window and threshold,
    its partners with constant thresholds (a band on the first score only) over one shared window, at every
    margin; windows aggregated by their mean. ORs that differ only in the order of constant members are listed
    once."""
    out, seen = [], set()
    for size in sizes:
        for a in scores:
            for partners in itertools.combinations([s for s in scores if s != a], size - 1):
                for wa, wb, th, c in itertools.product(windows, windows, thresholds, margins):
                    first = Monitor((a,), wa, "mean", th)
                    rest = tuple(Monitor((b,), wb, "mean", "constant") for b in partners)
                    # with a margin the first member is not interchangeable with its partners
                    key = (frozenset((first, *rest)), c) if th == "constant" and c == 1 else (first, rest, c)
                    if key not in seen:
                        seen.add(key)
                        out.append(AnyOf((first, *rest), c))
    return out


@dataclass
class CalibratedMonitor:
    monitor: Monitor
    alpha: float
    thresholds: dict[str, float | np.ndarray]  # per member score: a constant, or a band (one per step)
    n_calibration: int  # successful clean rollouts it was calibrated on
    calibration_seeds: list[int | None] = field(default_factory=list)

    def trace(self, episode: Episode, score: str) -> np.ndarray:
        if score not in episode.scores:
            raise CalibrationError(f"The episode has no {score!r} trace; it has {sorted(episode.scores)}.")
        return windowed(episode.scores[score], self.monitor.window, self.monitor.aggregate)

    def above(self, episode: Episode) -> np.ndarray:
        """(T,) bool: every member above its threshold (or not finite) at each step."""
        length = episode.length
        hit = np.ones(length, dtype=bool)
        for score in self.monitor.scores:
            m = self.trace(episode, score)
            tau = _band_for(self.thresholds[score], length)
            hit &= ~np.isfinite(m) | (m > tau)
        return hit

    def alarm(self, episode: Episode) -> int | None:
        """The first alarm's step; None if it never fires."""
        hit = np.flatnonzero(self.above(episode))
        return int(hit[0]) if len(hit) else None

    def as_dict(self) -> dict:
        return {
            "monitor": self.monitor.as_dict(),
            "alpha": self.alpha,
            "thresholds": {k: np.round(np.asarray(v, dtype=float), 6).tolist() for k, v in self.thresholds.items()},
            "n_calibration": self.n_calibration,
            "calibration_seeds": self.calibration_seeds,
        }


@dataclass
class CalibratedAnyOf:
    monitor: AnyOf
    alpha: float
    members: list[CalibratedMonitor]  # each at alpha / k

    @property
    def n_calibration(self) -> int:
        return min(m.n_calibration for m in self.members)

    def above(self, episode: Episode) -> np.ndarray:
        """(T,) bool: any member above its thresholds at each step."""
        hit = np.zeros(episode.length, dtype=bool)
        for m in self.members:
            a = m.above(episode)
            hit[: len(a)] |= a
        return hit

    def alarm(self, episode: Episode) -> int | None:
        hit = np.flatnonzero(self.above(episode))
        return int(hit[0]) if len(hit) else None

    def as_dict(self) -> dict:
        return {"monitor": self.monitor.as_dict(), "alpha": self.alpha, "members": [m.as_dict() for m in self.members]}


def _band_for(tau: float | np.ndarray, length: int) -> np.ndarray:
    tau = np.asarray(tau, dtype=np.float64)
    if tau.ndim == 0:
        return np.full(length, float(tau))
    return np.concatenate([tau, np.full(max(length - len(tau), 0), tau[-1])])[:length]


def unseen_by(episodes: Sequence[Episode], scores: Sequence[str]) -> list[Episode]:
    """The rollouts none of `scores` was fitted on."""
    return [e for e in episodes if not e.fitted_on & set(scores)]


def calibration_episodes(episodes: Sequence[Episode], scores: Sequence[str] = ()) -> list[Episode]:
    """The rollouts a threshold of `scores` may be set on: successful and clean, and not fitted on by any of
    them; nothing else."""
    return [e for e in unseen_by(episodes, scores) if e.success and e.condition == CLEAN]


def calibrate_monitor(
    monitor: Monitor | AnyOf, episodes: Sequence[Episode], alpha: float
) -> CalibratedMonitor | CalibratedAnyOf:
    """Thresholds of `monitor` at level `alpha` from the successful clean ones among `episodes` (the others
    are ignored: failures and perturbed rollouts never set a threshold, nor rollouts a member was fitted on).
    An OR's k members are each calibrated at alpha / k."""
    if isinstance(monitor, AnyOf):
        share = alpha / len(monitor.members)
        members = [calibrate_monitor(m, episodes, share) for m in monitor.members]
        for i, m in enumerate(members[1:], start=1):
            members[i] = replace(m, thresholds={k: monitor.margin * v for k, v in m.thresholds.items()})
        return CalibratedAnyOf(monitor, alpha, members)
    calib = calibration_episodes(episodes, monitor.scores)
    needed = conformal_min_scores(alpha) * (1 if monitor.threshold == "constant" else 2)
    if len(calib) < needed:
        raise CalibrationError(
            f"{monitor.name} at alpha={alpha} needs {needed} successful clean rollouts; got {len(calib)}."
        )
    probe = CalibratedMonitor(monitor, alpha, {}, len(calib))
    thresholds: dict[str, float | np.ndarray] = {}
    for score in monitor.scores:
        traces = [probe.trace(e, score) for e in calib]
        if not all(np.isfinite(t).all() and len(t) for t in traces):
            raise CalibrationError(f"{score!r} is missing or not finite on a calibration rollout.")
        if monitor.threshold == "constant":
            thresholds[score] = conformal_gamma(np.array([t.max() for t in traces]), alpha)
        else:
            if min(float(t.min()) for t in traces) <= 0:
                raise CalibrationError(f"A band needs a positive score; {score!r} is not on every step.")
            half = len(traces) // 2  # as `lerobot-vib-calibrate --rollouts` splits them: the same band
            try:
                thresholds[score] = BANDS[BAND_FLAGS[monitor.threshold]](traces[:half], traces[half:], alpha)
            except ValueError as e:
                raise CalibrationError(f"{monitor.name}: {e}") from e
    return CalibratedMonitor(monitor, alpha, thresholds, len(calib), [e.seed for e in calib])


@dataclass
class FailureMetrics:
    n_failed: int
    n_succeeded: int
    alarmed_failed: int
    alarmed_succeeded: int
    detection_times: list[float]  # per alarmed failure: first alarm step / episode length
    lead_times: list[int]  # per alarmed failure with a failure moment: moment - first alarm step

    @property
    def tpr(self) -> float | None:
        return self.alarmed_failed / self.n_failed if self.n_failed else None

    @property
    def tnr(self) -> float | None:
        return 1 - self.alarmed_succeeded / self.n_succeeded if self.n_succeeded else None

    @property
    def accuracy(self) -> float | None:
        n = self.n_failed + self.n_succeeded
        correct = self.alarmed_failed + self.n_succeeded - self.alarmed_succeeded
        return correct / n if n else None

    @property
    def balanced_accuracy(self) -> float | None:
        if self.tpr is None or self.tnr is None:
            return None
        return (self.tpr + self.tnr) / 2

    @property
    def detection_time(self) -> float | None:
        return float(np.mean(self.detection_times)) if self.detection_times else None

    @property
    def median_lead_time(self) -> float | None:
        return float(np.median(self.lead_times)) if self.lead_times else None

    def as_dict(self) -> dict:
        return {
            "n_failed": self.n_failed,
            "n_succeeded": self.n_succeeded,
            "alarmed_failed": self.alarmed_failed,
            "alarmed_succeeded": self.alarmed_succeeded,
            "tpr": self.tpr,
            "tnr": self.tnr,
            "accuracy": self.accuracy,
            "balanced_accuracy": self.balanced_accuracy,
            "detection_time": self.detection_time,
            "median_lead_time": self.median_lead_time,
            "n_lead_times": len(self.lead_times),
        }


def evaluate(calibrated: CalibratedMonitor | CalibratedAnyOf, episodes: Sequence[Episode]) -> FailureMetrics:
    """The monitor's alarms judged against each episode's outcome (the module docstring's metrics)."""
    failed = [e for e in episodes if not e.success]
    succeeded = [e for e in episodes if e.success]
    detection, lead, alarmed_failed = [], [], 0
    for e in failed:
        t = calibrated.alarm(e)
        if t is None:
            continue
        alarmed_failed += 1
        detection.append(t / max(e.length, 1))
        if e.failure_moment is not None:
            lead.append(int(e.failure_moment) - t)
    alarmed_succeeded = sum(calibrated.alarm(e) is not None for e in succeeded)
    return FailureMetrics(len(failed), len(succeeded), alarmed_failed, alarmed_succeeded, detection, lead)


def judge_candidates(
    candidates: Sequence[Monitor | AnyOf],
    validation: dict[object, Sequence[Episode]],
    alpha: float,
    benign: Sequence[str] = (),
) -> list[dict]:
    """Each candidate calibrated per group of `validation` (one per training seed, on that group's own
    successful clean rollouts) and judged on the group's rollouts its scores were not fitted on: one row per
    candidate that calibrates in every group, {"monitor", "order", "groups": {group: (metrics on every judged
    rollout, metrics on its successes under the `benign` conditions)}}. `rank` turns the rows into a ranking
    over any subset of the groups, so that a rule can be checked on a group it did not choose on."""
    rows = []
    for i, monitor in enumerate(candidates):
        groups = {}
        for group, episodes in validation.items():
            try:
                calibrated = calibrate_monitor(monitor, episodes, alpha)
            except CalibrationError:
                break
            judged = unseen_by(episodes, monitor.scores)
            groups[group] = (
                evaluate(calibrated, judged),
                evaluate(calibrated, [e for e in judged if e.success and e.condition in benign]),
            )
        else:
            rows.append({"monitor": monitor, "order": i, "groups": groups})
    return rows


def rank(judged: Sequence[dict], groups: Sequence[object] | None = None) -> list[dict]:
    """`judge_candidates`' rows aggregated over `groups` (default: all), best balanced accuracy first; a tie goes
    to the earlier detection, then to the one listed first. The balanced accuracy is the mean TPR over the
    groups with failures and the mean TNR over every group, so that a seed which solves every validation
    episode neither hides the others' failures nor its own false alarms; a row's "benign_stopped" is the mean
    share of benign successes alarmed. A candidate with no TPR or no TNR over the groups is left out."""
    rows = []
    for row in judged:
        chosen = [row["groups"][g] for g in (row["groups"] if groups is None else groups)]
        tprs = [m.tpr for m, _ in chosen if m.tpr is not None]
        tnrs = [m.tnr for m, _ in chosen if m.tnr is not None]
        if not tprs or not tnrs:
            continue
        tpr, tnr = float(np.mean(tprs)), float(np.mean(tnrs))
        detection = [m.detection_time for m, _ in chosen if m.detection_time is not None]
        benign_stopped = [1 - b.tnr for _, b in chosen if b.tnr is not None]
        rows.append(
            {
                "monitor": row["monitor"],
                "order": row["order"],
                "balanced_accuracy": (tpr + tnr) / 2,
                "tpr": tpr,
                "tnr": tnr,
                "detection_time": float(np.mean(detection)) if detection else math.inf,
                "benign_stopped": float(np.mean(benign_stopped)) if benign_stopped else None,
            }
        )
    rows.sort(key=lambda r: (-r["balanced_accuracy"], r["detection_time"], r["order"]))
    return rows


def choose_monitor(
    candidates: Sequence[Monitor | AnyOf],
    validation: dict[object, Sequence[Episode]],
    alpha: float,
    benign: Sequence[str] = (),
) -> tuple[Monitor | AnyOf | None, list[dict]]:
    """The candidate with the best balanced accuracy on the validation rollouts, averaged over the groups of
    `validation` (`judge_candidates`, `rank`). Returns it (None: none could be calibrated, or no group failed)
    and every candidate's row, best first. Only validation rollouts are read."""
    rows = rank(judge_candidates(candidates, validation, alpha, benign))
    return (rows[0]["monitor"] if rows else None), rows
