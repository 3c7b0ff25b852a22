"""Uncertainty-weighted temporal ensembling (paper Eq. 6, read as in DESIGN.md section 3).

At every step the policy predicts a chunk of `chunk_size` actions and records that pass's normalized
uncertainty u. The action executed at time t has one candidate from each of the last `chunk_size` chunks.
Ordering the candidates by arrival (j = 0 the oldest), candidate j gets the weight

    w_j = exp(-m * u_j * j) / sum_k exp(-m * u_k * k),

u_j being the u of the pass that produced it. With u_j = 1 for all j this is ACT's temporal ensembling
(LeRobot's `ACTTemporalEnsembler`, w_i = exp(-m * i), w_0 the oldest). A newer chunk predicted under high
uncertainty is discounted more, so reliable past predictions are not overshadowed by unreliable recent ones.
A candidate whose u is not finite gets weight 0; if no candidate has a finite u the result is NaN (which
the safety stop turns into the safety action).

From the paper's Eq. 6. The paper writes w = exp(u_t * m * i) / sum_i exp(u_i * m * i) over the candidates
a_{t-i} of the last T chunks, and says m trades temporal ensembling against uncertainty weighting so that
reliable past actions are not overshadowed by unreliable recent ones. Its sign and index are typeset
ambiguously; the reading above is the one that (a) is ACT's ensembling when every u is 1, which the paper
builds on, and (b) discounts a candidate more the higher its u, as the sentence says.

What the reading implies, and how to choose m. Candidate j's log-weight is -m * u_j * j, so
  - at u = 1 the weights fall by exp(-m) per step of age towards the newest; what matters is m * (C - 1)
    over a full window of C = chunk_size candidates: with C = 20, m = 0.01 gives 0.19 (newest 4.5% against
    oldest 5.5%, nearly a plain mean), m = 0.1 gives 1.9 (newest 7x lighter), m = 0.3 gives 5.7 (the
    oldest few candidates carry almost everything: the policy follows old plans, close to open loop);
  - u moves candidate j's log-weight by -m * j * (u_j - 1): in proportion to m * j. The oldest candidate's
    u never counts (j = 0), the newest's counts most; with m = 0.01 and C = 20 the newest needs u about 6
    to lose a factor e against u = 1. So m must be chosen for the chunk size: m * (C - 1) of about 1-6 is
    where u can move the weights at all, and there the ensemble is already weighted to old plans.
`benchmarks/eq6_sweep.py` measures this on the arm (docs/uncertainty.md, Eq. 6 on the arm).
"""

from __future__ import annotations

import torch
from torch import Tensor


class UncertaintyWeightedEnsembler:
    """Batched: `update(chunk (B, chunk_size, A), u (B,))` returns the action (B, A) to execute now."""

    def __init__(self, coeff: float, chunk_size: int):
        self.coeff = coeff
        self.chunk_size = chunk_size
        self.reset()

    def reset(self) -> None:
        # Newest last. Chunk k steps old contributes its action at index k.
        self._chunks: list[Tensor] = []
        self._u: list[Tensor] = []

    def update(self, chunk: Tensor, u: Tensor) -> Tensor:
        if chunk.ndim != 3 or chunk.shape[1] != self.chunk_size:
            raise ValueError(f"Expected a (batch, {self.chunk_size}, action_dim) chunk, got {tuple(chunk.shape)}.")
        if u.shape != chunk.shape[:1]:
            raise ValueError(f"Expected one u per batch element {tuple(chunk.shape[:1])}, got {tuple(u.shape)}.")
        self._chunks.append(chunk)
        self._u.append(u.to(chunk.dtype))
        if len(self._chunks) > self.chunk_size:
            self._chunks.pop(0)
            self._u.pop(0)
        n = len(self._chunks)
        # Chunk i (oldest first) was predicted n - 1 - i steps ago: its candidate for now is at that index.
        candidates = torch.stack([c[:, n - 1 - i] for i, c in enumerate(self._chunks)], dim=1)  # (B, n, A)
        u_hist = torch.stack(self._u, dim=1)  # (B, n)
        j = torch.arange(n, device=chunk.device, dtype=chunk.dtype)
        finite = torch.isfinite(u_hist)
        logits = torch.where(finite, -self.coeff * u_hist * j, torch.full_like(u_hist, -torch.inf))
        weights = torch.softmax(logits, dim=1)
        # Masked, not multiplied by 0: a chunk predicted from a non-finite observation may hold NaNs.
        action = torch.where(finite.unsqueeze(-1), weights.unsqueeze(-1) * candidates, 0.0).sum(dim=1)
        return torch.where(finite.any(dim=1, keepdim=True), action, torch.nan)
