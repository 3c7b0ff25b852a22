"""VIBPolicy: ACT-style action chunking through a Variational Information Bottleneck (paper Sec. III-D).

The policy plumbs; a network does the learning. Two networks, each in its own module, offer the same calls
(`encode` -> posterior, `rate`, `decode` -> action chunk, `observe` -> the scores of scores.py, `forward`):

    pooled (default)  pooled_network.py: the paper's Fig. 2, pooled camera features summed with the state
                      and cut into K state tokens, one Gaussian posterior per token
    tokens            token_network.py: ACT's own token memory, one posterior per image cell and state token

    loss:             L1(actions, non-padded steps) + beta * mean(R),   R the mean of the tokens' rates

Around the network the policy keeps what acting needs: the rate's running mean and the calibration (u = R /
R_bar), the scores' fitted parts, temporal ensembling (runtime.py, ensembling.py) and the safety stop
(stop.py reads u for it, safety.py decides). readiness.py says whether a checkpoint can act on u,
model_card.py what its card says.
"""

from __future__ import annotations

import logging
import math
import re
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
from huggingface_hub import ModelCard
from lerobot.policies.pretrained import PreTrainedPolicy
from lerobot.utils.constants import ACTION, OBS_ENV_STATE, OBS_STATE
from safetensors import SafetensorError
from torch import Tensor

from .backbone import skip_pretrained_backbone
from .bottleneck import Posterior
from .calibration import RateTracker, stop_threshold, threshold_source
from .configuration_vib import VIBConfig, VIBConfigError
from .ema import make_ema
from .inputs import check_observation, check_training_batch
from .model_card import vib_model_card
from .pooled_network import PooledNetwork
from .processor_vib import vib_dataset_stats
from .readiness import check_ready_to_act_on_u, episode_score
from .runtime import ChunkRuntime
from .safety import PolicySafetyAction, RobotUnits
from .scores import ChunkDisagreement, EmbeddingRND
from .stop import PolicyStop, UncertaintyStep
from .token_network import TokenNetwork

logger = logging.getLogger(__name__)

# torch's report of a tensor whose shape differs between a file and the network it is loaded into.
SIZE_MISMATCH = re.compile(
    r"size mismatch for ([\w.]+): copying a param with shape (torch.Size\(\[[^]]*\]\)) from checkpoint, "
    r"the shape in current model is (torch.Size\(\[[^]]*\]\))"
)


