"""One seed plan: no test seed calibrates or chooses anything, in any benchmark."""

from __future__ import annotations

import pytest

from lerobot_vib.scripts.benchmark import BenchmarkConfig
from lerobot_vib.seeds import PLAN, SPAN, TEST, VALIDATION, seed_range


def test_no_two_splits_of_the_plan_share_a_seed():
    ranges = [set(seed_range(split, SPAN)) for split in PLAN]
    assert all(not (a & b) for i, a in enumerate(ranges) for b in ranges[i + 1 :])


def test_the_benchmark_chooses_on_the_plans_validation_seeds_and_reports_on_its_test_seeds():
    field = BenchmarkConfig.__dataclass_fields__
    assert field["validation_seed"].default == VALIDATION
    assert field["test_seed"].default == TEST


def test_the_score_and_eq6_benchmarks_calibrate_and_choose_off_the_test_seeds():
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parents[1] / "benchmarks"))
    import eq6_sweep
    import uncertainty_scores

    for module in (uncertainty_scores, eq6_sweep):
        chosen_on = {s for split, first in module.DEFAULT_SPLIT_SEEDS.items() if split != "test"
                     for s in range(first, first + 1000)}  # fmt: skip
        assert module.DEFAULT_SPLIT_SEEDS["test"] == TEST
        assert not chosen_on & set(range(TEST, TEST + 1000))


@pytest.mark.parametrize("split, n, message", [("tests", 3, "Unknown seed split"), ("test", SPAN + 1, "do not fit")])
def test_a_bad_split_or_count_is_refused_by_name(split, n, message):
    with pytest.raises(ValueError, match=message):
        seed_range(split, n)
