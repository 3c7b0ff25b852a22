"""The pooled network (`--policy.encoder=pooled`): the paper's Fig. 2 as drawn (Sec. III-D).

    encoder p(z|s):  ResNet trunk per camera (shared) -> pooled -> MLP  ┐
                     observation.state -> MLP                         ├─ sum -> split into K state tokens
                     observation.environment_state -> MLP              ┘        -> Gaussian posterior per token
    marginal m(z):   learnable N(mu_m, sigma_m^2), shared by the tokens
    rate R(s):       mean_k sum_d KL(p(z_kd|s) || m(z_d))                       (bottleneck.py)
    decoder q(a|z):  encoder-only transformer over [proj(z_1..z_K); chunk_size learnable action queries]
                     -> the action-query outputs -> linear head -> (chunk_size, action_dim)

No CVAE, no cross-attention decoder, no autoregression; the transformer layers are LeRobot's ACT layers. The
camera reaches the tokens only through the pooled features (spatial-softmax keypoints by default), summed with
the state's projection, so no token belongs to a place in the image (token_network.py has one per cell).
"""

from __future__ import annotations

from dataclasses import dataclass
from types import SimpleNamespace

import torch
from lerobot.policies.act.modeling_act import ACTEncoder, create_sinusoidal_pos_embedding
from lerobot.policies.diffusion.modeling_diffusion import SpatialSoftmax
from lerobot.utils.constants import OBS_ENV_STATE, OBS_STATE
from torch import Tensor, nn

from .backbone import build_encoder_trunk
from .bottleneck import GaussianBottleneck, Posterior, VIBOutput
from .configuration_vib import VIBConfig
from .scores import EmbeddingRND, Observation


def _mlp(in_dim: int, hidden_dim: int, out_dim: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(in_dim, hidden_dim), nn.ReLU(), nn.Linear(hidden_dim, out_dim))


@dataclass
class EncoderParts:
    """The fused feature's summands, (B, K * d_token) each, and the cameras' pooled features side by side."""

    image: Tensor | None  # the camera path: the sum of the cameras' projections
    state: Tensor | None  # the state path: robot state and environment state projections
    pooled: Tensor | None  # (B, n_cameras * pooled_dim), before projection

    @property
    def fused(self) -> Tensor:
        return torch.stack([p for p in (self.image, self.state) if p is not None]).sum(0)


class KeypointsAndMean(nn.Module):
    """Spatial-softmax keypoints (where features are) beside the feature map's channel means (how strongly
    they are present). Keypoints alone are invariant to the map's overall level: a black or washed-out image
    yields keypoints near the map's centre, which the rate cannot tell from an ordinary frame."""

    def __init__(self, keypoints: nn.Module):
        super().__init__()
        self.keypoints = keypoints

    def forward(self, feature_map: Tensor) -> Tensor:
        return torch.cat([self.keypoints(feature_map).flatten(1), feature_map.mean(dim=(2, 3))], dim=1)


class ObservationEncoder(nn.Module):
    """s -> fused feature of size K * d_token: per-modality projections summed (paper Fig. 2)."""

    def __init__(self, config: VIBConfig):
        super().__init__()
        self.config = config
        self.camera_keys = list(config.image_features)
        fused_dim = config.n_state_tokens * config.d_token
        self.pooled_dim = 0
        if self.camera_keys:
            self.backbone, channels = build_encoder_trunk(config)
            image_shape = tuple(config.image_features[self.camera_keys[0]].shape)
            with torch.no_grad():  # in eval mode: a probe must not touch batch-norm statistics
                feature_map_shape = tuple(self.backbone.eval()(torch.zeros(1, *image_shape))["feature_map"].shape[1:])
            self.backbone.train()
            n_kp = config.spatial_softmax_num_keypoints
            if config.image_pooling == "spatial_softmax":
                self.pool = SpatialSoftmax(feature_map_shape, num_kp=n_kp)
                pooled_dim = 2 * n_kp
            elif config.image_pooling == "spatial_softmax_avg":
                self.pool = KeypointsAndMean(SpatialSoftmax(feature_map_shape, num_kp=n_kp))
                pooled_dim = 2 * n_kp + channels
            else:
                self.pool = nn.AdaptiveAvgPool2d(1)
                pooled_dim = channels
            self.pooled_dim = pooled_dim * len(self.camera_keys)
            # One projection per camera so that the sum still tells the cameras apart.
            self.camera_proj = nn.ModuleList(
                _mlp(pooled_dim, config.mlp_hidden_dim, fused_dim) for _ in self.camera_keys
            )
        if config.robot_state_feature:
            self.state_proj = _mlp(config.robot_state_feature.shape[0], config.mlp_hidden_dim, fused_dim)
        if config.env_state_feature:
            self.env_state_proj = _mlp(config.env_state_feature.shape[0], config.mlp_hidden_dim, fused_dim)

    def parts(self, batch: dict[str, Tensor]) -> EncoderParts:
        """The two paths of the fused feature, before they are summed, and the cameras' pooled features."""
        image = state = pooled_all = None
        if self.camera_keys:
            images = torch.cat([batch[key] for key in self.camera_keys])  # one trunk pass for all cameras
            pooled = self.pool(self.backbone(images)["feature_map"]).flatten(1)
            per_camera = pooled.chunk(len(self.camera_keys))
            image = torch.stack([proj(p) for p, proj in zip(per_camera, self.camera_proj, strict=True)]).sum(0)
            pooled_all = torch.cat(per_camera, dim=1)
        states = []
        if self.config.robot_state_feature:
            states.append(self.state_proj(batch[OBS_STATE]))
        if self.config.env_state_feature:
            states.append(self.env_state_proj(batch[OBS_ENV_STATE]))
        if states:
            state = torch.stack(states).sum(0)
        return EncoderParts(image=image, state=state, pooled=pooled_all)

    def forward(self, batch: dict[str, Tensor]) -> Tensor:
        return self.parts(batch).fused


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


