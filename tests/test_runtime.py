"""The run-time layer shared by VIBPolicy and the benchmark's variants (runtime.py)."""

import pytest
import torch
from lerobot.policies.act.modeling_act import ACTTemporalEnsembler

from lerobot_vib.runtime import ChunkRuntime
from lerobot_vib.safety import SafetyMonitor


def chunks(n_steps: int, batch: int = 2, chunk: int = 4, dim: int = 3) -> list[torch.Tensor]:
    g = torch.Generator().manual_seed(0)
    return [torch.randn(batch, chunk, dim, generator=g) for _ in range(n_steps)]


def hold(last):
    return last if last is not None else torch.zeros(2, 3)


def test_queue_predicts_a_chunk_every_n_action_steps_and_executes_it_open_loop():
    runtime = ChunkRuntime("none", chunk_size=4, n_action_steps=3, coeff=0.01)
    runtime.reset(SafetyMonitor(gamma=None))
    planned, calls = chunks(3), []

    def predict():
        calls.append(1)
        return planned[len(calls) - 1]

    actions = [runtime.step(torch.ones(2), predict, hold)[0] for _ in range(7)]
    assert len(calls) == 3  # steps 0, 3 and 6
    torch.testing.assert_close(torch.stack(actions[:3], 1), planned[0][:, :3])
    torch.testing.assert_close(actions[3], planned[1][:, 0])


def test_u_equal_to_one_in_eq6_mode_reduces_to_acts_ensembler():
    eq6 = ChunkRuntime("uncertainty", chunk_size=4, n_action_steps=1, coeff=0.3)
    act = ChunkRuntime("act", chunk_size=4, n_action_steps=1, coeff=0.3)
    reference = ACTTemporalEnsembler(0.3, 4)
    for runtime in (eq6, act):
        runtime.reset(SafetyMonitor(gamma=None))
    for chunk in chunks(6):
        a = eq6.step(torch.ones(2), lambda c=chunk: c, hold)[0]
        b = act.step(torch.full((2,), 7.0), lambda c=chunk: c, hold)[0]  # ACT ignores u
        torch.testing.assert_close(a, reference.update(chunk))
        torch.testing.assert_close(a, b)


def test_a_stop_emits_the_safety_action_without_predicting_and_a_resume_drops_old_plans():
    runtime = ChunkRuntime("none", chunk_size=4, n_action_steps=4, coeff=0.01)
    runtime.reset(SafetyMonitor(gamma=2.0, resume_steps=1))
    planned, calls = chunks(2, batch=1), []

    def predict():
        calls.append(1)
        return planned[len(calls) - 1]

    a0, _ = runtime.step(torch.tensor([1.0]), predict, lambda last: last)
    a1, d1 = runtime.step(torch.tensor([3.0]), predict, lambda last: last)  # stop: hold a0
    assert bool(d1.stopped) and torch.equal(a1, a0) and len(calls) == 1
    a2, d2 = runtime.step(torch.tensor([1.0]), predict, lambda last: last)  # calm: resume with a new chunk
    assert bool(d2.resumed) and not bool(d2.stopped) and len(calls) == 2
    torch.testing.assert_close(a2, planned[1][:, 0])


def test_a_non_finite_action_stops_its_env_only():
    runtime = ChunkRuntime("act", chunk_size=4, n_action_steps=1, coeff=0.01)
    runtime.reset(SafetyMonitor(gamma=None))
    chunk = chunks(1)[0]
    chunk[1] = torch.nan
    action, decision = runtime.step(torch.ones(2), lambda: chunk, lambda last: torch.zeros(2, 3))
    assert decision.stopped.tolist() == [False, True]
    assert torch.isfinite(action).all() and torch.equal(action[1], torch.zeros(3))


def test_bad_settings_and_chunks_are_refused():
    with pytest.raises(ValueError, match="ensemble"):
        ChunkRuntime("median", 4, 1, 0.01)
    with pytest.raises(ValueError, match="n_action_steps"):
        ChunkRuntime("none", 4, 5, 0.01)
    runtime = ChunkRuntime("act", 4, 1, 0.01)
    with pytest.raises(RuntimeError, match="monitor"):
        runtime.step(torch.ones(2), lambda: torch.zeros(2, 4, 3), hold)
    runtime.reset(SafetyMonitor(gamma=None))
    with pytest.raises(ValueError, match="chunk"):
        runtime.step(torch.ones(2), lambda: torch.zeros(2, 5, 3), hold)


# ------------------------------------------------------------------ every env acts as it would alone

