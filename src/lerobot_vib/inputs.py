"""What the policy accepts, checked before any work: a wrong input is named with its fix, never silently used.

An observation batch must hold every input the policy was built with (cameras, `observation.state`,
`observation.environment_state`), as floating-point tensors of the policy's dtype (what LeRobot's
preprocessor gives), shaped (batch, *feature shape), with one batch size. A training batch must also hold the
action chunk (batch, chunk_size, action_dim) and no NaN or inf.
"""

from __future__ import annotations

import torch
from lerobot.configs.types import PolicyFeature
from lerobot.utils.constants import ACTION
from torch import Tensor


def check_observation(batch: dict[str, Tensor], expected: dict[str, PolicyFeature], dtype: torch.dtype) -> int:
    """Raise a clear error for a missing key, a wrong dtype or shape; return the batch size."""
    batch_size = None
    for key, ft in expected.items():
        if key not in batch:
            raise KeyError(
                f"Observation is missing `{key}`, which this policy was configured with "
                f"(expects {sorted(expected)}; got {sorted(k for k in batch if k.startswith('observation'))})."
            )
        value = batch[key]
        if not isinstance(value, Tensor):
            raise TypeError(f"`{key}` must be a torch.Tensor, got {type(value).__name__}.")
        if not value.is_floating_point() or value.dtype != dtype:
            hint = " (images as floats in [0, 1], as LeRobot's env processors give them)" if "image" in key else ""
            raise TypeError(
                f"`{key}` has dtype {value.dtype}; the policy expects {dtype}{hint}. "
                "Pass observations through the policy's preprocessor (make_pre_post_processors)."
            )
        if tuple(value.shape[1:]) != tuple(ft.shape):
            raise ValueError(
                f"`{key}` has shape {tuple(value.shape)}; expected (batch, {', '.join(map(str, ft.shape))}) "
                "as configured. Check the camera resolution / state size against the training data (in the "
                "ALOHA sim, `--env.type=aloha_fast --env.observation_height=H --env.observation_width=W` "
                "renders at the training size)."
            )
        if batch_size is None:
            batch_size = value.shape[0]
        elif value.shape[0] != batch_size:
            raise ValueError(f"`{key}` has batch size {value.shape[0]}, other inputs have {batch_size}.")
    return int(batch_size)


def check_training_batch(
    batch: dict[str, Tensor], inputs: list[str], batch_size: int, chunk_size: int, action_dim: int
) -> None:
    """The action chunk is there with its shape, and nothing the loss reads is NaN or inf."""
    if ACTION not in batch:
        raise KeyError(f"Training batch is missing `{ACTION}`.")
    expected = (batch_size, chunk_size, action_dim)
    if tuple(batch[ACTION].shape) != expected:
        raise ValueError(
            f"`{ACTION}` has shape {tuple(batch[ACTION].shape)}; expected {expected} "
            "(batch, chunk_size, action_dim). Is the dataset loaded with `action_delta_indices`?"
        )
    for key in [*inputs, ACTION]:
        if key in batch and not torch.isfinite(batch[key]).all():
            raise ValueError(f"Training batch has non-finite values (NaN or inf) in `{key}`.")