class PooledNetwork(nn.Module):
    """The network: encoder, bottleneck (posterior heads + marginal), decoder."""

    def __init__(self, config: VIBConfig):
        super().__init__()
        self.config = config
        self.encoder = ObservationEncoder(config)
        self.bottleneck = GaussianBottleneck(
            config.d_token, config.latent_dim, logvar_init=config.posterior_logvar_init
        )
        self.decoder = ActionDecoder(config)

    def encode(self, batch: dict[str, Tensor]) -> Posterior:
        return self.posterior_of(self.encoder(batch))

    def posterior_of(self, fused: Tensor) -> Posterior:
        """The state tokens' posterior for a fused feature (B, K * d_token)."""
        tokens = fused.view(fused.shape[0], self.config.n_state_tokens, self.config.d_token)
        return self.bottleneck.posterior(tokens)

    def rate(self, posterior: Posterior) -> Tensor:
        return self.bottleneck.rate(posterior)

    def decode(self, z: Tensor) -> Tensor:
        return self.decoder(z)

    def rnd_embedding(self, parts: EncoderParts, batch: dict[str, Tensor]) -> Tensor:
        """The embedding that "embedding_rnd" reads (`config.rnd_input`)."""
        if self.config.rnd_input == "fused":
            return parts.fused
        pieces = [p for p in (parts.pooled, batch.get(OBS_STATE) if self.config.robot_state_feature else None)]
        return torch.cat([p for p in pieces if p is not None], dim=1)

    def observe(
        self,
        batch: dict[str, Tensor],
        state_embedding_mean: Tensor,
        rnd: EmbeddingRND,
        wanted: str | None = None,
        keep_embedding: bool = False,
    ) -> Observation:
        """One encoder pass and the scores of scores.py: every fitted one, or with `wanted` that one beside the
        rate. The image path's scores read `state_embedding_mean`, the state path's training mean (NaN until
        calibrated); the RND is read only when it is fitted and wanted."""
        parts = self.encoder.parts(batch)
        posterior = self.posterior_of(parts.fused)
        scores = {"rate": self.bottleneck.rate(posterior)}
        if parts.image is not None and wanted in (None, "image_rate", "low_image_rate"):
            if parts.state is None:
                scores["image_rate"] = scores["rate"]
            elif torch.isfinite(state_embedding_mean).all():
                held = parts.image + state_embedding_mean.to(parts.image)
                scores["image_rate"] = self.bottleneck.rate(self.posterior_of(held))
        if "image_rate" in scores:
            scores["low_image_rate"] = 1.0 / scores["image_rate"]
        rnd_wanted = rnd.fitted and wanted in (None, "embedding_rnd")
        embedding = self.rnd_embedding(parts, batch) if rnd_wanted or keep_embedding else None
        if rnd_wanted:
            scores["embedding_rnd"] = rnd.error(embedding)
        return Observation(posterior, scores, None, embedding if keep_embedding else None)

    def forward(self, batch: dict[str, Tensor], sample: bool) -> VIBOutput:
        posterior = self.encode(batch)
        z = posterior.sample() if sample else posterior.mean
        return VIBOutput(self.decoder(z), posterior, self.bottleneck.rate(posterior))
