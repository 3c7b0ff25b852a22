"""Failure prediction per episode (failure.py): monitors, their conformal calibration, the metrics, the choice,
and the failure moment the simulated arm reports."""

from __future__ import annotations

import numpy as np
import pytest

from lerobot_vib.failure import (
    AnyOf,
    CalibrationError,
    Episode,
    Monitor,
    calibrate_monitor,
    candidate_monitors,
    choose_monitor,
    evaluate,
    monitor_from_dict,
    or_candidates,
    windowed,
)

RNG = np.random.default_rng(0)


def episode(success: bool, condition: str = "normal", length: int = 50, level: float = 1.0, **extra) -> Episode:
    base = {"a": level + 0.1 * RNG.random(length), "b": 1.0 + 0.1 * RNG.random(length)}
    return Episode(success, {**base, **extra}, condition)


def successes(n: int, **kw) -> list[Episode]:
    return [episode(True, **kw) for _ in range(n)]


def test_a_score_fitted_on_a_rollout_neither_sets_nor_judges_its_thresholds():
    clean = successes(20)
    # in-sample: the score reads its own fitting rollouts far lower than new ones
    fitted = [Episode(True, {"a": np.full(50, 0.01), "b": np.ones(50)}, fitted_on=frozenset({"a"})) for _ in range(20)]
    monitor = Monitor(("a",))
    alone, mixed = calibrate_monitor(monitor, clean, 0.1), calibrate_monitor(monitor, clean + fitted, 0.1)
    assert mixed.thresholds == alone.thresholds and mixed.n_calibration == 20
    # a score that was not fitted on them still reads them
    assert calibrate_monitor(Monitor(("b",)), clean + fitted, 0.1).n_calibration == 40
    with pytest.raises(CalibrationError, match="successful clean rollouts"):
        calibrate_monitor(monitor, fitted + successes(3), 0.1)
    # the choice judges a monitor on the rollouts its scores did not see: a fitted failure counts for nothing
    blind = Episode(False, {"a": np.full(50, 9.0), "b": np.ones(50)}, fitted_on=frozenset({"a"}))
    quiet = Episode(False, {"a": np.ones(50), "b": np.ones(50)})
    _, ranking = choose_monitor([monitor], {0: clean + [blind, quiet]}, 0.1)
    assert ranking[0]["tpr"] == 0.0  # judged on `quiet` alone; `blind` would have made it 0.5


def test_a_window_mean_and_sum_match_the_definition_including_the_first_steps():
    u = np.array([1.0, 3.0, 5.0, 7.0])
    np.testing.assert_allclose(windowed(u, 2, "mean"), [1.0, 2.0, 4.0, 6.0])
    np.testing.assert_allclose(windowed(u, 3, "sum"), [1.0, 4.0, 9.0, 15.0])
    np.testing.assert_allclose(windowed(u, 1), u)
    assert np.isnan(windowed([1.0, np.nan, 1.0], 2)[1:]).all()  # unknown stays unknown in the window


def test_a_monitor_that_fires_on_every_step_has_tpr_1_and_tnr_0():
    calibrated = calibrate_monitor(Monitor(("a",)), successes(20), 0.1)
    calibrated.thresholds["a"] = -1.0  # below every u: an alarm at the first step of every episode
    metrics = evaluate(calibrated, [episode(False), episode(False), episode(True), episode(True, "gaussian")])
    assert (metrics.tpr, metrics.tnr, metrics.accuracy, metrics.balanced_accuracy) == (1.0, 0.0, 0.5, 0.5)
    assert metrics.detection_times == [0.0, 0.0]


def test_a_monitor_that_never_fires_has_tpr_0_tnr_1_and_no_detection_time():
    calibrated = calibrate_monitor(Monitor(("a",)), successes(20), 0.1)
    calibrated.thresholds["a"] = np.inf
    metrics = evaluate(calibrated, [episode(False), episode(True)])
    assert (metrics.tpr, metrics.tnr, metrics.detection_time, metrics.median_lead_time) == (0.0, 1.0, None, None)


