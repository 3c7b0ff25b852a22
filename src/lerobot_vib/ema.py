"""An exponential moving average of the network's weights, the weights a trained policy acts with.

After every optimizer step t = 1, 2, ... (LeRobot's training loop calls `policy.update()`):

    theta_bar_1 = theta_1
    theta_bar_t = d_t * theta_bar_{t-1} + (1 - d_t) * theta_t,    d_t = min(decay, (1 + t) / (10 + t))

The warm-up of d_t keeps the first, random weights from lingering: early on the average spans about the last
tenth of training, later `1 / (1 - decay)` steps.
Buffers (batch-norm statistics) are averaged the same way.

Why: with a constant learning rate and small batches, one checkpoint's success rate swings by tens of points
from the next one's; the average of the recent weights is a steadier policy to act with than the last ones.
torch's `AveragedModel` holds the copy and does the update; this module only chooses d_t.
"""

from __future__ import annotations

from torch import Tensor, nn
from torch.optim.swa_utils import AveragedModel

EMA_WARMUP = 10.0  # d_t = (1 + t) / (EMA_WARMUP + t) until it reaches `decay`


def ema_decay_at(step: int | Tensor, decay: float) -> float:
    """d_t for the t-th average (t >= 1)."""
    t = float(step)
    return min(decay, (1.0 + t) / (EMA_WARMUP + t))


def make_ema(model: nn.Module, decay: float) -> AveragedModel:
    """A frozen copy of `model` whose `update_parameters(model)` applies the average above."""
    if not 0.0 < decay < 1.0:
        raise ValueError(f"The EMA decay must be in (0, 1), got {decay}.")

    def average(averaged: Tensor, current: Tensor, n_averaged: Tensor) -> Tensor:
        # AveragedModel copies the weights at its first update and calls this from the second on, with
        # n_averaged = t - 1.
        if not averaged.is_floating_point():  # counters such as batch norm's num_batches_tracked
            return current
        d = ema_decay_at(int(n_averaged) + 1, decay)
        return d * averaged + (1.0 - d) * current

    ema = AveragedModel(model, avg_fn=average, use_buffers=True)
    ema.requires_grad_(False)
    return ema
