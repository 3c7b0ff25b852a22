"""benchmarks/paired_cells.py: a perturbed episode compared with its clean twin on the same seed."""

import importlib.util
from pathlib import Path

import pytest

_spec = importlib.util.spec_from_file_location(
    "paired_cells", Path(__file__).parents[1] / "benchmarks" / "paired_cells.py"
)
paired_cells = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(paired_cells)


def _cell(condition, success, max_reward, u, seeds=(1, 2)):
    return {
        "variant": "vib",
        "condition": condition,
        "seeds": list(seeds),
        "success": success,
        "max_reward": max_reward,
        "u": u,
    }


def test_twins_that_end_differently_are_counted_and_u_shift_is_relative():
    clean = _cell("normal", [True, False], [4.0, 1.0], [[1.0, 2.0], [1.0, 4.0, 1.0]])
    noisy = _cell("gaussian", [False, False], [2.0, 1.0], [[1.0, 2.2, 1.0], [1.0, 4.0, 1.5]])
    r = paired_cells.compare(clean, noisy)
    assert (r["pairs"], r["success_differs"], r["max_reward_differs"]) == (2, 1, 1)
    assert r["max_u_change_pct"] == (0.0, 10.0)
    # the success ended after 2 steps, its twin ran on: only the steps both ran are compared
    assert r["frame_u_abs_diff_max"] == pytest.approx(0.5)


def test_rows_without_a_score_compare_outcomes_only():
    r = paired_cells.compare(_cell("normal", [True], [4.0], None, (1,)), _cell("color", [True], [4.0], None, (1,)))
    assert r == {"pairs": 1, "success_differs": 0, "max_reward_differs": 0}


def test_cells_on_other_seeds_are_refused():
    with pytest.raises(ValueError, match="seeds differ"):
        paired_cells.compare(_cell("normal", [True], [4.0], None, (1,)), _cell("color", [True], [4.0], None, (2,)))