@pytest.mark.parametrize("threshold", ["constant", "band", "std_band"])
def test_thresholds_are_set_only_on_successful_clean_rollouts(threshold):
    clean = successes(30)
    monitor = Monitor(("a",), window=5, threshold=threshold)
    alone = calibrate_monitor(monitor, clean, 0.1)
    others = [episode(False, level=50.0), episode(True, "occlusion", level=50.0), episode(False, "color", level=9.0)]
    mixed = calibrate_monitor(monitor, [*others[:2], *clean, others[2]], 0.1)
    np.testing.assert_array_equal(np.asarray(alone.thresholds["a"]), np.asarray(mixed.thresholds["a"]))
    assert mixed.n_calibration == 30
    with pytest.raises(CalibrationError, match="successful clean rollouts"):
        calibrate_monitor(monitor, [*others, *successes(3)], 0.1)


@pytest.mark.parametrize("threshold", ["constant", "band", "std_band"])
def test_a_successful_clean_episode_alarms_at_most_alpha_of_the_time(threshold):
    # Exchangeable successes: over many draws of calibration and new episodes, the false-alarm rate <= alpha.
    alpha, alarms, trials = 0.2, 0, 300
    rng = np.random.default_rng(1)
    for _ in range(trials):
        calib = [Episode(True, {"a": 1 + rng.gamma(2.0, 0.1, 40)}) for _ in range(20)]
        calibrated = calibrate_monitor(Monitor(("a",), 3, "mean", threshold), calib, alpha)
        alarms += calibrated.alarm(Episode(True, {"a": 1 + rng.gamma(2.0, 0.1, 40)})) is not None
    assert alarms / trials <= alpha + 0.05


def test_an_and_monitor_fires_only_where_both_scores_are_above_their_thresholds():
    calib = successes(20)
    calibrated = calibrate_monitor(Monitor(("a", "b")), calib, 0.1)
    only_a = Episode(False, {"a": np.full(50, 9.0), "b": np.ones(50)})
    both = Episode(False, {"a": np.r_[np.ones(30), np.full(20, 9.0)], "b": np.r_[np.ones(40), np.full(10, 9.0)]})
    assert calibrated.alarm(only_a) is None
    assert calibrated.alarm(both) == 40


def test_an_or_monitor_fires_at_the_first_step_any_member_does_each_with_its_own_window():
    calib = successes(20)
    monitor = AnyOf((Monitor(("a",)), Monitor(("b",), window=5)))
    calibrated = calibrate_monitor(monitor, calib, 0.1)
    only_a = Episode(False, {"a": np.r_[np.ones(30), np.full(20, 9.0)], "b": np.ones(50)})
    only_b = Episode(False, {"a": np.ones(50), "b": np.r_[np.ones(10), np.full(40, 9.0)]})
    neither = Episode(False, {"a": np.ones(50), "b": np.ones(50)})
    assert calibrated.alarm(only_a) == 30
    assert calibrated.alarm(only_b) == 10  # b's 5-step mean crosses its threshold at once: 9 among ones
    assert calibrated.alarm(neither) is None
    b_alone = calibrate_monitor(Monitor(("b",), window=5), calib, 0.05)
    assert calibrated.members[1].thresholds == b_alone.thresholds  # each member at alpha / k
    assert monitor_from_dict(monitor.as_dict()) == monitor and monitor_from_dict(Monitor(("a",)).as_dict()).scores == (
        "a",
    )


def test_an_or_of_k_members_each_at_alpha_over_k_alarms_a_successful_clean_episode_at_most_alpha_of_the_time():
    alpha, alarms, trials = 0.2, 0, 300
    rng = np.random.default_rng(2)
    monitor = AnyOf((Monitor(("a",), 3), Monitor(("b",))))

    def draw() -> Episode:
        return Episode(True, {"a": 1 + rng.gamma(2.0, 0.1, 40), "b": 1 + rng.gamma(2.0, 0.1, 40)})

    for _ in range(trials):
        calibrated = calibrate_monitor(monitor, [draw() for _ in range(20)], alpha)
        alarms += calibrated.alarm(draw()) is not None
    assert alarms / trials <= alpha + 0.05


def test_or_candidates_put_a_band_only_on_the_first_score_and_list_an_or_of_two_constants_once():
    ors = or_candidates(["a", "b"], windows=(1, 5))
    assert all(m.members[1].threshold == "constant" for m in ors)
    constants = [frozenset(m.members) for m in ors if m.threshold == "constant"]
    assert len(constants) == len(set(constants)) == 4  # {a@1, a@5} x {b@1, b@5}
    assert sum(m.threshold == "band" for m in ors) == 8  # a or b first with a band, 2 x 2 windows each
    with pytest.raises(ValueError, match="distinct scores"):
        AnyOf((Monitor(("a",)), Monitor(("a",), 5)))


