"""VIBPolicy: ACT-style action chunking through a Variational Information Bottleneck (paper Sec. III-D).

    encoder p(z|s):  ResNet trunk per camera (shared) -> pooled -> MLP  ┐
                     observation.state -> MLP                         ├─ sum -> split into K state tokens
                     observation.environment_state -> MLP              ┘        -> Gaussian posterior per token
    marginal m(z):   learnable N(mu_m, sigma_m^2), shared by the tokens
    rate R(s):       mean_k sum_d KL(p(z_kd|s) || m(z_d))                       (bottleneck.py)
    decoder q(a|z):  encoder-only transformer over [proj(z_1..z_K); chunk_size learnable action queries]
                     -> the action-query outputs -> linear head -> (chunk_size, action_dim)
    loss:            L1(actions, non-padded steps) + beta * mean(R)

No CVAE, no cross-attention decoder, no autoregression. Transformer layers are LeRobot's ACT layers.
"""

from __future__ import annotations

import contextlib
import contextvars
import logging
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import torch
import torch.nn.functional as F
import torchvision
from huggingface_hub import ModelCard
from lerobot.policies.act.modeling_act import ACTEncoder, create_sinusoidal_pos_embedding
from lerobot.policies.diffusion.modeling_diffusion import SpatialSoftmax
from lerobot.policies.pretrained import PreTrainedPolicy
from lerobot.utils.constants import ACTION, OBS_ENV_STATE, OBS_STATE
from torch import Tensor, nn
from torchvision.models._utils import IntermediateLayerGetter
from torchvision.ops.misc import FrozenBatchNorm2d

from .bottleneck import GaussianBottleneck, Posterior
from .configuration_vib import VIBConfig

logger = logging.getLogger(__name__)

MODEL_CARD_INTRO = """\
**VIB** (Variational Information Bottleneck) is an ACT-style action-chunking policy whose observation \
encoding passes through an Information Bottleneck; its *rate*, KL(p(z|s) || m(z)), is an epistemic-uncertainty \
score available at run time (Uncertainty-Guided Robotic Manipulation Through Variational Information \
Bottleneck in Imitation Learning, VIB-ILCtrl).

The policy type comes from the LeRobot plugin `lerobot_policy_vib`: install it next to LeRobot \
(`pip install lerobot_policy_vib`) before `lerobot-eval` / `lerobot-rollout` / `--policy.path=...` can load it."""

# Set while `from_pretrained` builds the model: the checkpoint overwrites the backbone, so fetching
# ImageNet weights first would only fail offline for nothing.
_SKIP_PRETRAINED_BACKBONE: contextvars.ContextVar[bool] = contextvars.ContextVar(
    "vib_skip_pretrained_backbone", default=False
)


@contextlib.contextmanager
def _skip_pretrained_backbone() -> Iterator[None]:
    token = _SKIP_PRETRAINED_BACKBONE.set(True)
    try:
        yield
    finally:
        _SKIP_PRETRAINED_BACKBONE.reset(token)


def build_resnet_trunk(config: VIBConfig) -> tuple[nn.Module, int]:
    """ACT's image trunk: a torchvision ResNet up to layer4, frozen batch norm. Returns (trunk, channels)."""
    weights = None if _SKIP_PRETRAINED_BACKBONE.get() else config.pretrained_backbone_weights
    try:
        resnet = getattr(torchvision.models, config.vision_backbone)(
            replace_stride_with_dilation=[False, False, config.replace_final_stride_with_dilation],
            weights=weights,
            norm_layer=FrozenBatchNorm2d,
        )
    except OSError as e:  # URLError, connection errors: the weights are neither cached nor downloadable
        raise RuntimeError(
            f"Could not load the pretrained backbone weights {weights!r} for {config.vision_backbone} "
            f"({type(e).__name__}: {e}). They are downloaded by torchvision into the torch hub cache on first "
            "use; offline, train the backbone from scratch with `--policy.pretrained_backbone_weights=null` "
            "(or put the weights file in $TORCH_HOME/hub/checkpoints)."
        ) from e
    trunk = IntermediateLayerGetter(resnet, return_layers={"layer4": "feature_map"})
    return trunk, resnet.fc.in_features


def _mlp(in_dim: int, hidden_dim: int, out_dim: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(in_dim, hidden_dim), nn.ReLU(), nn.Linear(hidden_dim, out_dim))


