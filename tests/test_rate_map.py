"""Where the rate map points: the cells under a mask, the hottest cell, and the occluder's mask in the arm env."""

from __future__ import annotations

import numpy as np
import pytest

from lerobot_vib.rate_map import cells_under, hottest_cell, pointing
from lerobot_vib.sim.arm_env import ArmGraspEnv
from lerobot_vib.sim.perturbations import PerturbationConfig


def test_a_cell_is_under_the_mask_when_half_its_block_is_covered_and_not_when_less():
    mask = np.zeros((8, 8), dtype=bool)
    mask[:4, :2] = True  # cell (0, 0) of a 2x2 map, a 4x4 block: exactly half covered
    mask[4:, 4:5] = True  # cell (1, 1): a quarter
    assert cells_under(mask, (2, 2)).tolist() == [[True, False], [False, False]]


def test_a_map_hottest_under_the_board_points_at_it_and_one_hottest_elsewhere_does_not():
    mask = np.zeros((96, 128), dtype=bool)
    mask[48:, :64] = True  # the lower left quarter of a 12x16 map: rows 6-11, columns 0-7
    towards, away = np.zeros((12, 16)), np.zeros((12, 16))
    towards[9, 3], away[2, 12] = 5.0, 5.0
    result = pointing([towards, away], [mask, mask])
    assert (result["frames"], result["share"], result["chance"]) == (2, 0.5, 0.25)
    assert hottest_cell(towards) == (9, 3)


def test_a_board_that_lowers_its_cells_is_found_by_the_coldest_cell_and_a_negative_contrast():
    mask = np.zeros((96, 128), dtype=bool)
    mask[48:, :64] = True
    darker = np.ones((12, 16))
    darker[6:, :8] = -1.0  # every cell under the board 2 below the rest
    darker[0, 15] = 3.0  # the hottest cell far from it
    hot, cold = pointing([darker], [mask]), pointing([darker], [mask], end="coldest")
    assert hot["share"] == 0.0 and cold["share"] == 1.0
    assert cold["contrast"] == pytest.approx(-1.0 - (1.0 * 143 + 3.0) / 144)


def test_frames_without_the_board_are_not_counted():
    empty = np.zeros((96, 128), dtype=bool)
    assert pointing([np.ones((12, 16))], [empty])["frames"] == 0


@pytest.mark.parametrize(
    "maps, masks, message",
    [
        ([np.zeros((12, 16))], [], "1 rate maps against 0 masks"),
        ([np.zeros((12, 16))], [np.zeros((96, 128, 3), dtype=bool)], "must be \\(H, W\\)"),
        ([np.zeros((12, 16))], [np.zeros((8, 8), dtype=bool)], "cannot tile"),
        ([np.full((12, 16), np.nan)], [np.ones((96, 128), dtype=bool)], "finite"),
    ],
)
def test_bad_maps_and_masks_are_refused_by_name(maps, masks, message):
    with pytest.raises(ValueError, match=message):
        pointing(maps, masks)
    with pytest.raises(ValueError, match="end must be one of"):
        pointing(maps, masks, end="warmest")


def test_the_occluder_mask_covers_the_board_while_it_is_in_view_and_nothing_once_it_left():
    board = PerturbationConfig(occlusion=True, occlusion_start=0, occlusion_duration=2)
    env = ArmGraspEnv(observation_height=48, observation_width=64, perturbation=board)
    clean = ArmGraspEnv(observation_height=48, observation_width=64)
    obs, _ = env.reset(seed=3)
    reference, _ = clean.reset(seed=3)
    mask = env.occluder_mask()
    assert mask.shape == (48, 64) and 0.1 < mask.mean() < 0.9
    changed = (obs["pixels"]["scene"].astype(int) - reference["pixels"]["scene"]).any(axis=-1)
    assert changed[mask].mean() > 0.95  # where the mask says board, the image shows something else
    assert changed[~mask].mean() < 0.2  # elsewhere it is the same scene (shadows aside)
    hold = np.array([*obs["agent_pos"][:6], 1.0], dtype=np.float32)
    for _ in range(2):
        env.step(hold)
    assert not env.occluder_mask().any()
    env.close()
    clean.close()
