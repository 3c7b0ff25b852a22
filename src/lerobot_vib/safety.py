"""The safety stop (paper Sec. III-E, Fig. 3c): a per-environment state machine fed one score per step.

    RUN  -> STOP  when  u > gamma  (if the threshold stop is enabled)  or  the step is unknown
                        (u, the observation or the predicted action not finite: unknown means stop)
    STOP -> RUN   when  u < resume_threshold  for  resume_steps  consecutive steps
    STOP -> HALT  after  max_hold_steps  consecutive stopped steps
    STOP | HALT -> RUN   only by `resume()`: an operator's (or a robot loop's) explicit decision

Why HALT: a stopped arm holds still, so its image and pose stop changing and u goes flat. A stop caused by
something the hold keeps in view (the pose itself, an object that stays) would otherwise last forever. After
`max_hold_steps` the stop becomes terminal and says so (`halted`), so a loop can end the episode, send the arm
home, or ask an operator; `resume()` leaves either state, optionally ignoring the threshold for a few
`grace_steps` so the arm can move away from what it cannot judge (non-finite steps stop it even then).

`SafetyMonitor` knows nothing about the policy or the score: any uncertainty score (the VIB rate, RND, ...)
can drive it. `SafetyAction` produces what a stopped policy emits: `hold` repeats the last commanded action;
`home` moves towards a home pose, each action dimension changing by at most `max_step` per step:

    a_t = a_{t-1} + clip(home - a_{t-1}, -max_step, max_step)      (robot units).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from lerobot.configs.types import FeatureType, NormalizationMode, PolicyFeature
from lerobot.processor import NormalizerProcessorStep, TransitionKey, UnnormalizerProcessorStep, create_transition
from lerobot.utils.constants import ACTION, OBS_STATE
from torch import Tensor, nn


class NothingSafeToHoldError(RuntimeError):
    """The stop fired at an episode's first step and there is no action it can hold: nothing was commanded yet
    and the measured pose is missing or not finite. A command line shows it as one line (cli_errors.py)."""


@dataclass
class SafetyStep:
    """What one step of the monitor decided, per batch element."""

    stopped: Tensor  # (B,) bool: the safety action is emitted this step
    just_stopped: Tensor  # (B,) bool: RUN -> STOP at this step
    resumed: Tensor  # (B,) bool: STOP -> RUN at this step (plans made before the stop must be dropped)
    halted: Tensor | None = None  # (B,) bool: the stop is terminal (held max_hold_steps); only resume() ends it


class SafetyMonitor:
    """Batched RUN/STOP state machine with hysteresis.

    Args:
        gamma: stop when u > gamma. None: never stop on the threshold (non-finite steps still stop).
        resume_threshold: resume after u < resume_threshold for `resume_steps` steps (default: gamma).
        resume_steps: consecutive calm steps needed to resume.
        max_hold_steps: consecutive stopped steps after which the stop becomes terminal (HALT). None: never,
            for benchmarks that study the stop itself; a policy always sets it.
    """

    def __init__(
        self,
        gamma: float | None,
        resume_threshold: float | None = None,
        resume_steps: int = 10,
        max_hold_steps: int | None = None,
    ):
        if resume_steps < 1:
            raise ValueError(f"resume_steps must be >= 1, got {resume_steps}.")
        if max_hold_steps is not None and max_hold_steps < 1:
            raise ValueError(f"max_hold_steps must be >= 1, got {max_hold_steps}.")
        if resume_threshold is None:
            resume_threshold = gamma if gamma is not None else float("inf")
        if gamma is not None and resume_threshold > gamma:
            raise ValueError(f"resume_threshold ({resume_threshold}) must not exceed gamma ({gamma}).")
        self.gamma = gamma
        self.resume_threshold = resume_threshold
        self.resume_steps = resume_steps
        self.max_hold_steps = max_hold_steps
        self.reset()

    def reset(self) -> None:
        self.stopped: Tensor | None = None
        self.halted: Tensor | None = None
        self._calm_steps: Tensor | None = None
        self._held_steps: Tensor | None = None
        self._grace: Tensor | None = None

    def _start(self, u: Tensor) -> None:
        self.stopped = torch.zeros_like(u, dtype=torch.bool)
        self.halted = torch.zeros_like(self.stopped)
        self._calm_steps = torch.zeros_like(u, dtype=torch.long)
        self._held_steps = torch.zeros_like(self._calm_steps)
        self._grace = torch.zeros_like(self._calm_steps)

    def update(self, u: Tensor, unknown: Tensor | None = None) -> SafetyStep:
        """u: (B,) scores; unknown: (B,) bool, True where this step cannot be trusted for another reason."""
        u = u.detach().reshape(-1)
        if self.stopped is None:
            self._start(u)
        elif self.stopped.shape != u.shape:
            raise ValueError(f"Batch size changed from {self.stopped.shape[0]} to {u.shape[0]} without reset().")
        bad = ~torch.isfinite(u)
        if unknown is not None:
            bad = bad | unknown.reshape(-1).to(bad.device)
        too_high = u > self.gamma if self.gamma is not None else torch.zeros_like(bad)
        too_high = too_high & (self._grace == 0)  # an operator's resume() moves the arm away first
        self._grace = (self._grace - 1).clamp_min(0)
        calm = ~bad & (u < self.resume_threshold)

        was_stopped = self.stopped
        self._calm_steps = torch.where(was_stopped & calm, self._calm_steps + 1, torch.zeros_like(self._calm_steps))
        resumed = was_stopped & ~self.halted & (self._calm_steps >= self.resume_steps)
        just_stopped = ~was_stopped & (bad | too_high)
        # A step that cannot be trusted stops even a policy that would resume now.
        stopped = (was_stopped & ~resumed) | just_stopped | bad
        self._calm_steps = torch.where(stopped, self._calm_steps, torch.zeros_like(self._calm_steps))
        self._held_steps = torch.where(stopped, self._held_steps + 1, torch.zeros_like(self._held_steps))
        if self.max_hold_steps is not None:
            self.halted = self.halted | (self._held_steps >= self.max_hold_steps)
        self.stopped = stopped
        return SafetyStep(
            stopped=stopped, just_stopped=just_stopped, resumed=resumed & ~bad, halted=self.halted.clone()
        )

    def resume(self, mask: Tensor | None = None, grace_steps: int = 0) -> Tensor:
        """Leave STOP or HALT now for the envs in `mask` (default: all), whatever u is: an explicit decision
        from outside the policy. For the next `grace_steps` steps u > gamma does not stop them (a non-finite
        step still does). Returns the envs that were stopped and are now running."""
        if grace_steps < 0:
            raise ValueError(f"grace_steps must be >= 0, got {grace_steps}.")
        if self.stopped is None:
            return torch.zeros(0, dtype=torch.bool)  # no step yet: nothing is stopped
        mask = torch.ones_like(self.stopped) if mask is None else torch.as_tensor(mask, dtype=torch.bool)
        mask = mask.reshape(-1).to(self.stopped.device)
        if mask.shape != self.stopped.shape:
            raise ValueError(f"resume() needs one flag per env ({self.stopped.shape[0]}), got {mask.shape[0]}.")
        resumed = mask & self.stopped
        self.stopped = self.stopped & ~mask
        self.halted = self.halted & ~mask
        zero = torch.zeros_like(self._calm_steps)
        self._calm_steps = torch.where(mask, zero, self._calm_steps)
        self._held_steps = torch.where(mask, zero, self._held_steps)
        self._grace = torch.where(mask, torch.full_like(self._grace, grace_steps), self._grace)
        return resumed

    def set_threshold(self, gamma: float | Tensor, resume_threshold: float | None = None) -> None:
        """Change the thresholds from this step on (a time-indexed band moves them every step); `gamma` may be
        one per env, (B,), where each env reads the band at its own progress."""
        if resume_threshold is None:
            resume_threshold = gamma
        elif isinstance(gamma, Tensor):
            resume_threshold = gamma.clamp(max=resume_threshold)
        else:
            resume_threshold = min(resume_threshold, gamma)
        self.gamma, self.resume_threshold = gamma, resume_threshold

    def force_stop(self, mask: Tensor) -> None:
        """Stop these batch elements now (e.g. the policy produced a non-finite action)."""
        newly = mask & ~self.stopped
        self.stopped = self.stopped | mask
        self._calm_steps = torch.where(mask, torch.zeros_like(self._calm_steps), self._calm_steps)
        self._held_steps = torch.where(newly, torch.ones_like(self._held_steps), self._held_steps)


class SafetyAction:
    """The action a stopped policy emits, in robot units.

    Args:
        mode: "hold" or "home".
        home: (A,) home action (needed for "home"; for "hold", used when nothing was commanded yet).
        max_step: largest change per step and dimension when going home.
    """

    def __init__(self, mode: str, home: Tensor | None = None, max_step: float = 0.01):
        if mode not in ("hold", "home"):
            raise ValueError(f"Safety action must be 'hold' or 'home', got {mode!r}.")
        if mode == "home" and home is None:
            raise ValueError("The 'home' safety action needs a home pose.")
        if not max_step > 0:
            raise ValueError(f"max_step must be > 0, got {max_step}.")
        self.mode, self.home, self.max_step = mode, home, max_step

    def __call__(self, last_command: Tensor | None, fallback: Tensor | None = None, batch_size: int = 1) -> Tensor:
        """last_command: (B, A) last action sent to the robot, or None at the first step; fallback: (B, A)
        stand-in for it at the first step (e.g. the measured joint positions). Returns (B, A)."""
        reference = last_command
        if reference is None and fallback is not None and torch.isfinite(fallback).all():
            reference = fallback
        if reference is None:
            if self.mode == "hold" and self.home is not None:
                return self.home.expand(batch_size, -1).clone()
            if fallback is not None:  # a pose was measured, but it is NaN or inf: say so, that is the cause
                bad = sorted({int(i) for i in torch.nonzero(~torch.isfinite(fallback))[:, 0]})
                raise NothingSafeToHoldError(
                    f"Safety stop at the first step: the measured pose (observation.state) is not finite (NaN or "
                    f"inf) in env{'s' if len(bad) > 1 else ''} {', '.join(map(str, bad))}, and no action has been "
                    "commanded yet, so there is nothing safe to hold. Check the robot's joint readings; "
                    "`safety.home_pose` gives the stop a pose to hold when the readings cannot be trusted."
                )
            raise NothingSafeToHoldError(
                "Safety stop at the first step with no commanded action and no measured pose to start from: "
                + ("configure `safety.home_pose`." if self.mode == "hold" else "cannot go home in bounded steps.")
            )
        if self.mode == "hold":
            return reference.clone()
        home = self.home.to(reference)
        return reference + (home - reference).clamp(-self.max_step, self.max_step)


# Statistics each normalization mode needs (LeRobot's normalizer).
_MODE_STATS = {
    NormalizationMode.MEAN_STD: ("mean", "std"),
    NormalizationMode.MIN_MAX: ("min", "max"),
    NormalizationMode.QUANTILES: ("q01", "q99"),
    NormalizationMode.QUANTILE10: ("q10", "q90"),
    NormalizationMode.IDENTITY: (),
}


class RobotUnits(nn.Module):
    """Actions (and the robot state) between the policy's normalized space and robot units.

    The policy acts in normalized space; a home pose and its per-step bound are in robot units. The dataset
    statistics the processors normalize with are kept here as buffers (NaN until known), so a checkpoint
    carries them; the arithmetic is LeRobot's normalizer's.
    """

    def __init__(
        self,
        features: dict[str, PolicyFeature],
        norm_map: dict[str, NormalizationMode],
        dataset_stats: dict[str, dict] | None = None,
    ):
        super().__init__()
        self.features = features
        self.norm_map = {FeatureType(k) if isinstance(k, str) else k: NormalizationMode(v) for k, v in norm_map.items()}
        self._names: dict[str, dict[str, str]] = {}
        for key, ft in features.items():
            mode = self.norm_map.get(ft.type, NormalizationMode.IDENTITY)
            self._names[key] = {}
            for stat in _MODE_STATS[mode]:
                name = f"{key.replace('.', '_')}_{stat}"
                value = torch.full(tuple(ft.shape), torch.nan)
                if dataset_stats and stat in dataset_stats.get(key, {}):
                    value = torch.as_tensor(dataset_stats[key][stat], dtype=torch.float32).reshape(ft.shape)
                self.register_buffer(name, value)
                self._names[key][stat] = name

    def known(self, key: str) -> bool:
        return key in self._names and all(torch.isfinite(getattr(self, n)).all() for n in self._names[key].values())

    def _stats(self) -> dict[str, dict[str, Tensor]]:
        return {key: {stat: getattr(self, n) for stat, n in names.items()} for key, names in self._names.items()}

    def _transform(self, key: str, value: Tensor, inverse: bool) -> Tensor:
        if not self.known(key):
            raise RuntimeError(
                f"The normalization statistics of `{key}` are unknown to the policy: it was built without "
                "dataset statistics (train it with lerobot-train or pass `dataset_stats`)."
            )
        step_cls = UnnormalizerProcessorStep if inverse else NormalizerProcessorStep
        step = step_cls(features=self.features, norm_map=self.norm_map, stats=self._stats(), device=value.device)
        if key == ACTION:
            return step(create_transition(action=value))[TransitionKey.ACTION]
        return step(create_transition(observation={key: value}))[TransitionKey.OBSERVATION][key]

    def to_robot(self, key: str, value: Tensor) -> Tensor:
        return self._transform(key, value, inverse=True)

    def to_policy(self, key: str, value: Tensor) -> Tensor:
        return self._transform(key, value, inverse=False)


class PolicySafetyAction:
    """The safety action of a policy that acts in normalized space: `SafetyAction` in robot units, converted
    with the policy's dataset statistics (`RobotUnits`), since a home pose and its per-step bound are physical.

    `hold` repeats the last command (at the very first step: the measured joint positions, for robots whose
    state is in the action space, else the home pose); `home` steps towards `home_pose`. A halted env goes
    home when a home pose is configured, whatever the mode; the other envs keep their mode.
    """

    def __init__(self, mode: str, home_pose: list[float] | None, max_step: float, units: RobotUnits):
        self.mode, self.home_pose, self.max_step, self.units = mode, home_pose, max_step, units

    def __call__(
        self,
        last_command: Tensor | None,
        state: Tensor | None,
        halted: Tensor | None,
        batch_size: int,
        device: torch.device | str = "cpu",
    ) -> Tensor:
        """last_command, state: (B, A) / (B, S) normalized, or None; halted: (B,) bool or None. Returns (B, A)."""
        going_home = self.home_pose is not None and halted is not None and bool(halted.any())
        if self.mode == "hold" and last_command is not None and not going_home:
            return last_command
        units = self.units
        last = None if last_command is None else units.to_robot(ACTION, last_command)
        measured = None
        action_dim = units.features[ACTION].shape[0]
        if last is None and state is not None and state.shape[-1] == action_dim and units.known(OBS_STATE):
            measured = units.to_robot(OBS_STATE, state)  # joint-position robots: state = action space
        home = None
        if self.home_pose is not None:
            home = torch.tensor(self.home_pose, dtype=torch.float32, device=device)
        if last is None and home is None and state is not None and not torch.isfinite(state).all():
            measured = state  # not a pose to hold, but what SafetyAction names as the cause
        action = SafetyAction(self.mode, home, self.max_step)(last, measured, batch_size)
        if going_home and self.mode == "hold":
            homeward = SafetyAction("home", home, self.max_step)(action, None, batch_size)
            action = torch.where(halted.to(action.device).unsqueeze(-1), homeward, action)
        return units.to_policy(ACTION, action)
