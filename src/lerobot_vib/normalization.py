"""A floor under every normalization scale, so that a feature the demonstrations barely vary cannot explode.

LeRobot's normalizer divides by the dataset's scale: std for MEAN_STD, max - min for MIN_MAX, q99 - q01 and
q90 - q10 for the quantile modes. A joint that the demonstrations never move has a scale near zero (on the
simulated arm, joint 3's std is 0.00015 rad against 0.1-0.3 rad for the others), so a rollout deviation of
0.01 rad becomes a z-score of about 70, and everything downstream of the normalizer (the policy's inputs, the
rate, RND) follows that one joint. Each feature's scale s_i (dimension i) is therefore replaced by

    s_i' = max(s_i, floor * median_j s_j)           j over the feature's dimensions with s_j > 0,

relative to the feature's own dimensions because a unit-free rule serves radians, degrees and pixels alike.
A feature with no positive scale at all keeps a scale of 1 (centred, not scaled). MIN_MAX and quantile ranges
are widened about their midpoints. The floored statistics are the ones the processors save, so a checkpoint
normalizes at run time exactly as it trained. A one-dimensional feature has no sibling to compare with and is
never floored.

The default floor, 0.1, was chosen from the arm's statistics (docs/uncertainty.md): it lifts only the
never-moved joint (to 0.1 x the median joint std, about 0.015 rad) and leaves every other joint, the gripper
and the image channels untouched.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import torch
from lerobot.configs.types import FeatureType, NormalizationMode, PolicyFeature

logger = logging.getLogger(__name__)

# The statistics that set each mode's scale: (low, high) pairs, or ("std",) for MEAN_STD.
_SCALE_STATS = {
    NormalizationMode.MEAN_STD: ("std",),
    NormalizationMode.MIN_MAX: ("min", "max"),
    NormalizationMode.QUANTILES: ("q01", "q99"),
    NormalizationMode.QUANTILE10: ("q10", "q90"),
}


@dataclass
class FlooredFeature:
    """One feature whose scale was raised: its key, the dimensions, and their scales before and after."""

    key: str
    dims: list[int]
    before: list[float]
    after: list[float]

    def describe(self) -> str:
        changes = zip(self.dims, self.before, self.after, strict=True)
        pairs = ", ".join(f"[{d}] {b:.3g} -> {a:.3g}" for d, b, a in changes)
        return f"`{self.key}` {pairs}"


def _scale(stats: dict, names: tuple[str, ...]) -> torch.Tensor:
    if len(names) == 1:
        return torch.as_tensor(stats[names[0]], dtype=torch.float64)
    return torch.as_tensor(stats[names[1]], dtype=torch.float64) - torch.as_tensor(stats[names[0]], dtype=torch.float64)


def scale_floor(scale: torch.Tensor, floor: float) -> torch.Tensor:
    """The floored scales of one feature (same shape), by the rule in the module docstring."""
    flat = scale.reshape(-1)
    if flat.numel() < 2:
        return scale.clone()
    positive = flat[flat > 0]
    if positive.numel() == 0:
        return torch.ones_like(scale)
    return torch.clamp(scale, min=floor * float(positive.median()))


def _mode_of(ft: PolicyFeature, norm_map: dict) -> NormalizationMode:
    mode = norm_map.get(ft.type, norm_map.get(ft.type.value if isinstance(ft.type, FeatureType) else ft.type))
    return NormalizationMode(mode) if mode is not None else NormalizationMode.IDENTITY


def floor_stats(
    stats: dict[str, dict] | None,
    features: dict[str, PolicyFeature],
    norm_map: dict,
    floor: float,
) -> tuple[dict[str, dict] | None, list[FlooredFeature]]:
    """A copy of `stats` with every normalized feature's scale floored, and the features that changed."""
    if stats is None:
        return None, []
    if not floor > 0:
        raise ValueError(f"The normalization floor must be > 0, got {floor}.")
    out = {key: dict(value) for key, value in stats.items()}
    changed: list[FlooredFeature] = []
    for key, ft in features.items():
        names = _SCALE_STATS.get(_mode_of(ft, norm_map))
        if names is None or key not in stats or not all(n in stats[key] for n in names):
            continue
        scale = _scale(stats[key], names)
        new = scale_floor(scale, floor)
        raised = (new > scale).reshape(-1)
        if not raised.any():
            continue
        dims = torch.nonzero(raised).flatten().tolist()
        changed.append(FlooredFeature(key, dims, scale.reshape(-1)[dims].tolist(), new.reshape(-1)[dims].tolist()))
        original = stats[key][names[0]]

        def typed(value: torch.Tensor, like=original) -> object:
            # Keep the container the caller gave (LeRobot's datasets hold numpy arrays, checkpoints tensors).
            if torch.is_tensor(like):
                return value.to(like.dtype)
            return value.numpy().astype(getattr(like, "dtype", "float32"))

        if len(names) == 1:
            out[key][names[0]] = typed(new)
        else:
            low = torch.as_tensor(stats[key][names[0]], dtype=torch.float64)
            mid = low + scale / 2
            out[key][names[0]] = typed(mid - new / 2)
            out[key][names[1]] = typed(mid + new / 2)
    return out, changed


def warn_near_constant(changed: list[FlooredFeature], context: str) -> None:
    """Name the near-constant features (what `floor_stats` raised), so a user sees what the data never varies."""
    if changed:
        logger.warning(
            "%s: near-constant features (scale below the normalization floor, raised to it): %s. The "
            "demonstrations barely vary these dimensions; the policy cannot learn how they should move, and "
            "without the floor any deviation in them would dominate the inputs and the uncertainty.",
            context,
            "; ".join(c.describe() for c in changed),
        )


def near_constant_vectors(stats: dict[str, dict], floor: float = 0.1) -> list[FlooredFeature]:
    """Near-constant dimensions of a dataset's vector features (state, action), judged by their std as
    `floor_stats` would under MEAN_STD. For a recorder, which knows no policy config."""
    changed = []
    for key, value in stats.items():
        if "std" not in value or key.startswith("observation.images") or "image" in key:
            continue
        std = torch.as_tensor(value["std"], dtype=torch.float64)
        if std.ndim != 1:
            continue
        new = scale_floor(std, floor)
        dims = torch.nonzero(new > std).flatten().tolist()
        if dims:
            changed.append(FlooredFeature(key, dims, std[dims].tolist(), new[dims].tolist()))
    return changed
