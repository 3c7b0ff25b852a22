"""The benchmark's metrics against values computed by hand (metrics.py)."""

import numpy as np
import pytest

from lerobot_vib.metrics import (
    auroc,
    first_crossing,
    roc_curve,
    std_band,
    stop_metrics,
    time_indexed_band,
    wilson_interval,
)


def test_auroc_counts_ordered_pairs_and_half_ties():
    assert auroc([1, 2, 3], [2.5, 4]) == pytest.approx(5 / 6)  # 2.5 beats 1 and 2, 4 beats all three
    assert auroc([1, 2], [2, 3]) == pytest.approx(3.5 / 4)  # the tie 2 vs 2 counts one half
    assert auroc([0, 0], [0, 0]) == 0.5
    assert auroc([5, 6], [1, 2]) == 0.0


def test_auroc_refuses_empty_or_non_finite_groups():
    with pytest.raises(ValueError, match="negatives and positives"):
        auroc([], [1.0])
    with pytest.raises(ValueError, match="NaN"):
        auroc([1.0, float("nan")], [2.0])


def test_roc_curve_runs_from_origin_to_one_and_its_area_is_the_auroc():
    neg, pos = [0.1, 0.4, 0.35, 0.8], [0.9, 0.4, 0.6]
    fpr, tpr = roc_curve(neg, pos)
    assert (fpr[0], tpr[0], fpr[-1], tpr[-1]) == (0, 0, 1, 1)
    assert np.trapezoid(tpr, fpr) == pytest.approx(auroc(neg, pos))


def test_wilson_interval_matches_the_closed_form():
    assert wilson_interval(0, 10) == pytest.approx((0.0, 1.959964**2 / (10 + 1.959964**2)))
    low, high = wilson_interval(5, 10)
    assert (low, high) == pytest.approx((0.2366, 0.7634), abs=1e-4)
    assert wilson_interval(0, 0) == (0.0, 1.0)
    with pytest.raises(ValueError):
        wilson_interval(11, 10)


def test_every_success_gives_an_interval_that_holds_the_rate_itself():
    # 50 of 50 rounded the upper bound to 0.9999999999999999, and the success plot's error bar went negative
    for n in range(1, 201):
        assert wilson_interval(n, n)[1] == 1.0 and wilson_interval(0, n)[0] == 0.0


def test_first_crossing_with_a_constant_and_with_a_band_shorter_than_the_episode():
    assert first_crossing([1, 1, 3, 1], 2.0) == 2
    assert first_crossing([1, 1, 1], 2.0) is None
    assert first_crossing([1, float("nan")], 2.0) == 1  # unknown means stop
    assert first_crossing([5, 5, 1.5, 2.5], [9, 9, 2]) == 3  # steps past the band use its last value


def test_time_indexed_band_is_the_conformal_level_times_the_clean_shape():
    shape = [[1, 2, 1], [1, 2, 1]]
    level = [[1, 2, 1], [3, 2, 1]]  # max u / b: 1 and 3; alpha 0.5 with 2 scores takes the 2nd smallest
    np.testing.assert_allclose(time_indexed_band(shape, level, alpha=0.5), [3, 6, 3])
    # the shape continues with its last value where no shape episode reached
    np.testing.assert_allclose(time_indexed_band([[1, 2]], [[1, 2, 4]], alpha=0.5), [2, 4, 4])


def test_std_band_is_the_clean_mean_plus_the_conformal_level_of_clean_standard_deviations():
    shape = [[1, 2, 1], [3, 4, 1]]  # mu = 2, 3, 1; s = sqrt(2), sqrt(2), 0 (floored)
    level = [[2, 3, 1], [2, 3 + 2 * np.sqrt(2), 1]]  # max z: 0 and 2; alpha 0.5 with 2 scores takes the 2nd
    band = std_band(shape, level, alpha=0.5)
    np.testing.assert_allclose(band[:2], [2 + 2 * np.sqrt(2), 3 + 2 * np.sqrt(2)])
    assert 1 < band[2] < 1.01  # where every clean episode agrees, a small difference is already above the band
    # steps fewer than two shape episodes reached keep the last mean and deviation
    np.testing.assert_allclose(std_band([[1, 2], [3, 4, 9]], [[2, 3]], alpha=0.5)[1:], [3, 3])
    with pytest.raises(ValueError, match="two shape episodes"):
        std_band([[1, 2]], level, alpha=0.5)


def test_a_scene_wrong_from_the_start_crosses_the_std_band_at_once_and_the_proportional_band_only_late():
    # clean u: about 1 at every step, and in every third episode a spike of 10 at step 20 (a grasp seen closer):
    # the proportional band's one level q must cover the spike's ratio to the mean, so it is wide at every step;
    # a scene wrong from the start (a black camera) doubles u throughout
    rng = np.random.default_rng(0)
    clean = [1 + 0.05 * rng.random(40) + np.where(np.arange(40) == 20, 10.0 * (i % 3 == 0), 0) for i in range(20)]
    wrong = np.full(40, 2.0)
    assert first_crossing(wrong, std_band(clean[:10], clean[10:], 0.1)) == 0
    assert first_crossing(wrong, time_indexed_band(clean[:10], clean[10:], 0.1)) is None


def test_detection_delay_and_early_stops_on_scripted_traces():
    occluded = [1.0] * 10 + [5.0] * 5  # the occluder enters at 8, u crosses 3 at 10: delay 2
    early = [1, 4, 1, 1, 1, 1, 1, 1, 1]  # crosses at 1, before the occluder at 6: a false stop
    missed = [1.0] * 12
    ended = [1.0] * 4  # the episode ended before the occluder entered at 6: left out
    m = stop_metrics([occluded, early, missed, ended], 3.0, onsets=[8, 6, 6, 6])
    assert (m.n_episodes, m.stopped, m.early, m.delays) == (3, 1, 1, [2])
    assert m.rate == pytest.approx(1 / 3) and m.mean_delay == 2
    clean = stop_metrics([[1, 1], [1, 4]], 3.0)
    assert (clean.n_episodes, clean.stopped, clean.early) == (2, 1, 0)