def test_an_or_margin_multiplies_only_the_partners_thresholds_and_never_alarms_a_clean_episode_more_often():
    calib = successes(20)
    plain = calibrate_monitor(AnyOf((Monitor(("a",)), Monitor(("b",)))), calib, 0.1)
    wide = calibrate_monitor(AnyOf((Monitor(("a",)), Monitor(("b",))), margin=4.0), calib, 0.1)
    assert wide.members[0].thresholds == plain.members[0].thresholds
    assert wide.members[1].thresholds["b"] == pytest.approx(4.0 * plain.members[1].thresholds["b"])
    rng = np.random.default_rng(5)
    clean = [Episode(True, {"a": 1 + rng.gamma(2.0, 0.2, 40), "b": 1 + rng.gamma(2.0, 0.2, 40)}) for _ in range(200)]
    assert sum(wide.alarm(e) is not None for e in clean) <= sum(plain.alarm(e) is not None for e in clean)
    # a partner far outside the clean rollouts still fires at once; one just outside them no longer does
    black = Episode(False, {"a": np.ones(40), "b": np.full(40, 50.0)})
    noisy = Episode(True, {"a": np.ones(40), "b": np.full(40, 1.5 * plain.members[1].thresholds["b"])})
    assert wide.alarm(black) == plain.alarm(black) == 0
    assert plain.alarm(noisy) == 0 and wide.alarm(noisy) is None
    either = AnyOf((Monitor(("a",)), Monitor(("b",))), margin=2.0)
    assert monitor_from_dict(either.as_dict()) == either and "2 x" in either.name
    with pytest.raises(ValueError, match="margin must be >= 1"):
        AnyOf((Monitor(("a",)), Monitor(("b",))), margin=0.5)


def test_or_candidates_of_three_share_one_partner_window_and_list_each_margin():
    ors = or_candidates(["a", "b", "c"], windows=(1, 5), thresholds=("constant",), sizes=(3,), margins=(1.0, 2.0))
    assert all(len(m.members) == 3 and m.members[1].window == m.members[2].window for m in ors)
    plain = {frozenset(m.members) for m in ors if m.margin == 1}
    # margin 1, constants: the members are interchangeable, so each set of windows is listed once: all three at
    # one window (2), or one member alone at the other window (3 members x 2 windows)
    assert len(plain) == sum(m.margin == 1 for m in ors) == 8
    assert sum(m.margin == 2 for m in ors) == 12  # with a margin the first member differs: 3 firsts x 2 x 2
    assert or_candidates(["a", "b"], windows=(1, 5)) == or_candidates(["a", "b"], windows=(1, 5), sizes=(2,))


def test_the_shipped_monitor_is_the_earliest_meeting_every_target_on_validation_else_the_best_balanced_one():
    from lerobot_vib.scripts.failure_report import BEST_BALANCED, EARLIEST, ship_rule

    def row(name: str, tpr: float, tnr: float, detection: float, benign: float | None) -> dict:
        return {"monitor": Monitor((name,)), "tpr": tpr, "tnr": tnr, "detection_time": detection,
                "balanced_accuracy": (tpr + tnr) / 2, "order": 0, "benign_stopped": benign}  # fmt: skip

    late = row("late", 0.98, 0.96, 0.80, 0.0)
    early_but_stops_noise = row("noisy", 0.95, 0.92, 0.10, 0.25)
    early = row("early", 0.91, 0.93, 0.22, 0.05)
    assert ship_rule([late, early_but_stops_noise, early]) == (Monitor(("early",)), EARLIEST)
    assert ship_rule([late, early_but_stops_noise]) == (Monitor(("late",)), EARLIEST)
    assert ship_rule([row("weak", 0.8, 0.8, 0.1, 0.0)]) == (Monitor(("weak",)), BEST_BALANCED)


def test_lead_time_is_positive_when_the_alarm_comes_before_the_missed_grasp():
    calibrated = calibrate_monitor(Monitor(("a",)), successes(20), 0.1)
    early = Episode(False, {"a": np.r_[np.ones(10), np.full(40, 9.0)], "b": np.ones(50)}, failure_moment=25)
    late = Episode(False, {"a": np.r_[np.ones(30), np.full(20, 9.0)], "b": np.ones(50)}, failure_moment=25)
    metrics = evaluate(calibrated, [early, late])
    assert metrics.lead_times == [15, -5]
    assert metrics.detection_times == [10 / 50, 30 / 50]