class VIBPolicy(PreTrainedPolicy):
    """VIB-ILCtrl (Uncertainty-Guided Robotic Manipulation Through Variational Information Bottleneck in
    Imitation Learning) as a LeRobot policy. `last_rate` holds the rate R of the last forward pass."""

    config_class = VIBConfig
    name = "vib"

    def __init__(self, config: VIBConfig, **kwargs: Any):
        # kwargs: `dataset_stats` / `dataset_meta` from LeRobot's factory; normalization is the processors'.
        super().__init__(config)
        config.validate_features()
        self.config = config
        # Inputs the model reads; others (e.g. an extra `observation.velocity`) are ignored, as in ACT.
        self._used_inputs = {
            k: ft
            for k, ft in config.input_features.items()
            if k in config.image_features or k in (OBS_STATE, OBS_ENV_STATE)
        }
        if ignored := sorted(set(config.input_features) - set(self._used_inputs)):
            logger.warning("VIB ignores these input features: %s", ignored)
        self.model = TokenNetwork(config) if config.encoder == "tokens" else PooledNetwork(config)
        # The other scores' fitted parts (scores.py): the pooled network's state-path training mean for
        # "image_rate", the token network's per-cell rate statistics for "map_score", and the RND of
        # "embedding_rnd". NaN / unfitted until `lerobot-vib-calibrate`; outside `model`, so neither the
        # optimizer nor the weight average touches them.
        if config.encoder == "tokens":
            self.register_buffer("map_cell_mean", torch.full((self.model.n_cells,), torch.nan))
            self.register_buffer("map_cell_std", torch.full((self.model.n_cells,), torch.nan))
            rnd_dim = self.model.embedding_dim
        else:
            fused_dim = config.n_state_tokens * config.d_token
            self.register_buffer("state_embedding_mean", torch.full((fused_dim,), torch.nan))
            state_dim = config.robot_state_feature.shape[0] if config.robot_state_feature else 0
            rnd_dim = fused_dim if config.rnd_input == "fused" else self.model.encoder.pooled_dim + state_dim
        self.embedding_rnd = EmbeddingRND(rnd_dim)
        # Traces every score at every step (benchmarks): decodes a chunk per step for "chunk_disagreement".
        self.trace_all_scores = False
        # The averaged weights the policy acts with (`ema.py`); the optimizer never sees them.
        self.ema = make_ema(self.model, config.ema_decay) if config.ema_decay is not None else None
        self.rate_tracker = RateTracker(config.rate_momentum)
        units_features = {ACTION: config.action_feature}
        if config.robot_state_feature:
            units_features[OBS_STATE] = config.robot_state_feature
        # The floored statistics, as the processors normalize with them (processor_vib.py).
        stats = vib_dataset_stats(config, kwargs.get("dataset_stats"))
        self.robot_units = RobotUnits(units_features, config.normalization_mapping, stats)
        self.last_rate: Tensor | None = None
        self.last_step: UncertaintyStep | None = None
        self._threshold_announced = False
        self.reset()

    @classmethod
    def from_pretrained(cls, pretrained_name_or_path: str | Path, **kwargs: Any) -> VIBPolicy:
        with skip_pretrained_backbone():
            policy = super().from_pretrained(pretrained_name_or_path, **kwargs)
        if policy.config.safety.enabled or policy.config.temporal_ensemble == "uncertainty":
            check_ready_to_act_on_u(policy, str(pretrained_name_or_path))
        return policy

    @classmethod
    def _load_as_safetensor(cls, model: VIBPolicy, model_file: str, map_location: str, strict: bool) -> VIBPolicy:
        try:
            return super()._load_as_safetensor(model, model_file, map_location, strict)
        except SafetensorError as e:
            raise VIBConfigError(
                f"Cannot read the weights in {model_file}: the file is damaged or only partly downloaded or copied "
                f"({e}). Copy or download the checkpoint again (from the Hub: `force_download=True`)."
            ) from e
        except RuntimeError as e:
            mismatches = SIZE_MISMATCH.findall(str(e))
            if not mismatches:
                raise
            name, saved, built = mismatches[0]
            raise VIBConfigError(
                f"The weights in {model_file} do not fit this configuration: {len(mismatches)} tensor(s) differ in "
                f"shape, first {name} ({saved[11:-1]} in the file, {built[11:-1]} in the network built from the "
                "config). A `--policy.*` flag that changes the network's sizes (chunk_size, dim_model, n_layers, "
                "the cameras' image size, ...) cannot be applied to trained weights: drop it."
            ) from None

    def generate_model_card(self, *args: Any, **kwargs: Any) -> ModelCard:
        """LeRobot's card with what the policy is, the plugin it needs and its uncertainty (model_card.py)."""
        card = super().generate_model_card(*args, **kwargs)
        return vib_model_card(
            card, self.config, self.rate_mean(), kwargs.get("dataset_repo_id", args[0] if args else None)
        )

    def get_optim_params(self) -> list[dict]:
        backbone, rest = [], []
        for name, p in self.named_parameters():
            if p.requires_grad:
                trunk = name.startswith(("model.encoder.backbone.", "model.backbone."))  # pooled, tokens
                (backbone if trunk else rest).append(p)
        return [{"params": rest}, {"params": backbone, "lr": self.config.optimizer_lr_backbone}]

    @property
    def network(self) -> PooledNetwork | TokenNetwork:
        """The weights the policy acts with: the moving average in eval mode when `ema_decay` is set."""
        if self.ema is not None and not self.training:
            return self.ema.module
        return self.model

    def update(self) -> None:
        """After each optimizer step (LeRobot's training loop calls it): fold the new weights into the average."""
        if self.ema is not None:
            self.ema.update_parameters(self.model)

    def reset(self) -> None:
        """Call whenever the environment is reset."""
        cfg = self.config
        # The safety monitor is built at the first step: thresholds may come from loaded buffers.
        self.runtime = ChunkRuntime(
            cfg.temporal_ensemble, cfg.chunk_size, cfg.n_action_steps, cfg.temporal_ensemble_coeff
        )
        self._batch_size: int | None = None
        self._disagreement = ChunkDisagreement(cfg.chunk_size)
        self._episode_step = 0
        self._active_score = cfg.uncertainty_score or "rate"
        self._rate_map: Tensor | None = None
        self._embedding: Tensor | None = None
        self.stop = PolicyStop(cfg, self.score_mean, lambda step: self.stop_threshold(step))
        self.last_step = None

    # ------------------------------------------------------------------------------------------- uncertainty

    def rate_mean(self) -> float:
        """R_bar: the calibrated mean rate if `lerobot-vib-calibrate` ran, else the running mean from training."""
        calibrated = self.config.calibration.rate_mean
        return calibrated if calibrated is not None else self.rate_tracker.mean

    def score_mean(self, score: str | None = None) -> float:
        """s_bar of a score (default: the configured one): R_bar for the rate, else its calibrated mean (NaN
        if it was never calibrated)."""
        score = score or self.config.uncertainty_score
        if score == "rate":
            return self.rate_mean()
        return self.config.calibration.score_means.get(score, math.nan)

    def stop_threshold(self, step: int | None = None) -> float:
        """gamma at episode step `step` (default: the current one); calibration.py's `stop_threshold` says how."""
        return stop_threshold(self.config, self.rate_tracker, self._episode_step if step is None else step)

    def _start_episode(self) -> None:
        self._active_score = episode_score(self)
        monitor = self.stop.start(self._active_score, self.robot_units, announce=not self._threshold_announced)
        self._threshold_announced |= self.config.safety.enabled  # once per policy, not once per episode
        self.runtime.reset(monitor)

    # ---------------------------------------------------------------------------------------------- input checks

    def _check_observation(self, batch: dict[str, Tensor]) -> int:
        """Raise a clear error for a missing key, a wrong dtype or shape; return the batch size (inputs.py)."""
        return check_observation(batch, self._used_inputs, next(self.parameters()).dtype)

    def _check_training_batch(self, batch: dict[str, Tensor], batch_size: int) -> None:
        action_dim = self.config.action_feature.shape[0]
        check_training_batch(batch, [*self._used_inputs], batch_size, self.config.chunk_size, action_dim)

    # --------------------------------------------------------------------------------------------- inference

    @torch.no_grad()
    def predict_action_chunk(self, batch: dict[str, Tensor], **kwargs: Any) -> Tensor:
        """(B, chunk_size, action_dim) actions for a normalized observation batch; sets `last_rate` (B,)."""
        self.eval()
        self._check_observation(batch)
        out = self.network(batch, sample=self.config.sample_latent_at_inference)
        self.last_rate = out.rate
        return out.actions

    @torch.no_grad()
    def select_action(self, batch: dict[str, Tensor], **kwargs: Any) -> Tensor:
        """One action per call, with the uncertainty of this step's observation in `last_step`.

        Every step encodes the observation (the rate needs it); chunks are decoded when the action queue
        runs out, or every step with temporal ensembling (`runtime.py` decides). A non-finite u, observation
        or action always stops (unknown means stop).
        """
        self.eval()
        batch_size = self._check_observation(batch)
        if self._batch_size is not None and batch_size != self._batch_size:
            raise ValueError(
                f"The batch size changed from {self._batch_size} to {batch_size} within an episode: the queued and "
                "ensembled actions belong to the old batch. Call `policy.reset()` when the environments are reset."
            )
        self._batch_size = batch_size
        if self.runtime.monitor is None:
            self._start_episode()
        obs_finite = torch.stack([torch.isfinite(batch[k]).flatten(1).all(dim=1) for k in self._used_inputs]).all(0)

        score = self._active_score
        planned: list[Tensor] = []

        def decode() -> Tensor:
            if planned:  # already decoded this step for the disagreement score
                return planned[0]
            if posterior is None:
                raise RuntimeError("A chunk must be planned but the observation was not encoded.")
            z = posterior.sample() if self.config.sample_latent_at_inference else posterior.mean
            planned.append(self.network.decode(z))
            return planned[0]

        if self._reuse_last_plan_uncertainty():
            posterior, rate, u, scores = None, self.last_step.rate, self.last_step.u, self.last_step.scores
            self._rate_map = self.last_step.rate_map
            self._embedding = self.last_step.embedding
        else:
            partners = {**self.config.calibration.and_gammas, **self.config.calibration.or_gammas}
            every = self.trace_all_scores or bool(partners)
            posterior, scores = self.observation_scores(batch, None if every else score)
            rate = scores["rate"]
            if score == "chunk_disagreement" or self.trace_all_scores or "chunk_disagreement" in partners:
                scores["chunk_disagreement"] = self._disagreement.update(decode())
            u = scores[score] / self.score_mean(score)

        monitor = self.runtime.monitor
        gamma, thresholds = self.stop.threshold(monitor, self._episode_step, u)
        in_force = gamma if thresholds is None else thresholds
        stop_u = self.stop.value(u, scores, in_force)
        action, decision = self.runtime.step(
            u, decode, lambda last: self._safety_action(batch, batch_size, last), unknown=~obs_finite, stop_u=stop_u
        )
        self.stop.advance(decision.stopped)
        self.stop.log_events(decision, stop_u, in_force, obs_finite, self._episode_step, monitor)
        self._episode_step += 1
        self.last_rate = rate
        self.last_step = UncertaintyStep(
            rate=rate,
            u=u,
            gamma=gamma,
            threshold_active=self.config.safety.enabled,
            stopped=decision.stopped,
            just_stopped=decision.just_stopped,
            resumed=decision.resumed,
            halted=decision.halted,
            score=score,
            scores=scores,
            rate_map=self._rate_map,
            embedding=self._embedding,
            thresholds=thresholds,
            stop_value=stop_u,
        )
        return action

    def threshold_in_force(self, step: int | None = None) -> dict[str, Any]:
        """The stop threshold in force and where it comes from, in one place: {"enabled", "gamma" (at episode
        step `step`, default the current one), "source"}. `safety.gamma: null` beside `calibration.gamma` means
        the calibrated one applies; this says so."""
        return {
            "enabled": self.config.safety.enabled,
            "gamma": self.stop_threshold(step),
            "source": threshold_source(self.config),
        }

    def resume(self, envs: Tensor | None = None, grace_steps: int = 0) -> Tensor:
        """Resume stopped or halted envs now, whatever u is: the explicit decision of an operator or a robot
        loop (e.g. after moving the arm by hand or removing what stopped it). `envs`: (B,) bool, default all.
        For `grace_steps` steps u > gamma does not stop them again, so the arm can move out of a pose it
        cannot judge; a non-finite step still stops them. Their plans start afresh. Returns the envs resumed."""
        if self.runtime.monitor is None:
            raise RuntimeError("Nothing to resume: the policy has not acted since `reset()`.")
        return self.runtime.resume(envs, grace_steps)

    def _reuse_last_plan_uncertainty(self) -> bool:
        """With `uncertainty_every_step=False`, steps served from the action queue skip the network."""
        return (
            not self.config.uncertainty_every_step
            and self.config.uncertainty_score != "chunk_disagreement"
            and not self.trace_all_scores
            and not self.config.calibration.and_gammas
            and not self.config.calibration.or_gammas
            and self.runtime.queued
            and self.last_step is not None
            and not self.runtime.any_stopped
        )

    def _encode(self, batch: dict[str, Tensor]) -> tuple[Posterior, Tensor]:
        network = self.network
        posterior = network.encode(batch)
        return posterior, network.rate(posterior)

    def observation_scores(
        self, batch: dict[str, Tensor], wanted: str | None = None
    ) -> tuple[Posterior, dict[str, Tensor]]:
        """One encoder pass: the posterior and the raw value (B,) of every observation score that is fitted
        ("rate" always), or with `wanted` only that one beside the rate (the per-step cost of `select_action`).
        The network computes them (its `observe`) from the fitted parts this policy keeps; the token network
        also leaves its rate map for `last_step.rate_map`."""
        keep = self.trace_all_scores
        if self.config.encoder == "tokens":
            seen = self.network.observe(batch, self.map_cell_mean, self.map_cell_std, self.embedding_rnd, wanted, keep)
        else:
            seen = self.network.observe(batch, self.state_embedding_mean, self.embedding_rnd, wanted, keep)
        self._rate_map, self._embedding = seen.rate_map, seen.embedding
        return seen.posterior, seen.scores

    def _safety_action(self, batch: dict[str, Tensor], batch_size: int, last_command: Tensor | None) -> Tensor:
        """What a stopped env emits, in the policy's normalized space (safety.py's `PolicySafetyAction`)."""
        safety = self.config.safety
        act = PolicySafetyAction(safety.action, safety.home_pose, safety.home_max_step, self.robot_units)
        halted = self.runtime.monitor.halted if self.runtime.monitor is not None else None
        return act(last_command, batch.get(OBS_STATE), halted, batch_size, self.config.device)

    # -------------------------------------------------------------------------------------------------- train

    def forward(self, batch: dict[str, Tensor], reduction: str = "mean") -> tuple[Tensor, dict[str, float]]:
        """Loss L = L1 + beta * R. `reduction="none"` returns the per-sample loss (LeRobot's sample weighting)."""
        batch_size = self._check_observation(batch)
        self._check_training_batch(batch, batch_size)
        out = self.network(batch, sample=self.training)

        abs_err = F.l1_loss(out.actions, batch[ACTION], reduction="none")
        if "action_is_pad" in batch:
            valid = (~batch["action_is_pad"]).unsqueeze(-1).to(abs_err.dtype)
        else:
            valid = torch.ones_like(abs_err[..., :1])
        n_valid = valid.expand_as(abs_err)
        rate = out.rate
        self.last_rate = rate.detach()
        if self.training:
            self.rate_tracker.update(rate)

        if reduction == "none":
            l1 = (abs_err * valid).sum((1, 2)) / n_valid.sum((1, 2)).clamp_min(1)
            loss = l1 + self.config.beta * rate
        elif reduction == "mean":
            l1 = (abs_err * valid).sum() / n_valid.sum().clamp_min(1)
            loss = l1 + self.config.beta * rate.mean()
        else:
            raise ValueError(f"`reduction` must be 'mean' or 'none', got {reduction!r}.")
        return loss, {"l1_loss": l1.mean().item(), "rate": rate.mean().item()}
