"""The run-time layer: one action per step from a chunk-predicting policy and one uncertainty score per step.

At every step t the caller gives the normalized score u_t (any score: the VIB rate R / R_bar, an RND error
over its training mean, or 1 for none) and a way to predict a chunk (B, chunk_size, A) from this step's
observation. `ChunkRuntime` then decides, in this order:

    1. the safety monitor (safety.py) sees u_t:   STOP if u_t > gamma or the step is unknown;
       an env that stops or resumes drops its own plans (they belong to another situation);
    2. if every env is stopped:                    a_t = the safety action (no chunk is predicted);
    3. else each running env's planner gives its a_t:
         "none"          the action queue: a chunk every n_action_steps steps, executed open loop;
         "act"           ACT's temporal ensembling (LeRobot's ACTTemporalEnsembler), a chunk every step;
         "uncertainty"   Eq. 6 (ensembling.py), a chunk every step, each weighted by the u of its pass;
       a stopped env's planner is not fed (a chunk from what stopped it must not outlive the stop);
    4. a non-finite a_t stops its env (unknown means stop); stopped envs get the safety action.

Every env has its own plans (queue or ensemble) and its own stop, so an env in a batch acts exactly as it
would alone: one env's stop, resume or NaN never touches another's actions. A chunk is predicted for the
whole batch whenever any running env needs one; the others ignore it.

The layer knows nothing about the network or the score, so VIBPolicy and every benchmark variant (ACT
driven by the VIB rate or by RND, VIB driven by RND, ...) share it instead of copying it.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable

import torch
from lerobot.policies.act.modeling_act import ACTTemporalEnsembler
from torch import Tensor

from .ensembling import UncertaintyWeightedEnsembler
from .safety import SafetyMonitor, SafetyStep

ENSEMBLE_MODES = ("none", "act", "uncertainty")


class _EnvPlans:
    """One env's plans: its action queue, or its ensemble of the chunks predicted at its recent steps."""

    def __init__(self, ensemble: str, chunk_size: int, n_action_steps: int, coeff: float):
        self.ensemble = ensemble
        self._queue: deque[Tensor] = deque(maxlen=n_action_steps)
        self.n_action_steps = n_action_steps
        self._act = ACTTemporalEnsembler(coeff, chunk_size) if ensemble == "act" else None
        self._eq6 = UncertaintyWeightedEnsembler(coeff, chunk_size) if ensemble == "uncertainty" else None

    @property
    def needs_chunk(self) -> bool:
        return self.ensemble != "none" or not self._queue

    def clear(self) -> None:
        self._queue.clear()
        if self._act is not None:
            self._act.reset()
        if self._eq6 is not None:
            self._eq6.reset()

    def next(self, chunk: Tensor | None, u: Tensor) -> Tensor:
        """chunk: (1, chunk_size, A) when `needs_chunk`; u: (1,). Returns (A,)."""
        if self.ensemble == "none":
            if not self._queue:
                self._queue.extend(chunk[0, : self.n_action_steps])
            return self._queue.popleft()
        if self._act is not None:
            return self._act.update(chunk)[0]
        return self._eq6.update(chunk, u)[0]