def test_the_choice_prefers_the_score_that_rises_in_failures_and_reads_validation_only():
    def val(seed_offset: int) -> list[Episode]:
        eps = successes(24)
        eps += [Episode(False, {"a": 1.0 + 0.1 * RNG.random(50), "b": np.r_[np.ones(20), np.full(30, 3.0)]})
                for _ in range(8)]  # fmt: skip
        return eps

    candidates = candidate_monitors(["a", "b"], windows=(1, 5), pairs=True)
    assert Monitor(("a", "b"), 5, "sum", "band") in candidates and Monitor(("a",), 1, "sum") not in candidates
    chosen, ranking = choose_monitor(candidates, {1000: val(0), 2000: val(1)}, 0.1)
    assert chosen.scores == ("b",)
    assert ranking[0]["balanced_accuracy"] >= ranking[-1]["balanced_accuracy"]
    assert ranking[0]["tpr"] == 1.0


def test_a_seed_that_solves_every_validation_episode_still_calibrates_but_does_not_hide_the_others_failures():
    failing = successes(24) + [Episode(False, {"a": np.ones(50), "b": np.full(50, 3.0)}) for _ in range(8)]
    flawless = successes(24)
    candidates = candidate_monitors(["a", "b"], windows=(1,))
    chosen, ranking = choose_monitor(candidates, {1000: failing, 3000: flawless}, 0.1)
    assert chosen.scores == ("b",) and ranking[0]["tpr"] == 1.0
    # the flawless seed's false alarms still count against a monitor
    noisy = successes(12) + successes(12, b=np.full(50, 3.0))
    _, ranking = choose_monitor([Monitor(("b",))], {1000: failing, 3000: noisy}, 0.1)
    assert ranking[0]["tnr"] < 1.0
    # with no failure anywhere there is nothing to choose by
    assert choose_monitor(candidates, {3000: flawless}, 0.1) == (None, [])


def test_a_monitor_refuses_a_window_below_one_step_and_unknown_kinds():
    with pytest.raises(ValueError, match="window"):
        Monitor(("a",), window=0)
    with pytest.raises(ValueError, match="threshold"):
        Monitor(("a",), threshold="quantile")
    with pytest.raises(ValueError, match="distinct"):
        Monitor(("a", "a"))
    assert Monitor.from_dict(Monitor(("a", "b"), 5, "sum", "band").as_dict()) == Monitor(("a", "b"), 5, "sum", "band")


def test_a_failure_moment_is_found_in_a_scripted_missed_grasp_and_never_in_a_scripted_grasp():
    from lerobot_vib.sim.arm_env import EPISODE_LENGTH, ArmGraspEnv, block_pose
    from lerobot_vib.sim.arm_scripted import plan_grasp

    env = ArmGraspEnv(observation_height=24, observation_width=32, workspace="near", shadows=False)
    try:
        seen = {}
        for offset in (0.0, 0.05):  # the plan aimed at the block, and 5 cm beside it
            env.reset(seed=3)
            xy, yaw = block_pose(3, "near")
            target = np.array([xy[0], xy[1] + offset, env.block_half])
            missed, success = [], False
            for t, action in enumerate(plan_grasp(env.model, target, yaw, EPISODE_LENGTH, env.block_half).actions):
                _, _, success, _, info = env.step(action)
                if info["grasp_missed"]:
                    missed.append(t)
                if success:
                    break
            seen[offset] = (success, missed)
    finally:
        env.close()
    assert seen[0.0] == (True, [])
    success, missed = seen[0.05]
    assert not success and missed and 50 <= missed[0] <= 60  # while the plan closes the gripper (steps 48-58)


def _scripted_cell(rng, condition: str, n: int, fail_every: int, seed0: int) -> dict:
    """A benchmark cell whose score "b" jumps to 4 after step 20 in the failed episodes, "a" is noise."""
    success = [i % fail_every != 0 for i in range(n)]
    b = [np.r_[np.ones(20), np.full(30, 1.0 if ok else 4.0)] + 0.05 * rng.random(50) for ok in success]
    return {
        "condition": condition,
        "seeds": list(range(seed0, seed0 + n)),
        "success": success,
        "scores": {"a": [(1 + 0.1 * rng.random(50)).tolist() for _ in success], "b": [x.tolist() for x in b]},
        "grasp_missed_at": [None if ok else 45 for ok in success],
    }


