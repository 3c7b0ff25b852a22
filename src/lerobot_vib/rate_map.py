"""Where the token network's rate map points: is the hottest (or the coldest) image cell where the image changed?

The token network gives one rate per cell of the trunk's feature map (`policy.last_step.rate_map`,
(B, cameras, H', W')). Cell (i, j) is the trunk's output for the image block of rows
[round(i H / H'), round((i + 1) H / H')) and columns likewise: its receptive field is wider, but the block is
the part of the image it stands for. Given a mask of changed pixels (the occluder, from the simulator's
segmentation), a cell lies *under* the mask when the mask covers at least half of its block. A frame counts
as pointing when its hottest cell lies under the mask:

    share  = frames whose argmax cell is under the mask / frames with a non-empty mask
    chance = mean over those frames of (cells under the mask / all cells)

so that `share` can be read against what a map of random values would score (`chance`): a board that covers
most of the image makes pointing at it easy. `end="coldest"` asks the same of the smallest cell: a board hides
what was behind it, and a featureless view can *lower* a cell's rate (docs/uncertainty.md), so the map may
point at the board by its coldest cell. Neither extreme says how far the board's cells stand apart, so

    contrast = mean over those frames of (mean of the map under the mask - mean elsewhere)

gives that in the map's own units (standard deviations, for a map of z-scores).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np


def cells_under(mask: np.ndarray, grid: tuple[int, int]) -> np.ndarray:
    """(H', W') bool: the cells of a `grid` = (H', W') map over the (H, W) `mask` whose image block the mask
    covers for at least half of its pixels."""
    mask = np.asarray(mask, dtype=bool)
    if mask.ndim != 2:
        raise ValueError(f"The mask must be (H, W), got shape {mask.shape}.")
    rows, cols = grid
    if not (0 < rows <= mask.shape[0] and 0 < cols <= mask.shape[1]):
        raise ValueError(f"A {rows}x{cols} map cannot tile a {mask.shape[0]}x{mask.shape[1]} mask.")
    r = np.round(np.linspace(0, mask.shape[0], rows + 1)).astype(int)
    c = np.round(np.linspace(0, mask.shape[1], cols + 1)).astype(int)
    covered = np.add.reduceat(np.add.reduceat(mask.astype(float), r[:-1], axis=0), c[:-1], axis=1)
    area = np.outer(np.diff(r), np.diff(c))
    return covered / area >= 0.5


def hottest_cell(rate_map: np.ndarray) -> tuple[int, int]:
    """The (row, column) of the largest value of an (H', W') map."""
    rate_map = np.asarray(rate_map, dtype=float)
    if rate_map.ndim != 2 or not np.isfinite(rate_map).all():
        raise ValueError(f"The rate map must be a finite (H', W') array, got shape {rate_map.shape}.")
    return tuple(int(i) for i in np.unravel_index(np.argmax(rate_map), rate_map.shape))


ENDS = ("hottest", "coldest")


def pointing(
    rate_maps: Sequence[np.ndarray], masks: Sequence[np.ndarray], end: str = "hottest"
) -> dict[str, float | int]:
    """`share`, `chance` and `contrast` (the module docstring) over the frames whose mask is not empty, and
    their count; `end` names the cell that must lie under the mask."""
    if end not in ENDS:
        raise ValueError(f"end must be one of {ENDS}, got {end!r}.")
    if len(rate_maps) != len(masks):
        raise ValueError(f"{len(rate_maps)} rate maps against {len(masks)} masks.")
    sign = 1.0 if end == "hottest" else -1.0
    hits, chance, contrast, frames = 0, 0.0, 0.0, 0
    for rate_map, mask in zip(rate_maps, masks, strict=True):
        rate_map = np.asarray(rate_map, dtype=float)
        under = cells_under(mask, np.shape(rate_map))
        if not under.any():
            continue
        frames += 1
        hits += bool(under[hottest_cell(sign * rate_map)])
        chance += float(under.mean())
        contrast += float(rate_map[under].mean() - rate_map[~under].mean()) if (~under).any() else 0.0
    if not frames:
        return {"frames": 0, "share": float("nan"), "chance": float("nan"), "contrast": float("nan")}
    return {"frames": frames, "share": hits / frames, "chance": chance / frames, "contrast": contrast / frames}
