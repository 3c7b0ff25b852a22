"""The safety stop: stops on u > gamma and on anything non-finite, holds or goes home, resumes with hysteresis."""

import itertools
import math

import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from helpers import make_batch, make_config, with_rate_statistics
from lerobot_vib.modeling_vib import VIBPolicy
from lerobot_vib.safety import SafetyAction, SafetyMonitor

NAN, INF = float("nan"), float("inf")


def run_monitor(monitor: SafetyMonitor, us: list[float]) -> list[bool]:
    return [bool(monitor.update(torch.tensor([u])).stopped) for u in us]


def test_stops_when_u_exceeds_gamma_and_resumes_after_calm_steps():
    monitor = SafetyMonitor(gamma=2.0, resume_steps=3)
    stopped = run_monitor(monitor, [1.0, 1.5, 2.5, 1.0, 1.0, 1.0, 1.0])
    # Stop at the spike; three calm steps later (the third one included) the policy runs again.
    assert stopped == [False, False, True, True, True, False, False]


def test_hysteresis_needs_u_below_the_resume_threshold_for_consecutive_steps():
    monitor = SafetyMonitor(gamma=2.0, resume_threshold=1.2, resume_steps=2)
    stopped = run_monitor(monitor, [3.0, 1.5, 1.5, 1.0, 1.9, 1.0, 1.0, 1.0])
    # 1.5 is below gamma but not calm; a relapse to 1.9 restarts the count.
    assert stopped == [True, True, True, True, True, True, False, False]


def test_u_equal_to_gamma_does_not_stop():
    assert run_monitor(SafetyMonitor(gamma=2.0), [2.0]) == [False]


@pytest.mark.parametrize("bad", [NAN, INF, -INF])
def test_non_finite_u_stops_even_without_a_threshold(bad):
    monitor = SafetyMonitor(gamma=None, resume_steps=2)
    assert run_monitor(monitor, [0.5, bad, 0.5, 0.5, 0.5]) == [False, True, True, False, False]


def test_unknown_observation_stops_and_blocks_resuming():
    monitor = SafetyMonitor(gamma=2.0, resume_steps=1)
    assert bool(monitor.update(torch.tensor([0.5]), unknown=torch.tensor([True])).stopped)
    assert bool(monitor.update(torch.tensor([0.5]), unknown=torch.tensor([True])).stopped)
    step = monitor.update(torch.tensor([0.5]), unknown=torch.tensor([False]))
    assert not bool(step.stopped) and bool(step.resumed)


def test_batched_environments_stop_independently():
    monitor = SafetyMonitor(gamma=1.0, resume_steps=1)
    assert monitor.update(torch.tensor([0.5, 3.0, NAN])).stopped.tolist() == [False, True, True]
    assert monitor.update(torch.tensor([0.5, 0.5, 0.5])).stopped.tolist() == [False, False, False]
    with pytest.raises(ValueError, match="Batch size changed"):
        monitor.update(torch.tensor([0.5]))


def test_resume_threshold_above_gamma_is_refused():
    with pytest.raises(ValueError, match="resume_threshold"):
        SafetyMonitor(gamma=1.0, resume_threshold=2.0)


def test_home_moves_at_most_max_step_per_step_and_arrives():
    home = torch.tensor([1.0, -2.0, 0.0])
    action = SafetyAction("home", home, max_step=0.1)
    current = torch.tensor([[0.0, 0.0, 0.05]])
    for _ in range(30):
        nxt = action(current)
        assert (nxt - current).abs().max() <= 0.1 + 1e-7
        current = nxt
    torch.testing.assert_close(current, home.unsqueeze(0))


def test_hold_repeats_the_last_command_and_falls_back_at_the_first_step():
    hold = SafetyAction("hold", home=torch.tensor([9.0, 9.0]))
    last = torch.tensor([[1.0, 2.0]])
    torch.testing.assert_close(hold(last), last)
    torch.testing.assert_close(hold(None, fallback=torch.tensor([[3.0, 4.0]])), torch.tensor([[3.0, 4.0]]))
    torch.testing.assert_close(hold(None, batch_size=2), torch.tensor([[9.0, 9.0], [9.0, 9.0]]))
    with pytest.raises(RuntimeError, match="home_pose"):
        SafetyAction("hold")(None)


# ----------------------------------------------------------------------------------- the policy with its stop

STATS = {
    "action": {"mean": torch.tensor([0.5, -1.0, 2.0]), "std": torch.tensor([2.0, 0.5, 1.0])},
    "observation.state": {"mean": torch.tensor([0.5, -1.0, 2.0]), "std": torch.tensor([2.0, 0.5, 1.0])},
}