def _report_config(train_seeds: list[int]):
    from types import SimpleNamespace

    return SimpleNamespace(variants=["vib_tokens"], train_seeds=train_seeds, conditions=["normal", "gaussian"],
                           alpha=0.1, failure_alphas=[0.1, 0.3], rnd_steps=50)  # fmt: skip


def test_the_report_ships_the_validation_choice_and_states_its_test_numbers_in_one_line(tmp_path):
    from lerobot_vib.scripts import failure_report

    rng = np.random.default_rng(3)
    cfg = _report_config([1000])
    cells = {
        ("vib_tokens", "validation", 1000, "act:0.3"): _scripted_cell(rng, "validation", 40, 4, 400_000),
        ("vib_tokens", "normal", 1000, None): _scripted_cell(rng, "normal", 20, 3, 600_000),
        ("vib_tokens", "gaussian", 1000, None): _scripted_cell(rng, "gaussian", 20, 2, 600_000),
    }
    result = failure_report.failure_prediction(cfg, cells, lambda v, s: "act:0.3")["vib_tokens"]
    assert result["shipped"]["monitor"]["scores"] == ["b"]
    pooled = result["test"]["pooled"]
    assert pooled["n_failed"] == 7 + 10 and pooled["tpr"] == 1.0 and pooled["median_lead_time"] > 0
    lines = failure_report.markdown(cfg, {"vib_tokens": result}, {"vib_tokens": "VIB tokens"})
    assert lines[3] == failure_report.shipped_line(result) and lines[3].startswith("shipped monitor: TPR 1.00")
    assert any(line.startswith("| FIPER (Römer") for line in lines)
    assert failure_report.plot({"vib_tokens": result}, tmp_path, {}) == ["failure_roc.png"]


def test_a_seed_too_weak_to_calibrate_is_set_aside_by_name_and_the_others_still_ship_a_monitor():
    from lerobot_vib.scripts import failure_report

    rng = np.random.default_rng(4)
    cfg = _report_config([1000, 2000])
    cells = {}
    # seed 2000 solves 8 of 40 clean validation episodes: a threshold at alpha = 0.1 needs 9 successes
    for seed, fail_every in ((1000, 4), (2000, 1)):
        validation = _scripted_cell(rng, "validation", 40, fail_every, 400_000)
        if seed == 2000:
            validation["success"] = [i < 8 for i in range(40)]
        cells[("vib_tokens", "validation", seed, "act:0.3")] = validation
        cells[("vib_tokens", "normal", seed, None)] = _scripted_cell(rng, "normal", 20, 3, 600_000)
    result = failure_report.failure_prediction(cfg, cells, lambda v, s: "act:0.3")["vib_tokens"]
    assert result["uncalibrated_seeds"] == {"2000": {"successes": 8, "clean": 40, "needed": 9}}
    assert list(result["validation_episodes"]) == ["1000"] and list(result["test"]["per_seed"]) == ["1000"]
    assert result["test"]["pooled"]["n_failed"] == 7  # seed 1000's test failures alone
    lines = failure_report.markdown(cfg, {"vib_tokens": result}, {})
    assert lines[5].startswith("Training seeds 1000; set aside: training seed 2000 solved 8 of 40")

    # with no seed left, the report says which seeds and why, and ships nothing
    alone = {k: v for k, v in cells.items() if k[2] == 2000}
    none_left = failure_report.failure_prediction(_report_config([2000]), alone, lambda v, s: "act:0.3")
    assert "training seed 2000 solved 8 of 40" in none_left["vib_tokens"]["error"]
    assert "shipped" not in none_left["vib_tokens"]


def test_a_seed_with_no_failed_validation_rollout_is_still_reported_and_none_at_all_names_the_cause():
    from lerobot_vib.scripts import failure_report

    rng = np.random.default_rng(5)
    cfg = _report_config([1000, 3000])
    cells = {}
    for seed in (1000, 3000):
        validation = _scripted_cell(rng, "validation", 40, 4, 400_000)
        if seed == 3000:  # this seed solves every validation episode
            validation["success"] = [True] * 40
        cells[("vib_tokens", "validation", seed, "act:0.3")] = validation
        cells[("vib_tokens", "normal", seed, None)] = _scripted_cell(rng, "normal", 20, 3, 600_000)
    result = failure_report.failure_prediction(cfg, cells, lambda v, s: "act:0.3")["vib_tokens"]
    assert result["shipped"]["monitor"]["scores"] == ["b"]
    assert list(result["test"]["per_seed"]) == ["1000", "3000"]

    flawless = {k: v for k, v in cells.items() if k[2] == 3000}
    nothing = failure_report.failure_prediction(_report_config([3000]), flawless, lambda v, s: "act:0.3")
    assert "every validation rollout succeeded" in nothing["vib_tokens"]["error"]
    assert "shipped" not in nothing["vib_tokens"]


