"""One plan of episode seeds for every evaluation here: which seeds may choose or calibrate, which only report.

    recording       0..         `lerobot-vib-record-sim`'s scripted demonstrations (the training data)
    learning        100000..    learning curves (`benchmarks/arm_learning.py`); nothing is chosen on them
    calibration     200000..    rollouts that a stop threshold, a statistic or a fitted part is set on
    validation      400000..    every choice: run time, beta, floor, score, monitor; rollout thresholds too
    test            600000..    reported only: nothing is calibrated or chosen on them, anywhere

Each range holds 100000 seeds, so no two overlap for any episode count used here. A run that needs other seeds
(to rerun a report made before this plan) passes them as flags, and its report says so.
"""

from __future__ import annotations

SPAN = 100_000
PLAN: dict[str, int] = {
    "recording": 0,
    "learning": 100_000,
    "calibration": 200_000,
    "validation": 400_000,
    "test": 600_000,
}
CALIBRATION, VALIDATION, TEST = PLAN["calibration"], PLAN["validation"], PLAN["test"]


def seed_range(split: str, n_episodes: int, first: int | None = None) -> list[int]:
    """The first `n_episodes` seeds of `split` (from `first` where given), refused past the split's span."""
    if split not in PLAN:
        raise ValueError(f"Unknown seed split {split!r}; the plan has {sorted(PLAN)}.")
    if not 0 <= n_episodes <= SPAN:
        raise ValueError(f"{n_episodes} episodes do not fit a split of {SPAN} seeds.")
    start = PLAN[split] if first is None else first
    return list(range(start, start + n_episodes))