class ChunkRuntime:
    """Per-episode state: each env's plans (action queue or ensemble), the safety monitor and the last command.

    Args:
        ensemble: "none" (action queue), "act" (ACT's ensembling) or "uncertainty" (Eq. 6).
        chunk_size: actions per predicted chunk.
        n_action_steps: actions taken from each chunk in "none" mode.
        coeff: the ensembling coefficient m of ACT and of Eq. 6.
    """

    def __init__(self, ensemble: str, chunk_size: int, n_action_steps: int, coeff: float):
        if ensemble not in ENSEMBLE_MODES:
            raise ValueError(f"`ensemble` must be one of {ENSEMBLE_MODES}, got {ensemble!r}.")
        if not 1 <= n_action_steps <= chunk_size:
            raise ValueError(f"n_action_steps must be in [1, chunk_size={chunk_size}], got {n_action_steps}.")
        self.ensemble = ensemble
        self.chunk_size = chunk_size
        self.n_action_steps = n_action_steps
        self.coeff = coeff
        self.monitor: SafetyMonitor | None = None
        self.reset()

    def reset(self, monitor: SafetyMonitor | None = None) -> None:
        """A new episode. `monitor` decides the stops (None: built by the caller at its first step)."""
        self._plans: list[_EnvPlans] = []
        self.monitor = monitor
        self.last_command: Tensor | None = None

    @property
    def queued(self) -> bool:
        """Every env has actions waiting in its queue: the next step needs no chunk (and, if the caller
        wishes, no score)."""
        return self.ensemble == "none" and bool(self._plans) and not any(p.needs_chunk for p in self._plans)

    @property
    def any_stopped(self) -> bool:
        return self.monitor is not None and self.monitor.stopped is not None and bool(self.monitor.stopped.any())

    def clear_plans(self, mask: Tensor | None = None) -> None:
        """Drop the plans of the envs in `mask` (default: all)."""
        for b, plans in enumerate(self._plans):
            if mask is None or bool(mask[b]):
                plans.clear()

    def resume(self, mask: Tensor | None = None, grace_steps: int = 0) -> Tensor:
        """Resume stopped or halted envs now (`SafetyMonitor.resume`), with fresh plans."""
        if self.monitor is None:
            raise RuntimeError("Nothing to resume: no step has run since reset().")
        resumed = self.monitor.resume(mask, grace_steps)
        if resumed.numel():
            self.clear_plans(resumed)
        return resumed

    def step(
        self,
        u: Tensor,
        predict_chunk: Callable[[], Tensor],
        safety_action: Callable[[Tensor | None], Tensor],
        unknown: Tensor | None = None,
        stop_u: Tensor | None = None,
    ) -> tuple[Tensor, SafetyStep]:
        """One step. u: (B,); predict_chunk() -> (B, chunk_size, A), called only when a chunk is needed;
        safety_action(last_command) -> (B, A); unknown: (B,) bool, steps that cannot be trusted; stop_u: (B,)
        what the stop reads instead of u (a windowed u), while Eq. 6 weighs chunks by u.

        Returns the action (B, A) and the monitor's decision, with `stopped` including non-finite actions.
        """
        if self.monitor is None:
            raise RuntimeError("ChunkRuntime.reset(monitor) must give a safety monitor before the first step.")
        decision = self.monitor.update(u if stop_u is None else stop_u, unknown=unknown)
        if not self._plans:
            self._plans = [
                _EnvPlans(self.ensemble, self.chunk_size, self.n_action_steps, self.coeff) for _ in range(len(u))
            ]
        stopped = decision.stopped
        self.clear_plans(decision.resumed | stopped)
        if stopped.all():
            action = safety_action(self.last_command)
        else:
            action = self._plan(u, stopped, predict_chunk)
            bad = ~stopped & ~torch.isfinite(action).all(dim=-1)
            if bad.any():
                self.monitor.force_stop(bad)
                self.clear_plans(bad)
                stopped = stopped | bad
            if stopped.any():
                action = torch.where(stopped.unsqueeze(-1), safety_action(self.last_command), action)
        self.last_command = action
        step = SafetyStep(
            stopped=stopped, just_stopped=decision.just_stopped, resumed=decision.resumed, halted=decision.halted
        )
        return action, step

    def _plan(self, u: Tensor, stopped: Tensor, predict_chunk: Callable[[], Tensor]) -> Tensor:
        """(B, A): each running env's next action; stopped rows are NaN (the caller replaces them)."""
        running = [b for b in range(len(self._plans)) if not bool(stopped[b])]
        chunk = None
        if any(self._plans[b].needs_chunk for b in running):
            chunk = predict_chunk()
            self._check_chunk(chunk, len(self._plans))
        rows: dict[int, Tensor] = {}
        for b in running:
            plans = self._plans[b]
            rows[b] = plans.next(chunk[b : b + 1] if plans.needs_chunk else None, u[b : b + 1])
        template = next(iter(rows.values()))
        nan = torch.full_like(template, torch.nan)
        return torch.stack([rows.get(b, nan) for b in range(len(self._plans))])

    def _check_chunk(self, chunk: Tensor, batch_size: int) -> None:
        if chunk.ndim != 3 or chunk.shape[1] != self.chunk_size or chunk.shape[0] != batch_size:
            raise ValueError(
                f"Expected a ({batch_size}, {self.chunk_size}, action_dim) chunk, got {tuple(chunk.shape)}."
            )