STATS_5 = {  # the same for the default 5-d state of helpers.make_config
    "action": STATS["action"],
    "observation.state": {"mean": torch.zeros(5), "std": torch.ones(5)},
}


def scripted_policy(safety: dict, us: list[float], nan_chunks: set[int] = frozenset(), **config) -> VIBPolicy:
    """A small state-only policy whose u at step t is us[t] and whose decoder returns NaN at `nan_chunks`."""
    cfg = make_config(
        **{"cameras": {}, "state_dim": 3, "action_dim": 3, "chunk_size": 4, "n_action_steps": 4, **config}
    )
    for k, v in safety.items():
        setattr(cfg.safety, k, v)
    cfg.safety.__post_init__()
    cfg.calibration.rate_mean = 1.0  # so that u = rate
    policy = VIBPolicy(cfg, dataset_stats=STATS).eval()
    step = {"t": 0, "decodes": 0}
    encode, decode = policy.observation_scores, policy.model.decoder.forward

    def fake_encode(batch, wanted=None):
        posterior, scores = encode(batch, wanted)
        u = us[step["t"]]
        step["t"] += 1
        return posterior, {**scores, "rate": torch.full((batch_size(batch),), u)}

    def fake_decode(z):
        out = decode(z)
        step["decodes"] += 1
        return out * NAN if step["decodes"] in nan_chunks else out

    policy.observation_scores = fake_encode
    policy.model.decoder.forward = fake_decode
    policy.steps = step
    return policy


def batch_size(batch):
    return next(iter(batch.values())).shape[0]


def test_policy_emits_the_hold_action_while_stopped_and_replans_on_resume():
    us = [0.5, 0.5, 5.0, 5.0, 0.5, 0.5, 0.5, 0.5]
    policy = scripted_policy({"enabled": True, "gamma": 2.0, "resume_steps": 2}, us)
    obs = make_batch(policy.config, batch_size=1, with_action=False)
    out, states, decodes = [], [], []
    for _ in us:
        out.append(policy.select_action(obs))
        states.append(bool(policy.last_step.stopped))
        decodes.append(policy.steps["decodes"])
    assert states == [False, False, True, True, True, False, False, False]
    for t in (2, 3, 4):  # held: the action commanded just before the stop
        torch.testing.assert_close(out[t], out[1])
    assert decodes[5] == decodes[4] + 1  # the queue was cleared at the resume: a fresh chunk
    assert policy.last_step.gamma == 2.0 and policy.last_step.threshold_active


def test_policy_goes_home_in_bounded_steps_in_robot_units():
    home = [3.0, 0.0, -1.0]
    policy = scripted_policy(
        {"enabled": True, "gamma": 2.0, "action": "home", "home_pose": home, "home_max_step": 0.05}, [5.0] * 80
    )
    obs = make_batch(policy.config, batch_size=1, with_action=False)
    mean, std = STATS["action"]["mean"], STATS["action"]["std"]
    robot = [policy.select_action(obs) * std + mean for _ in range(80)]  # what the unnormalizer outputs
    steps = torch.stack([(b - a).abs().max() for a, b in itertools.pairwise(robot)])
    assert steps.max() <= 0.05 + 1e-5
    torch.testing.assert_close(robot[-1], torch.tensor([home]), atol=1e-4, rtol=0)


def test_home_without_dataset_statistics_fails_before_any_action():
    cfg = make_config(cameras={}, state_dim=3, action_dim=3)
    cfg.safety.action, cfg.safety.home_pose = "home", [0.0, 0.0, 0.0]
    cfg.calibration.rate_mean = 1.0
    policy = VIBPolicy(cfg)  # built without dataset_stats
    with pytest.raises(RuntimeError, match="normalization statistics"):
        policy.select_action(make_batch(cfg, batch_size=1, with_action=False))
    assert policy.runtime.last_command is None


def test_a_policy_without_rate_statistics_refuses_to_act():
    policy = VIBPolicy(make_config())
    with pytest.raises(RuntimeError, match="R_bar"):
        policy.select_action(make_batch(policy.config, batch_size=1, with_action=False))


