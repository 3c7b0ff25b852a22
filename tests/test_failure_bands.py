"""benchmarks/failure_bands.py: the shipped failure monitor with and without FAIL-Detect's band offered, on a
committed benchmark folder."""

import importlib.util
import json
from pathlib import Path

import numpy as np

_spec = importlib.util.spec_from_file_location(
    "failure_bands", Path(__file__).parents[1] / "benchmarks" / "failure_bands.py"
)
failure_bands = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(failure_bands)

VARIANT = "vib_tokens_narrow"


def _cell(condition: str, outcomes: list[bool], seed0: int, rng: np.random.Generator) -> dict:
    # successes: u about 1 with a spike at a random step (a grasp); failures: a scene wrong from the first frame
    traces = []
    for ok in outcomes:
        u = 1 + 0.05 * rng.random(30)
        if ok:
            u[rng.integers(10, 20)] += rng.uniform(0, 3)
        else:
            u += 1.0
        traces.append(np.round(u, 4).tolist())
    return {
        "variant": VARIANT,
        "condition": condition,
        "seeds": list(range(seed0, seed0 + len(outcomes))),
        "success": outcomes,
        "scores": {"rate": traces, "state_rate": [[1.0] * 30 for _ in outcomes]},
        "grasp_missed_at": [None if ok else 20 for ok in outcomes],
    }


def _folder(root: Path) -> Path:
    rng = np.random.default_rng(0)
    validation = root / "validation" / VARIANT / "seed_1000"
    validation.mkdir(parents=True)
    (validation / "act_0.3.json").write_text(json.dumps(_cell("validation", [True] * 30 + [False] * 10, 400000, rng)))
    for condition, outcomes in {"normal": [True] * 15 + [False] * 5, "black": [False] * 5}.items():
        cell = root / "cells" / condition / VARIANT
        cell.mkdir(parents=True)
        (cell / "seed_1000.json").write_text(json.dumps(_cell(condition, outcomes, 600000, rng)))
    (root / "choices.json").write_text(json.dumps({VARIANT: {"1000": {"runtime": "act:0.3"}}}))
    return root


def test_the_folder_is_read_as_the_benchmark_keys_its_cells(tmp_path):
    cells, seeds = failure_bands.load_cells(_folder(tmp_path), VARIANT)
    assert seeds == [1000]
    assert set(cells) == {
        (VARIANT, "validation", 1000, "act:0.3"),
        (VARIANT, "normal", 1000, None),
        (VARIANT, "black", 1000, None),
    }


def test_both_candidate_sets_ship_on_the_same_rollouts_and_only_the_second_may_offer_the_std_band(tmp_path):
    before, both = failure_bands.compare([_folder(tmp_path)], VARIANT, alpha=0.1)
    assert "std_band" not in before["shipped"] and before["candidates"] < both["candidates"]
    assert before["validation_episodes"] == both["validation_episodes"] == {"1000": 40}
    # a superset of candidates: the earliest monitor meeting the targets on validation can only come earlier
    assert both["validation"]["detection_time"] <= before["validation"]["detection_time"]
    # the scene wrong from the first frame is above the tight band at once, and every failure is caught
    assert both["test"]["tpr"] == 1.0 and both["per_condition"]["black"]["detection_time"] == 0.0
    report = failure_bands.markdown({(str(tmp_path), VARIANT): [before, both]}, 0.1, "cmd", "cpu", 1.0)
    assert "| and FAIL-Detect's band |" in report and "1000: 40" in report


def test_ors_of_three_with_a_margin_are_offered_beside_the_ors_of_two_and_never_ship_a_later_alarm(tmp_path):
    """benchmarks/failure_ors.py: the second candidate set holds the first."""
    import sys

    sys.path.insert(0, str(Path(__file__).parents[1] / "benchmarks"))
    spec = importlib.util.spec_from_file_location(
        "failure_ors", Path(__file__).parents[1] / "benchmarks" / "failure_ors.py"
    )
    failure_ors = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(failure_ors)
    before, after = failure_bands.compare([_folder(tmp_path)], VARIANT, 0.1, failure_ors.OFFERED)
    assert before["candidates"] < after["candidates"]
    assert after["validation"]["detection_time"] <= before["validation"]["detection_time"]
    assert " x [" not in before["shipped"]  # no margin among the ORs offered before