def test_the_earliest_monitor_is_taken_only_among_those_meeting_the_tpr_and_tnr_targets_on_validation():
    from lerobot_vib.scripts.failure_report import earliest_meeting_targets

    def row(name: str, tpr: float, tnr: float, detection: float, order: int) -> dict:
        return {"monitor": Monitor((name,)), "tpr": tpr, "tnr": tnr, "detection_time": detection,
                "balanced_accuracy": (tpr + tnr) / 2, "order": order}  # fmt: skip

    ranking = [
        row("late", 0.98, 0.96, 0.80, 0),
        row("early_but_noisy", 1.0, 0.74, 0.27, 1),
        row("mid", 0.91, 0.9, 0.5, 2),
    ]
    assert earliest_meeting_targets(ranking) == Monitor(("mid",))
    assert earliest_meeting_targets(ranking[1:2]) is None


def test_an_rnd_fitted_on_clean_rollouts_sees_half_the_successes_and_reads_a_new_scene_higher(tmp_path):
    from safetensors.numpy import save_file

    from lerobot_vib.scripts import failure_report

    rng = np.random.default_rng(5)

    def cell(name: str, condition: str, seeds: list[int], success: list[bool], shift: float) -> dict:
        embeddings = [(rng.normal(size=(30, 8)) + shift).astype(np.float32) for _ in seeds]
        save_file({f"episode_{i}": e for i, e in enumerate(embeddings)}, str(tmp_path / f"{name}.safetensors"))
        return {
            "condition": condition, "seeds": seeds, "success": success,
            "scores": {"a": [np.ones(30).tolist() for _ in seeds]},
            "embeddings_file": str(tmp_path / f"{name}.safetensors"),
        }  # fmt: skip

    key = ("vib_tokens", "validation", 1000, "act:0.3")
    cells = {
        key: cell("val", "validation", list(range(400_000, 400_012)), [True] * 10 + [False] * 2, 0.0),
        ("vib_tokens", "occlusion", 1000, None): cell("occ", "occlusion", [600_000, 600_001], [False, False], 6.0),
        ("act_chosen", "normal", 1000, None): {"condition": "normal", "seeds": [600_000], "success": [True]},
    }
    out = failure_report.with_rollout_rnd(cells, "vib_tokens", 1000, "act:0.3", steps=300)
    assert set(out) == {key, ("vib_tokens", "occlusion", 1000, None)}  # other rows are not touched
    assert out[key]["fitted_on"] == {failure_report.ROLLOUT_RND: [400_000, 400_002, 400_004, 400_006, 400_008]}
    assert "fitted_on" not in out[("vib_tokens", "occlusion", 1000, None)]  # no test rollout is fitted on
    val_u = np.array(out[key]["scores"][failure_report.ROLLOUT_RND])
    occluded_u = np.array(out[("vib_tokens", "occlusion", 1000, None)]["scores"][failure_report.ROLLOUT_RND])
    assert val_u[0:10:2].mean() == pytest.approx(1.0, rel=1e-3)  # normalized on the frames it was fitted on
    assert occluded_u.mean() > 3 * val_u[1:10:2].mean()
    episodes = failure_report.cell_episodes(out[key])
    assert [failure_report.ROLLOUT_RND in e.fitted_on for e in episodes[:4]] == [True, False, True, False]
    assert "fitted_on" not in cells[key]  # the cells given are left as they are


def _judged(per_group: dict[str, list[tuple[float, float, float]]]) -> list[dict]:
    """judge_candidates-style rows from (TPR, TNR, detection time) per group, 100 failures and 100 successes
    per group, no benign successes alarmed."""
    from lerobot_vib.failure import FailureMetrics

    def metrics(tpr: float, tnr: float, detection: float) -> tuple:
        hits = round(100 * tpr)
        return FailureMetrics(100, 100, hits, round(100 * (1 - tnr)), [detection] * hits, []), FailureMetrics(
            0, 10, 0, 0, [], []
        )

    return [
        {"monitor": Monitor((name,)), "order": i, "groups": {g: metrics(*m) for g, m in zip("ABC", rows, strict=True)}}
        for i, (name, rows) in enumerate(per_group.items())
    ]