def test_nan_observation_gives_the_safety_action_not_nan():
    policy = scripted_policy({"home_pose": [0.0, 0.0, 0.0]}, [0.5] * 4)
    obs = make_batch(policy.config, batch_size=1, with_action=False)
    first = policy.select_action(obs)
    obs_nan = {k: v.clone() for k, v in obs.items()}
    obs_nan["observation.state"][0, 1] = NAN
    held = policy.select_action(obs_nan)
    assert bool(policy.last_step.stopped) and torch.isfinite(held).all()
    torch.testing.assert_close(held, first)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    us=st.lists(st.one_of(st.floats(0.0, 4.0), st.sampled_from([NAN, INF, -INF, 2.0])), min_size=1, max_size=25),
    nan_chunks=st.sets(st.integers(1, 8), max_size=3),
    mode=st.sampled_from(["hold", "home"]),
    ensemble=st.sampled_from(["none", "uncertainty"]),
)
def test_only_the_safety_action_leaves_a_stopped_policy_and_never_a_non_finite_one(us, nan_chunks, mode, ensemble):
    n_action_steps = 1 if ensemble != "none" else 4
    policy = scripted_policy(
        {
            "enabled": True,
            "gamma": 2.0,
            "resume_threshold": 1.5,
            "resume_steps": 2,
            "action": mode,
            "home_pose": [1.0, 1.0, 1.0],
            "home_max_step": 0.1,
        },
        us,
        nan_chunks,
        temporal_ensemble=ensemble,
        n_action_steps=n_action_steps,
    )
    obs = make_batch(policy.config, batch_size=1, with_action=False)
    mean, std = STATS["action"]["mean"], STATS["action"]["std"]
    previous = None
    for u in us:
        action = policy.select_action(obs)
        assert torch.isfinite(action).all()
        step = policy.last_step
        if not math.isfinite(u) or u > 2.0:
            assert bool(step.stopped)
        if bool(step.stopped):
            if previous is None:  # stopped at the first step: the measured state stands in
                expected_robot = obs["observation.state"] * std + mean
                if mode == "home":
                    home = torch.tensor([[1.0, 1.0, 1.0]])
                    expected_robot = expected_robot + (home - expected_robot).clamp(-0.1, 0.1)
                torch.testing.assert_close(action * std + mean, expected_robot, atol=1e-5, rtol=0)
            elif mode == "hold":
                torch.testing.assert_close(action, previous)
            else:
                moved = ((action - previous) * std).abs().max()
                assert moved <= 0.1 + 1e-5
        previous = action


def test_uncertainty_at_plans_only_skips_the_encoder_but_still_stops_on_nan():
    policy = scripted_policy({}, [0.5] * 10, uncertainty_every_step=False)
    obs = make_batch(policy.config, batch_size=1, with_action=False)
    for _ in range(6):
        policy.select_action(obs)
    assert policy.steps["t"] == 2  # encoded at steps 0 and 4 only (n_action_steps = 4)
    obs["observation.state"][0, 0] = NAN
    action = policy.select_action(obs)
    assert bool(policy.last_step.stopped) and torch.isfinite(action).all()


# ------------------------------------------------------------------------------------- a stop always ends


def test_a_stop_whose_u_never_falls_halts_and_only_an_explicit_resume_ends_it():
    monitor = SafetyMonitor(gamma=2.0, resume_steps=2, max_hold_steps=5)
    halted = []
    for u in [1.0] + [3.0] * 6 + [1.0] * 4:  # u falls only after the halt: too late, the halt is terminal
        halted.append(bool(monitor.update(torch.tensor([u])).halted))
    assert halted == [False] * 5 + [True] * 6 and bool(monitor.stopped)
    assert monitor.resume().tolist() == [True]
    assert run_monitor(monitor, [1.0, 3.0]) == [False, True]  # running again, and the stop is armed again


def test_pause_and_resume_still_works_when_the_occluder_leaves_before_max_hold_steps():
    monitor = SafetyMonitor(gamma=2.0, resume_steps=3, max_hold_steps=8)
    us = [1.0] * 3 + [3.0] * 4 + [1.0] * 6  # 4 occluded steps + 3 calm ones = 7 stopped steps < 8
    steps = [monitor.update(torch.tensor([u])) for u in us]
    assert [bool(s.stopped) for s in steps] == [False] * 3 + [True] * 6 + [False] * 4
    assert not any(bool(s.halted) for s in steps)


def test_grace_steps_ignore_the_threshold_but_never_a_non_finite_step():
    monitor = SafetyMonitor(gamma=2.0, resume_steps=2, max_hold_steps=2)
    run_monitor(monitor, [3.0, 3.0])
    monitor.resume(grace_steps=3)
    assert run_monitor(monitor, [5.0, NAN]) == [False, True]
    with pytest.raises(ValueError, match="grace_steps"):
        monitor.resume(grace_steps=-1)
    with pytest.raises(ValueError, match="max_hold_steps"):
        SafetyMonitor(gamma=2.0, max_hold_steps=0)


