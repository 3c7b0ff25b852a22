"""Where the token network's rate map points: is the hottest image cell where the image changed?

The token network gives one rate per cell of the trunk's feature map (`policy.last_step.rate_map`,
(B, cameras, H', W')). Cell (i, j) is the trunk's output for the image block of rows
[round(i H / H'), round((i + 1) H / H')) and columns likewise: its receptive field is wider, but the block is
the part of the image it stands for. Given a mask of changed pixels (the occluder, from the simulator's
segmentation), a cell lies *under* the mask when the mask covers at least half of its block. A frame counts
as pointing when its hottest cell lies under the mask:

    share  = frames whose argmax cell is under the mask / frames with a non-empty mask
    chance = mean over those frames of (cells under the mask / all cells)

so that `share` can be read against what a map of random values would score (`chance`): a board that covers
most of the image makes pointing at it easy.
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


def pointing(rate_maps: Sequence[np.ndarray], masks: Sequence[np.ndarray]) -> dict[str, float | int]:
    """`share` and `chance` (the module docstring) over the frames whose mask is not empty, and their count."""
    if len(rate_maps) != len(masks):
        raise ValueError(f"{len(rate_maps)} rate maps against {len(masks)} masks.")
    hits, chance, frames = 0, 0.0, 0
    for rate_map, mask in zip(rate_maps, masks, strict=True):
        under = cells_under(mask, np.shape(rate_map))
        if not under.any():
            continue
        frames += 1
        hits += bool(under[hottest_cell(rate_map)])
        chance += float(under.mean())
    if not frames:
        return {"frames": 0, "share": float("nan"), "chance": float("nan")}
    return {"frames": frames, "share": hits / frames, "chance": chance / frames}
