"""benchmarks/map_reductions.py: the rate map's z-scores reduced over k cells and w steps, judged by the rule that
chose the default score."""

import importlib.util
import sys
from pathlib import Path

import numpy as np
import torch

BENCHMARKS = Path(__file__).parents[1] / "benchmarks"
sys.path.insert(0, str(BENCHMARKS))  # the script imports its neighbours (rate_map_pointing, report)
_spec = importlib.util.spec_from_file_location("map_reductions", BENCHMARKS / "map_reductions.py")
map_reductions = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(map_reductions)
sys.path.remove(str(BENCHMARKS))


def test_one_cell_reductions_are_the_policys_own_map_scores_and_a_window_is_a_trailing_mean():
    from lerobot_vib.scores import map_score

    z = np.random.default_rng(0).normal(size=(7, 48))
    got = map_reductions.reductions(z)
    zero, one = torch.zeros(48), torch.ones(48)
    policy_high = map_score(torch.from_numpy(z), zero, one, top_k=2).numpy()
    policy_low = map_score(-torch.from_numpy(z), -zero, one, top_k=2).numpy()
    np.testing.assert_allclose(got["map_score k=2"], policy_high, rtol=1e-6)
    np.testing.assert_allclose(got["low_map_score k=2"], policy_low, rtol=1e-6)
    np.testing.assert_allclose(got["map_score k=1"], z.max(axis=1))
    np.testing.assert_allclose(got["map_score all"], z.mean(axis=1))
    three = got["map_score k=1, w=3"]
    assert three[0] == z[0].max() and np.isclose(three[4], z[2:5].max(axis=1).mean())


def test_a_board_over_many_cells_is_caught_by_a_many_cell_mean_where_a_one_cell_clean_peak_hides_it():
    from lerobot_vib.scripts.benchmark_report import choose_score_on_validation, score_stops
    from lerobot_vib.sim.perturbations import CONDITIONS, draw_scene_episode

    rng = np.random.default_rng(1)

    def clean(seed: int) -> np.ndarray:  # one cell spikes once (a grasp), higher than the board lifts any cell
        z = rng.normal(0, 0.3, size=(100, 48))
        z[rng.integers(20, 80), rng.integers(48)] += 6.0
        return z

    def occluded(seed: int) -> np.ndarray:
        z = rng.normal(0, 0.3, size=(100, 48))
        window = draw_scene_episode(CONDITIONS["occlusion"], seed).occluded_steps
        for t in window:
            if t < 100:
                z[t, :12] += 3.0
        return z

    validation = map_reductions.cell({s: (clean(s), True) for s in range(400000, 400040)})
    board = map_reductions.cell({s: (occluded(s), True) for s in range(400000, 400020)})
    stops = score_stops({"normal": validation, "occlusion": board}, validation, alpha=0.1)
    entered = stops["map_score k=8"]["conformal"]["occlusion_episodes"]
    assert entered > 0 and stops["map_score k=8"]["conformal"]["in_time"] == entered
    assert stops["map_score k=1"]["conformal"]["in_time"] == 0
    choice = choose_score_on_validation(validation, board, alpha=0.1)
    assert choice["score"] != "map_score k=1" and choice["row"]["in_time"] == entered