def test_a_halted_policy_goes_home_if_it_has_a_home_pose_and_resumes_when_told():
    home = [3.0, 0.0, -1.0]
    safety = {"enabled": True, "gamma": 2.0, "home_pose": home, "home_max_step": 0.05, "max_hold_steps": 4}
    policy = scripted_policy(safety, [0.5] + [5.0] * 150 + [0.5] * 3)
    obs = make_batch(policy.config, batch_size=1, with_action=False)
    mean, std = STATS["action"]["mean"], STATS["action"]["std"]
    robot = [policy.select_action(obs) * std + mean for _ in range(4)]
    for a in robot[2:4]:  # stopped at step 1 (holding the action of step 0), not halted yet
        torch.testing.assert_close(a, robot[1])
    assert not bool(policy.last_step.halted)
    robot += [policy.select_action(obs) * std + mean for _ in range(147)]  # halted at step 4, the 4th stopped
    assert bool(policy.last_step.halted) and policy.last_step.row(0)["halted"]
    steps = torch.stack([(b - a).abs().max() for a, b in itertools.pairwise(robot)])
    assert steps.max() <= 0.05 + 1e-5
    torch.testing.assert_close(robot[-1], torch.tensor([home]), atol=1e-4, rtol=0)
    policy.select_action(obs)  # u = 0.5 now, but a halt does not resume by itself
    assert bool(policy.last_step.stopped)
    assert policy.resume().tolist() == [True]
    policy.select_action(obs)
    assert not bool(policy.last_step.stopped) and not bool(policy.last_step.halted)


def test_max_hold_steps_must_let_a_stop_end():
    from lerobot_vib.configuration_vib import SafetyConfig, VIBConfigError

    for bad in (0, -3, None):
        with pytest.raises(VIBConfigError, match="max_hold_steps"):
            SafetyConfig(max_hold_steps=bad)


def test_in_a_batch_one_envs_nan_leaves_the_other_envs_actions_unchanged():
    """Two real policies with the same weights and batch of 2; env 0 sees a NaN state at step 1 in one."""
    cfg = make_config(chunk_size=4, n_action_steps=2)
    cfg.safety.resume_steps = 2
    policy = with_rate_statistics(VIBPolicy(cfg, dataset_stats=STATS_5).eval())
    obs = [make_batch(cfg, batch_size=2, with_action=False, seed=s) for s in range(10)]
    runs = []
    for perturbed in (False, True):
        policy.reset()
        actions, stopped = [], []
        for t, o in enumerate(obs):
            o = {k: v.clone() for k, v in o.items()}
            if perturbed and t == 1:
                o["observation.state"][0] = NAN
            actions.append(policy.select_action(o))
            stopped.append(policy.last_step.stopped.clone())
        runs.append((torch.stack(actions), torch.stack(stopped)))
    (calm, _), (disturbed, stopped) = runs
    assert stopped[:, 0].tolist() == [False, True, True] + [False] * 7 and not stopped[:, 1].any()
    torch.testing.assert_close(disturbed[:, 1], calm[:, 1], rtol=0, atol=0)


def test_each_stop_resume_and_halt_is_logged_once_with_u_and_the_threshold_in_force(caplog):
    """lerobot-eval and lerobot-rollout showed nothing of the stop; the log is what they show."""
    config = make_config()
    config.safety.enabled, config.safety.gamma = True, 2.0
    config.safety.resume_steps, config.safety.max_hold_steps = 2, 4
    policy = with_rate_statistics(VIBPolicy(config))
    with caplog.at_level("WARNING", logger="lerobot_vib"):
        policy._start_episode()
        monitor = policy.runtime.monitor
        # stop at step 1, resume after two calm steps, stop again at step 5 and halt after 4 stopped steps
        for u in [1.0, 3.0, 1.0, 1.0, 1.0, 3.0, 3.0, 3.0, 3.0, 3.0, 3.0]:
            u = torch.tensor([u])
            policy.stop.log_events(monitor.update(u), u, 2.0, torch.tensor([True]), policy._episode_step, monitor)
            policy._episode_step += 1
    lines = [r.getMessage() for r in caplog.records]
    assert sum("Safety stop on:" in line for line in lines) == 1 and "safety.gamma (set by hand" in lines[0]
    stops = [line for line in lines if line.startswith("Safety stop: ")]
    assert stops == [
        "Safety stop: env 0 at episode step 1: u = 3.000 > gamma = 2.000, safety.gamma (set by hand; it overrides "
        "the calibration).",
        "Safety stop: env 0 at episode step 5: u = 3.000 > gamma = 2.000, safety.gamma (set by hand; it overrides "
        "the calibration).",
    ]
    assert [line for line in lines if "ended" in line] == [
        "Safety stop ended: env 0 resumes at episode step 3 (u = 1.000, below 2.000 for 2 steps)."
    ]
    halts = [line for line in lines if "halted" in line]
    assert len(halts) == 1 and "episode step 8" in halts[0] and "policy.resume()" in halts[0]


