"""benchmarks/paired_rows.py: two rows on the same episodes, compared twin by twin."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

_spec = importlib.util.spec_from_file_location(
    "paired_rows", Path(__file__).parents[1] / "benchmarks" / "paired_rows.py"
)
paired_rows = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(paired_rows)
paired, sign_test = paired_rows.paired, paired_rows.sign_test


def test_the_sign_test_is_exact_and_symmetric():
    assert sign_test(0, 0) == 1.0
    assert sign_test(5, 0) == pytest.approx(2 / 32)  # all five discordant twins one way
    assert sign_test(3, 12) == sign_test(12, 3) == pytest.approx(2 * sum((1, 15, 105, 455)) / 2**15)


def test_only_the_discordant_twins_count_and_other_seeds_are_refused():
    a = {"seeds": [1, 2, 3, 4], "success": [True, True, False, True]}
    b = {"seeds": [1, 2, 3, 4], "success": [True, False, False, False]}
    assert paired(a, b) == {"episodes": 4, "a": 3, "b": 1, "only_a": 2, "only_b": 0, "p": 0.5}
    with pytest.raises(ValueError, match="other seeds"):
        paired(a, {**b, "seeds": [5, 6, 7, 8]})