class ObservationEncoder(nn.Module):
    """s -> fused feature of size K * d_token: per-modality projections summed (paper Fig. 2)."""

    def __init__(self, config: VIBConfig):
        super().__init__()
        self.config = config
        self.camera_keys = list(config.image_features)
        fused_dim = config.n_state_tokens * config.d_token
        if self.camera_keys:
            self.backbone, channels = build_resnet_trunk(config)
            image_shape = tuple(config.image_features[self.camera_keys[0]].shape)
            with torch.no_grad():
                feature_map_shape = tuple(self.backbone(torch.zeros(1, *image_shape))["feature_map"].shape[1:])
            if config.image_pooling == "spatial_softmax":
                self.pool = SpatialSoftmax(feature_map_shape, num_kp=config.spatial_softmax_num_keypoints)
                pooled_dim = 2 * config.spatial_softmax_num_keypoints
            else:
                self.pool = nn.AdaptiveAvgPool2d(1)
                pooled_dim = channels
            # One projection per camera so that the sum still tells the cameras apart.
            self.camera_proj = nn.ModuleList(
                _mlp(pooled_dim, config.mlp_hidden_dim, fused_dim) for _ in self.camera_keys
            )
        if config.robot_state_feature:
            self.state_proj = _mlp(config.robot_state_feature.shape[0], config.mlp_hidden_dim, fused_dim)
        if config.env_state_feature:
            self.env_state_proj = _mlp(config.env_state_feature.shape[0], config.mlp_hidden_dim, fused_dim)

    def forward(self, batch: dict[str, Tensor]) -> Tensor:
        parts = []
        if self.camera_keys:
            images = torch.cat([batch[key] for key in self.camera_keys])  # one trunk pass for all cameras
            pooled = self.pool(self.backbone(images)["feature_map"]).flatten(1)
            for pooled_cam, proj in zip(pooled.chunk(len(self.camera_keys)), self.camera_proj, strict=True):
                parts.append(proj(pooled_cam))
        if self.config.robot_state_feature:
            parts.append(self.state_proj(batch[OBS_STATE]))
        if self.config.env_state_feature:
            parts.append(self.env_state_proj(batch[OBS_ENV_STATE]))
        return torch.stack(parts).sum(0)


class ActionDecoder(nn.Module):
    """q(a|z): encoder-only transformer over [proj(z); learnable action queries] -> action chunk."""

    def __init__(self, config: VIBConfig):
        super().__init__()
        self.n_tokens = config.n_state_tokens
        self.latent_proj = nn.Linear(config.latent_dim, config.dim_model)
        self.action_queries = nn.Embedding(config.chunk_size, config.dim_model)
        n_positions = config.n_state_tokens + config.chunk_size
        if config.position_embedding == "learned":
            self.pos_embed = nn.Embedding(n_positions, config.dim_model)
        else:
            self.register_buffer("sinusoidal_pos_embed", create_sinusoidal_pos_embedding(n_positions, config.dim_model))
        # ACTEncoder reads its sizes off an ACTConfig-like object.
        self.transformer = ACTEncoder(
            SimpleNamespace(
                n_encoder_layers=config.n_layers,
                dim_model=config.dim_model,
                n_heads=config.n_heads,
                dim_feedforward=config.dim_feedforward,
                dropout=config.dropout,
                feedforward_activation=config.feedforward_activation,
                pre_norm=config.pre_norm,
            )
        )
        self.action_head = nn.Linear(config.dim_model, config.action_feature.shape[0])
        for p in self.transformer.parameters():  # ACT's initialization
            if p.dim() > 1:
                nn.init.xavier_uniform_(p)

    def position_embedding(self) -> Tensor:
        return self.pos_embed.weight if hasattr(self, "pos_embed") else self.sinusoidal_pos_embed

    def forward(self, z: Tensor) -> Tensor:
        """z: (B, K, latent_dim) -> actions (B, chunk_size, action_dim)."""
        batch_size = z.shape[0]
        tokens = torch.cat(
            [self.latent_proj(z), self.action_queries.weight.unsqueeze(0).expand(batch_size, -1, -1)], dim=1
        )
        # ACT's layers are sequence-first.
        out = self.transformer(tokens.transpose(0, 1), pos_embed=self.position_embedding().unsqueeze(1))
        return self.action_head(out[self.n_tokens :].transpose(0, 1))


@dataclass
class VIBOutput:
    actions: Tensor  # (B, chunk_size, action_dim)
    posterior: Posterior  # (B, K, latent_dim) each
    rate: Tensor  # (B,)