def test_the_threshold_in_force_says_which_of_the_settings_applies():
    from lerobot_vib.configuration_vib import CalibrationConfig

    config = make_config()
    config.calibration = CalibrationConfig(rate_mean=2.0, rate_std=0.5, gamma=1.318, gamma_method="conformal_rollouts")
    config.uncertainty_score = "rate"
    policy = VIBPolicy(config)
    assert policy.threshold_in_force() == {
        "enabled": False, "gamma": 1.318, "source": "calibration.gamma (conformal_rollouts)"
    }  # fmt: skip
    policy.config.safety.gamma = 1.5
    assert policy.threshold_in_force()["gamma"] == 1.5
    assert policy.threshold_in_force()["source"].startswith("safety.gamma")


def script_u(policy: VIBPolicy, us: list[float]) -> None:
    """The policy's u at its t-th step is us[t] (its rate scripted as us[t] * R_bar)."""
    r_bar, steps, real = policy.rate_mean(), iter(us), policy.observation_scores

    def scripted(batch, wanted=None):
        posterior, scores = real(batch, wanted)
        return posterior, {"rate": torch.full_like(scores["rate"], next(steps) * r_bar)}

    policy.observation_scores = scripted


@pytest.mark.parametrize(
    ("band_index", "stopped_steps"), [("progress", list(range(1, 9))), ("episode_step", [1, 2, 3, 4])]
)
def test_a_time_band_read_at_the_envs_progress_stands_still_while_the_arm_holds(band_index, stopped_steps):
    """Read at the episode's step, the band rose above a u that never fell and let a held arm go by the clock
    (step 5 below, u still 3); read at the env's progress, the stop ends when u falls (step 9)."""
    config = make_config(uncertainty_score="rate")
    policy = with_rate_statistics(VIBPolicy(config))
    c = policy.config.calibration
    c.gamma_band, c.gamma, c.gamma_score, c.gamma_method = [2.0] * 4 + [50.0] * 20, 50.0, "rate", "time_band_rollouts"
    policy.config.safety.enabled, policy.config.safety.resume_steps = True, 2
    policy.config.safety.band_index = band_index
    script_u(policy, [1.0, 3.0, 3.0, 3.0, 3.0, 3.0, 3.0, 3.0, 1.0, 1.0, 1.0])
    policy.reset()
    obs = make_batch(policy.config, batch_size=1, with_action=False)
    stopped = []
    for step in range(11):
        policy.select_action(obs)
        if bool(policy.last_step.stopped[0]):
            stopped.append(step)
    assert stopped == stopped_steps


@pytest.mark.parametrize(("window", "stopped_at"), [(1, [2]), (3, [7])])
def test_a_stop_on_a_windowed_u_ignores_a_one_frame_spike_and_catches_a_sustained_rise(window, stopped_at):
    """u spikes for one frame at step 2 and stays up from step 6: with the window of 3 the calibrated stop reads
    the mean of the last three u, so only the sustained rise stops it, one step after it began."""
    config = make_config(uncertainty_score="rate")
    policy = with_rate_statistics(VIBPolicy(config))
    c = policy.config.calibration
    c.gamma, c.gamma_score, c.gamma_method, c.window = 2.0, "rate", "conformal_rollouts", window
    policy.config.safety.enabled, policy.config.safety.resume_steps = True, 50
    script_u(policy, [1.0, 1.0, 4.0, 1.0, 1.0, 1.0, 2.6, 2.6, 2.6, 2.6])
    policy.reset()
    obs = make_batch(policy.config, batch_size=1, with_action=False)
    just_stopped, values = [], []
    for step in range(10):
        policy.select_action(obs)
        values.append(float(policy.last_step.stop_value[0]))
        if bool(policy.last_step.just_stopped[0]):
            just_stopped.append(step)
    assert just_stopped == stopped_at
    if window == 3:
        assert values[2] == pytest.approx(2.0) and values[8] == pytest.approx(2.6)  # (1 + 1 + 4) / 3, then 2.6
        assert float(policy.last_step.u[0]) == pytest.approx(2.6)  # Eq. 6 still reads u itself