def test_a_monitor_that_meets_the_targets_by_luck_on_two_seeds_and_misses_on_the_third_buys_the_rule_a_margin():
    from lerobot_vib.scripts.failure_report import cross_validated_margin

    judged = _judged(
        {
            "safe": [(0.97, 0.97, 0.50)] * 3,
            "edge": [(0.97, 0.93, 0.10), (0.97, 0.93, 0.10), (0.97, 0.70, 0.10)],  # 0.93 on A and B, 0.70 on C
        }
    )
    margin, table = cross_validated_margin(judged, margins=(0.0, 0.02, 0.05))
    by_margin = {r["margin"]: r for r in table}
    # margin 0: chosen on A and B, "edge" ships and alarms on 30% of C's successes; pooled TNR (97+97+70)/300
    assert by_margin[0.0]["picked"] == {"A": "safe, w=1 mean, constant", "B": "safe, w=1 mean, constant",
                                        "C": "edge, w=1 mean, constant"}  # fmt: skip
    assert by_margin[0.0]["tnr"] == pytest.approx(0.88)
    assert by_margin[0.02]["tnr"] == pytest.approx(0.88)  # 0.93 clears 0.92 too
    assert by_margin[0.05]["tnr"] == pytest.approx(0.97)  # "edge" must clear 0.95 now: "safe" everywhere
    assert margin == 0.05


def test_a_monitor_that_meets_the_targets_on_every_held_out_seed_keeps_the_rule_without_a_margin():
    from lerobot_vib.scripts.failure_report import cross_validated_margin

    judged = _judged({"safe": [(0.97, 0.97, 0.50)] * 3, "early": [(0.93, 0.93, 0.10)] * 3})
    margin, table = cross_validated_margin(judged, margins=(0.0, 0.05))
    assert margin == 0.0 and table[0]["detection_time"] == pytest.approx(0.10)
    assert table[1]["detection_time"] == pytest.approx(0.50)  # a margin only made the alarm later
    # with one training seed nothing can be held out
    one = [{**r, "groups": {"A": r["groups"]["A"]}} for r in judged]
    assert cross_validated_margin(one, margins=(0.0, 0.05)) == (0.0, [])


def test_a_margin_asks_every_target_for_room():
    from lerobot_vib.scripts.failure_report import meets_targets

    row = {"tpr": 0.93, "tnr": 0.93, "benign_stopped": 0.06}
    assert meets_targets(row) and meets_targets(row, 0.03)
    assert not meets_targets(row, 0.05)  # TPR and TNR 0.93 < 0.95
    assert not meets_targets({**row, "benign_stopped": 0.09}, 0.02)  # 0.09 > 0.10 - 0.02


def test_the_report_chooses_the_ship_rules_margin_on_held_out_seeds_and_prints_each_margins_figures():
    from lerobot_vib.scripts import failure_report

    rng = np.random.default_rng(5)
    cfg = _report_config([1000, 2000, 3000])
    cells = {}
    for seed in cfg.train_seeds:
        cells[("vib_tokens", "validation", seed, "act:0.3")] = _scripted_cell(rng, "validation", 40, 4, 400_000)
        cells[("vib_tokens", "normal", seed, None)] = _scripted_cell(rng, "normal", 20, 3, 600_000)
    result = failure_report.failure_prediction(cfg, cells, lambda v, s: "act:0.3")["vib_tokens"]
    table = result["margin_cross_validation"]
    assert [r["margin"] for r in table] == list(failure_report.SHIP_MARGINS)
    assert all(set(r["picked"]) == {"1000", "2000", "3000"} for r in table)
    # "b" separates every seed's failures: no margin is needed, and the smallest is the earliest that meets them
    assert result["shipped"]["margin"] == 0.0 and table[0]["tpr"] == 1.0
    lines = failure_report.markdown(cfg, {"vib_tokens": result}, {})
    assert any(line.startswith("| 0 (shipped) | 1.00 |") for line in lines)
    only = failure_report.failure_prediction(_report_config([1000]), cells, lambda v, s: "act:0.3")["vib_tokens"]
    assert only["margin_cross_validation"] == [] and only["shipped"]["margin"] == 0.0