STEPS, CHUNK, DIM = 16, 4, 3
MODES = [("none", 2), ("act", 1), ("uncertainty", 1)]


def scenario(perturbed: bool) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """u (T, 2), unknown (T, 2) and the chunk each step's observation gives (T, 2, CHUNK, DIM).

    Perturbed: env 0's observation is NaN at step 1 (unknown, and its chunk NaN), and its u is above gamma at
    steps 7-8 (an occluder). Env 1 is the same in both."""
    g = torch.Generator().manual_seed(1)
    plan = torch.randn(STEPS, 2, CHUNK, DIM, generator=g)
    us = 0.5 + torch.rand(STEPS, 2, generator=g)  # below gamma = 2
    unknown = torch.zeros(STEPS, 2, dtype=torch.bool)
    if perturbed:
        unknown[1, 0] = True
        us[1, 0] = torch.nan
        plan[1, 0] = torch.nan
        us[7:9, 0] = 3.0
    return us, unknown, plan


def run(mode: str, n_action_steps: int, us, unknown, plan, envs: list[int]) -> tuple[torch.Tensor, torch.Tensor]:
    """The runtime on the envs `envs` of the scenario; a chunk is a function of the step's observation."""
    runtime = ChunkRuntime(mode, CHUNK, n_action_steps, coeff=0.3)
    runtime.reset(SafetyMonitor(gamma=2.0, resume_steps=2))
    actions, stopped = [], []
    for t in range(STEPS):
        a, d = runtime.step(
            us[t, envs],
            lambda t=t: plan[t, envs],
            lambda last: last if last is not None else torch.zeros(len(envs), DIM),
            unknown=unknown[t, envs],
        )
        actions.append(a)
        stopped.append(d.stopped)
    return torch.stack(actions), torch.stack(stopped)


@pytest.mark.parametrize(("mode", "n_action_steps"), MODES)
def test_env_1s_actions_do_not_depend_on_env_0s_stops(mode, n_action_steps):
    calm, _ = run(mode, n_action_steps, *scenario(False), envs=[0, 1])
    disturbed, stopped = run(mode, n_action_steps, *scenario(True), envs=[0, 1])
    assert stopped[:, 0].any() and not stopped[:, 1].any()
    torch.testing.assert_close(disturbed[:, 1], calm[:, 1], rtol=0, atol=0)


@pytest.mark.parametrize(("mode", "n_action_steps"), MODES)
def test_each_env_in_a_batch_acts_and_stops_as_it_would_alone(mode, n_action_steps):
    batch, batch_stopped = run(mode, n_action_steps, *scenario(True), envs=[0, 1])
    for env in (0, 1):
        alone, alone_stopped = run(mode, n_action_steps, *scenario(True), envs=[env])
        torch.testing.assert_close(batch[:, env], alone[:, 0], rtol=0, atol=0)
        assert torch.equal(batch_stopped[:, env], alone_stopped[:, 0])
    # A NaN chunk does not outlive its stop: stopped at step 1, resumed on the second calm step (3); stopped
    # at 7-8 by u, resumed on the second calm step (10).
    assert batch_stopped[:, 0].nonzero().flatten().tolist() == [1, 2, 7, 8, 9]


def test_a_resume_from_outside_restarts_only_that_envs_plans():
    runtime = ChunkRuntime("none", CHUNK, 2, coeff=0.0)
    runtime.reset(SafetyMonitor(gamma=2.0, resume_steps=2, max_hold_steps=3))
    us, _, plan = scenario(False)
    us[2:, 0] = 5.0  # env 0's u never falls: it halts after 3 stopped steps
    for t in range(6):
        _, d = runtime.step(us[t], lambda t=t: plan[t], lambda last: last)
    assert d.halted.tolist() == [True, False] and d.stopped.tolist() == [True, False]
    assert runtime.resume(torch.tensor([True, False]), grace_steps=2).tolist() == [True, False]
    a6, d6 = runtime.step(us[6], lambda: plan[6], lambda last: last)
    assert not d6.stopped.any()  # u = 5 is ignored during the grace steps
    torch.testing.assert_close(a6[0], plan[6, 0, 0])  # env 0 replans from this step's chunk
    torch.testing.assert_close(a6[1], plan[6, 1, 0])  # env 1's queue ran out at step 6 anyway (2 per chunk)
    runtime.step(us[7], lambda: plan[7], lambda last: last)
    _, d8 = runtime.step(us[8], lambda: plan[8], lambda last: last)
    assert d8.stopped.tolist() == [True, False]  # the grace is over: u = 5 stops env 0 again
