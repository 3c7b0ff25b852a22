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
