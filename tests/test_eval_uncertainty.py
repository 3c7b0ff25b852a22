"""lerobot-vib-eval's bookkeeping: each env's record ends where LeRobot ends its episode."""

import numpy as np
import pytest

from lerobot_vib.scripts.eval_uncertainty import UncertaintyCapture, summarize


def step(u: list[float], stopped: list[bool], just_stopped: list[bool]) -> dict:
    return {
        "rate": np.array(u) * 10,
        "u": np.array(u),
        "stopped": np.array(stopped),
        "just_stopped": np.array(just_stopped),
        "gamma": 2.0,
        "safety": True,
    }


def test_an_env_that_finishes_early_is_not_counted_while_it_waits():
    capture = UncertaintyCapture()
    steps = [
        step([1.0, 1.0], [False, False], [False, False]),
        step([3.0, 3.0], [True, True], [True, True]),  # env 0 ends here (done), env 1 stops
        step([9.0, 1.0], [True, False], [False, False]),  # env 0 waits for env 1: not its episode
    ]
    done = np.array([[False, True, True], [False, False, False]])
    capture._add_batch(steps, done, seeds=[5, 6])
    eval_info = {"per_task": [{"metrics": {"successes": [True, False], "max_rewards": [4.0, 1.0]}}]}
    info = summarize(capture.episodes, eval_info)
    first, second = info["per_episode"]
    assert first["steps"] == 2 and first["u_max"] == 3.0 and first["u_mean"] == 2.0
    assert first["stop_steps"] == [1] and first["stopped_steps"] == 1
    assert second["steps"] == 3 and second["u_mean"] == pytest.approx(5 / 3) and second["stopped_steps"] == 1
    assert (first["seed"], second["seed"]) == (5, 6)
    assert info["successes"]["n_episodes"] == 1 and info["failures"]["u_max_mean"] == 3.0
    assert info["overall"]["pc_success"] == 50.0 and info["overall"]["stopped_step_fraction"] == 2 / 5
    assert info["rate_mean"] == pytest.approx(10.0)  # u = rate / R_bar: what `--rollouts` calibration checks


def test_only_the_episodes_lerobot_keeps_are_reported():
    """n_episodes=3 in batches of 2 runs 4 episodes per task; LeRobot keeps the first 3 of each task."""
    capture = UncertaintyCapture()
    capture.episodes = [{"seed": s} for s in (0, 1, 2, 3, 0, 1, 2, 3)]  # two tasks
    assert [e["seed"] for e in capture.kept(n_episodes=3, batch_size=2)] == [0, 1, 2, 0, 1, 2]


def test_a_record_that_does_not_match_eval_info_is_refused():
    capture = UncertaintyCapture()
    with pytest.raises(RuntimeError, match="misaligned"):
        capture._add_batch([step([1.0], [False], [False])], np.zeros((1, 2), dtype=bool), seeds=None)
    capture._add_batch([step([1.0], [False], [False])], np.ones((1, 1), dtype=bool), seeds=None)
    with pytest.raises(RuntimeError, match="lists 2 episodes"):
        summarize(capture.episodes, {"per_task": [{"metrics": {"successes": [1, 0], "max_rewards": [4, 0]}}]})


def test_the_step_a_stop_became_terminal_is_reported():
    capture = UncertaintyCapture()
    steps = [step([3.0], [True], [True]), step([3.0], [True], [False]), step([3.0], [True], [False])]
    for s, halted in zip(steps, (False, True, True), strict=True):
        s["halted"] = np.array([halted])
    capture._add_batch(steps, np.zeros((1, 3), dtype=bool), seeds=[7])
    capture._add_batch(steps[:1], np.zeros((1, 1), dtype=bool), seeds=[8])
    info = summarize(capture.episodes, {"per_task": [{"metrics": {"successes": [0, 0], "max_rewards": [0, 0]}}]})
    assert [e["halted_at"] for e in info["per_episode"]] == [1, None]


def test_an_episode_picture_shows_the_rate_map_at_the_highest_u_and_at_the_first_stop(tmp_path):
    from PIL import Image

    from lerobot_vib.scripts.episode_pictures import _key_steps, draw_episode

    u = np.array([1.0, 1.2, 2.5, 3.0, 1.0])
    ep = {
        "u": u, "stop_value": u, "threshold": np.full(5, 2.0), "stopped": u > 2.0,
        "just_stopped": np.array([0, 0, 1, 0, 0], dtype=bool), "grasp_missed_at": 4,
        "rate_map": np.random.default_rng(0).random((5, 1, 12, 16)),
    }  # fmt: skip
    assert _key_steps(ep) == [("highest u", 3), ("first stop", 2)]
    assert _key_steps({**ep, "just_stopped": u > 2.9}) == [("highest u, first stop", 3)]
    draw_episode(ep, {"episode_ix": 0, "seed": 7, "success": False, "stops": 1}, "map_score", tmp_path / "e.png")
    with_map = Image.open(tmp_path / "e.png").size
    draw_episode({**ep, "rate_map": None}, {"episode_ix": 0, "seed": 7}, None, tmp_path / "f.png")
    assert with_map[1] > Image.open(tmp_path / "f.png").size[1]  # the rate maps take a row of their own


def test_the_video_frames_show_u_against_the_threshold_and_a_red_band_while_stopped():
    from types import SimpleNamespace

    from lerobot_vib.scripts.eval_uncertainty import _drawing_u

    frame = np.full((96, 128, 3), 200, dtype=np.uint8)
    subs = [SimpleNamespace(render=lambda: frame.copy()) for _ in range(2)]
    env = SimpleNamespace(envs=subs)
    step = {"score": "low_image_rate", "u": np.array([1.0, 3.0]), "stop_value": np.array([1.0, 3.0]),
            "gamma": 2.0, "thresholds": None, "stopped": np.array([False, True])}  # fmt: skip
    rendered = []
    render = _drawing_u(lambda e: rendered.append([s.render() for s in e.envs]), [step])
    render(env)
    running, stopped = rendered[0]
    assert (running[0, 0] == 0).all() and tuple(stopped[0, 0]) == (150, 0, 0)  # black band, red while stopped
    assert (running[60:] == 200).all()  # the scene below the band is untouched
    assert subs[0].render() is not None and (subs[0].render() == 200).all()  # render restored afterwards