def run_two_score_stop(combination: str, script: list[tuple[float, float]]) -> tuple[list, list, list, set]:
    """A policy whose stop reads the rate (gamma 2) and the image rate (its own threshold 2), combined by
    `combination` ("and_gammas" or "or_gammas"), on a scripted (u of the rate, image rate) per step. Returns the
    steps it stopped and resumed at, the stop value per step, and which scores each step asked for."""
    config = make_config(uncertainty_score="rate")
    policy = with_rate_statistics(VIBPolicy(config))
    c = policy.config.calibration
    c.gamma, c.gamma_score, c.gamma_method = 2.0, "rate", "conformal_rollouts"
    setattr(c, combination, {"image_rate": 2.0})
    c.score_means = {"image_rate": 1.0}
    policy.config.safety.enabled, policy.config.safety.resume_steps = True, 1
    r_bar, real, steps = policy.rate_mean(), policy.observation_scores, iter(script)
    asked = []

    def scripted(batch, wanted=None):
        asked.append(wanted)
        posterior, scores = real(batch, wanted)
        rate, image = next(steps)
        return posterior, {"rate": torch.full_like(scores["rate"], rate * r_bar),
                           "image_rate": torch.full_like(scores["rate"], image)}  # fmt: skip

    policy.observation_scores = scripted
    policy.reset()
    obs = make_batch(policy.config, batch_size=1, with_action=False)
    just_stopped, resumed, values = [], [], []
    for step in range(len(script)):
        policy.select_action(obs)
        values.append(float(policy.last_step.stop_value[0]))
        just_stopped += [step] if bool(policy.last_step.just_stopped[0]) else []
        resumed += [step] if bool(policy.last_step.resumed[0]) else []
    return just_stopped, resumed, values, set(asked)


def test_an_and_stop_fires_only_while_both_scores_are_above_and_ends_when_either_falls():
    """FIPER's AND in the policy: the rate (gamma 2) and the image rate (its own threshold 2) must both be up."""
    script = [(3.0, 1.0), (3.0, 3.0), (3.0, 3.0), (1.0, 3.0), (3.0, 3.0), (3.0, 1.0)]
    just_stopped, resumed, values, asked = run_two_score_stop("and_gammas", script)
    assert just_stopped == [1, 4] and resumed == [3, 5]  # the rate fell at 3, the image rate at 5
    assert values[0] == pytest.approx(1.0) and values[3] == pytest.approx(1.0)  # 2 * min(3/2, 1/2)
    assert asked == {None}  # every score is computed when an AND needs them


def test_an_or_stop_fires_while_either_score_is_above_and_ends_only_when_both_have_fallen():
    """The OR in the policy: the rate (gamma 2) or the image rate (its own threshold 2) stops the arm."""
    script = [(1.0, 1.0), (1.0, 3.0), (3.0, 1.0), (1.0, 1.0), (3.0, 1.0), (1.0, 1.0)]
    just_stopped, resumed, values, asked = run_two_score_stop("or_gammas", script)
    assert just_stopped == [1, 4] and resumed == [3, 5]  # the image rate alone at 1, the rate alone at 2 and 4
    assert values[1] == pytest.approx(3.0)  # 2 * max(1/2, 3/2)
    assert asked == {None}  # every score is computed when an OR needs them


def test_the_model_card_says_the_stop_also_fires_on_an_or_partner_and_at_what_level():
    from lerobot_vib.model_card import describe_calibration

    config = make_config(uncertainty_score="rate")
    c = config.calibration
    c.rate_mean, c.gamma, c.gamma_score, c.gamma_method, c.conformal_alpha = 1.0, 2.0, "rate", "conformal_rollouts", 0.1
    c.or_gammas, c.or_window, c.rollout_seeds = {"state_rate": 1.7}, 5, list(range(40))
    text = describe_calibration(config, 1.0)
    assert "also fires when `state_rate` (its mean over 5 steps) above 1.7" in text and "alpha / 2" in text
    assert "times their conformal ones" not in text
    c.or_margin = 4.0
    assert "the OR's at 4 times their conformal ones" in describe_calibration(config, 1.0)
