"""The run-time layer: one action per step from a chunk-predicting policy and one uncertainty score per step.

At every step t the caller gives the normalized score u_t (any score: the VIB rate R / R_bar, an RND error
over its training mean, or 1 for none) and a way to predict a chunk (B, chunk_size, A) from this step's
observation. `ChunkRuntime` then decides, in this order:

    1. the safety monitor (safety.py) sees u_t:   STOP if u_t > gamma or the step is unknown;
       a resume drops every plan made before the stop;
    2. if every env is stopped:                    a_t = the safety action (no chunk is predicted);
    3. else the planner gives a_t:
         "none"          the action queue: a chunk every n_action_steps steps, executed open loop;
         "act"           ACT's temporal ensembling (LeRobot's ACTTemporalEnsembler), a chunk every step;
         "uncertainty"   Eq. 6 (ensembling.py), a chunk every step, each weighted by the u of its pass;
    4. a non-finite a_t stops its env (unknown means stop); stopped envs get the safety action.

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


class ChunkRuntime:
    """Per-episode state: the action queue or ensembler, the safety monitor and the last command.

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
        self._queue: deque[Tensor] = deque(maxlen=self.n_action_steps)
        self._act = ACTTemporalEnsembler(self.coeff, self.chunk_size)
        self._eq6 = UncertaintyWeightedEnsembler(self.coeff, self.chunk_size)
        self.monitor = monitor
        self.last_command: Tensor | None = None

    @property
    def queued(self) -> bool:
        """Actions are waiting in the queue: the next step needs no chunk (and, if the caller wishes, no score)."""
        return self.ensemble == "none" and len(self._queue) > 0

    @property
    def any_stopped(self) -> bool:
        return self.monitor is not None and self.monitor.stopped is not None and bool(self.monitor.stopped.any())

    def clear_plans(self) -> None:
        self._queue.clear()
        self._act.reset()
        self._eq6.reset()

    def step(
        self,
        u: Tensor,
        predict_chunk: Callable[[], Tensor],
        safety_action: Callable[[Tensor | None], Tensor],
        unknown: Tensor | None = None,
    ) -> tuple[Tensor, SafetyStep]:
        """One step. u: (B,); predict_chunk() -> (B, chunk_size, A), called only when a chunk is needed;
        safety_action(last_command) -> (B, A); unknown: (B,) bool, steps that cannot be trusted.

        Returns the action (B, A) and the monitor's decision, with `stopped` including non-finite actions.
        """
        if self.monitor is None:
            raise RuntimeError("ChunkRuntime.reset(monitor) must give a safety monitor before the first step.")
        decision = self.monitor.update(u, unknown=unknown)
        if decision.resumed.any():
            self.clear_plans()  # plans made before the stop belong to another situation
        stopped = decision.stopped
        if stopped.all():
            action = safety_action(self.last_command)
        else:
            action = self._plan(u, predict_chunk)
            bad = ~torch.isfinite(action).all(dim=-1)
            if bad.any():
                self.monitor.force_stop(bad)
                stopped = stopped | bad
            if stopped.any():
                action = torch.where(stopped.unsqueeze(-1), safety_action(self.last_command), action)
        self.last_command = action
        return action, SafetyStep(stopped=stopped, just_stopped=decision.just_stopped, resumed=decision.resumed)

    def _plan(self, u: Tensor, predict_chunk: Callable[[], Tensor]) -> Tensor:
        if self.ensemble == "none":
            if not self._queue:
                chunk = predict_chunk()
                self._check_chunk(chunk)
                self._queue.extend(chunk[:, : self.n_action_steps].transpose(0, 1))
            return self._queue.popleft()
        chunk = predict_chunk()
        self._check_chunk(chunk)
        if self.ensemble == "act":
            return self._act.update(chunk)
        return self._eq6.update(chunk, u)

    def _check_chunk(self, chunk: Tensor) -> None:
        if chunk.ndim != 3 or chunk.shape[1] != self.chunk_size:
            raise ValueError(f"Expected a (batch, {self.chunk_size}, action_dim) chunk, got {tuple(chunk.shape)}.")