class VIB(nn.Module):
    """The network: encoder, bottleneck (posterior heads + marginal), decoder."""

    def __init__(self, config: VIBConfig):
        super().__init__()
        self.config = config
        self.encoder = ObservationEncoder(config)
        self.bottleneck = GaussianBottleneck(config.d_token, config.latent_dim)
        self.decoder = ActionDecoder(config)

    def encode(self, batch: dict[str, Tensor]) -> Posterior:
        fused = self.encoder(batch)
        tokens = fused.view(fused.shape[0], self.config.n_state_tokens, self.config.d_token)
        return self.bottleneck.posterior(tokens)

    def forward(self, batch: dict[str, Tensor], sample: bool) -> VIBOutput:
        posterior = self.encode(batch)
        z = posterior.sample() if sample else posterior.mean
        return VIBOutput(self.decoder(z), posterior, self.bottleneck.rate(posterior))


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
        self.model = VIB(config)
        self.last_rate: Tensor | None = None
        self.reset()

    @classmethod
    def from_pretrained(cls, pretrained_name_or_path: str | Path, **kwargs: Any) -> VIBPolicy:
        with _skip_pretrained_backbone():
            return super().from_pretrained(pretrained_name_or_path, **kwargs)

    def generate_model_card(self, *args: Any, **kwargs: Any) -> ModelCard:
        """LeRobot's card, with what the policy is and the plugin it needs to load."""
        card = super().generate_model_card(*args, **kwargs)
        generic = f"This is a **{self.name}** policy trained with [LeRobot](https://github.com/huggingface/lerobot)."
        if generic in card.text:
            card.text = card.text.replace(generic, MODEL_CARD_INTRO)
        else:
            card.text = MODEL_CARD_INTRO + "\n\n" + card.text
        card.data.tags = sorted(set(card.data.tags or []) | {"vib", "uncertainty"})
        return card

    def get_optim_params(self) -> list[dict]:
        backbone, rest = [], []
        for name, p in self.named_parameters():
            if p.requires_grad:
                (backbone if name.startswith("model.encoder.backbone") else rest).append(p)
        return [{"params": rest}, {"params": backbone, "lr": self.config.optimizer_lr_backbone}]

    def reset(self) -> None:
        """Call whenever the environment is reset."""
        self._action_queue: deque[Tensor] = deque(maxlen=self.config.n_action_steps)

    # ---------------------------------------------------------------------------------------------- input checks

    def _check_observation(self, batch: dict[str, Tensor]) -> int:
        """Raise a clear error for a missing key or a wrong shape; return the batch size."""
        expected = self._used_inputs
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
            if tuple(value.shape[1:]) != tuple(ft.shape):
                raise ValueError(
                    f"`{key}` has shape {tuple(value.shape)}; expected (batch, {', '.join(map(str, ft.shape))}) "
                    "as configured. Check the camera resolution / state size against the training data."
                )
            if batch_size is None:
                batch_size = value.shape[0]
            elif value.shape[0] != batch_size:
                raise ValueError(f"`{key}` has batch size {value.shape[0]}, other inputs have {batch_size}.")
        return int(batch_size)

    def _check_training_batch(self, batch: dict[str, Tensor], batch_size: int) -> None:
        if ACTION not in batch:
            raise KeyError(f"Training batch is missing `{ACTION}`.")
        expected = (batch_size, self.config.chunk_size, self.config.action_feature.shape[0])
        if tuple(batch[ACTION].shape) != expected:
            raise ValueError(
                f"`{ACTION}` has shape {tuple(batch[ACTION].shape)}; expected {expected} "
                "(batch, chunk_size, action_dim). Is the dataset loaded with `action_delta_indices`?"
            )
        for key in [*self._used_inputs, ACTION]:
            if key in batch and not torch.isfinite(batch[key]).all():
                raise ValueError(f"Training batch has non-finite values (NaN or inf) in `{key}`.")

    # --------------------------------------------------------------------------------------------- inference

    @torch.no_grad()
    def predict_action_chunk(self, batch: dict[str, Tensor], **kwargs: Any) -> Tensor:
        """(B, chunk_size, action_dim) actions for a normalized observation batch; sets `last_rate` (B,)."""
        self.eval()
        self._check_observation(batch)
        out = self.model(batch, sample=self.config.sample_latent_at_inference)
        self.last_rate = out.rate
        return out.actions

    @torch.no_grad()
    def select_action(self, batch: dict[str, Tensor], **kwargs: Any) -> Tensor:
        """One action per call; a new chunk is predicted when the queue of `n_action_steps` runs out."""
        self.eval()
        if len(self._action_queue) == 0:
            actions = self.predict_action_chunk(batch)[:, : self.config.n_action_steps]
            self._action_queue.extend(actions.transpose(0, 1))
        return self._action_queue.popleft()

    # -------------------------------------------------------------------------------------------------- train

    def forward(self, batch: dict[str, Tensor], reduction: str = "mean") -> tuple[Tensor, dict[str, float]]:
        """Loss L = L1 + beta * R. `reduction="none"` returns the per-sample loss (LeRobot's sample weighting)."""
        batch_size = self._check_observation(batch)
        self._check_training_batch(batch, batch_size)
        out = self.model(batch, sample=self.training)

        abs_err = F.l1_loss(out.actions, batch[ACTION], reduction="none")
        if "action_is_pad" in batch:
            valid = (~batch["action_is_pad"]).unsqueeze(-1).to(abs_err.dtype)
        else:
            valid = torch.ones_like(abs_err[..., :1])
        n_valid = valid.expand_as(abs_err)
        rate = out.rate
        self.last_rate = rate.detach()

        if reduction == "none":
            l1 = (abs_err * valid).sum((1, 2)) / n_valid.sum((1, 2)).clamp_min(1)
            loss = l1 + self.config.beta * rate
        elif reduction == "mean":
            l1 = (abs_err * valid).sum() / n_valid.sum().clamp_min(1)
            loss = l1 + self.config.beta * rate.mean()
        else:
            raise ValueError(f"`reduction` must be 'mean' or 'none', got {reduction!r}.")
        return loss, {"l1_loss": l1.mean().item(), "rate": rate.mean().item()}
