"""The token network (`--policy.encoder=tokens`): ACT's own token memory with a bottleneck on every token.

    image tokens   x_c,ij = Conv1x1(trunk(image_c))[:, i, j]      one per cell of camera c's feature map
    state token    x_s    = Linear(observation.state)
    env token      x_e    = Linear(observation.environment_state)

Every token n gets a diagonal Gaussian posterior after its input projection and before ACT's encoder,

    q(z_n | s) = N(mu_n, diag sigma_n^2),    (mu_n, log sigma_n^2) = Linear_type(n)(x_n),

with a learnable marginal m per token type (image, state, env; with `token_marginal=cell`, one per image
cell), so each token's rate r_n = sum_d KL(q(z_nd | s) || m_nd) belongs to that token alone. The paper's R is
the mean of r_n over the N tokens and enters the loss as L1 + beta R. z (a sample in training, the posterior
mean at evaluation) is lifted back to `dim_model` by one linear map and read by ACT's encoder with ACT's
position embeddings (learned for the 1D tokens, the 2D sinusoid for the cells); ACT's decoder turns
`chunk_size` learned action queries into the chunk by cross-attention. No CVAE: the action chunk is not
encoded at training time.

Because an image token's rate is its cell's, the image rates form a map over each camera's image:
`rate_map`, (B, cameras, H', W'), H' x W' the trunk's feature map (12 x 16 for a layer2 trunk at 96 x 128).

LeRobot's ACT modules are reused as they are: `ACTEncoder`, `ACTDecoder`, `ACTSinusoidalPositionEmbedding2d`.
"""

from __future__ import annotations

from types import SimpleNamespace

import torch
from lerobot.policies.act.modeling_act import ACTDecoder, ACTEncoder, ACTSinusoidalPositionEmbedding2d
from lerobot.utils.constants import OBS_ENV_STATE, OBS_STATE
from torch import Tensor, nn

from .backbone import build_encoder_trunk
from .bottleneck import GaussianBottleneck, Posterior, VIBOutput
from .scores import EmbeddingRND, Observation, token_scores


class TokenNetwork(nn.Module):
    """Tokens -> per-token posteriors -> ACT's encoder and decoder -> action chunk.

    Token order: the robot state, the environment state (each if present), then each camera's cells row by
    row. `n_1d_tokens` counts the first kind, `map_shape` = (cameras, H', W') the second.
    """

    def __init__(self, config):
        super().__init__()
        self.config = config
        d = config.dim_model
        self.camera_keys = list(config.image_features)
        self.one_d_keys = [k for k, ft in ((OBS_STATE, config.robot_state_feature),
                                           (OBS_ENV_STATE, config.env_state_feature)) if ft]  # fmt: skip
        self.n_1d_tokens = len(self.one_d_keys)
        self.map_shape: tuple[int, int, int] = (0, 0, 0)
        if self.camera_keys:
            self.backbone, channels = build_encoder_trunk(config)
            self.image_proj = nn.Conv2d(channels, d, kernel_size=1)
            image_shape = tuple(config.image_features[self.camera_keys[0]].shape)
            with torch.no_grad():  # in eval mode: a probe must not touch batch-norm statistics
                feature_map = self.backbone.eval()(torch.zeros(1, *image_shape))["feature_map"]
            self.backbone.train()
            height, width = feature_map.shape[2:]
            self.map_shape = (len(self.camera_keys), height, width)
            # ACT's 2D sinusoid depends only on the map's size: computed once, never saved
            cell_pos = ACTSinusoidalPositionEmbedding2d(d // 2)(torch.zeros(1, d, height, width))
            cell_pos = cell_pos.flatten(2)[0].transpose(0, 1)  # (H' W', d), row by row as the tokens
            self.register_buffer("cell_pos_embed", cell_pos.repeat(len(self.camera_keys), 1), persistent=False)
            n_cells = self.n_cells
            self.image_bottleneck = GaussianBottleneck(
                d,
                config.latent_dim,
                n_marginals=n_cells if config.token_marginal == "cell" else 1,
                logvar_init=config.posterior_logvar_init,
            )
        self.one_d_proj = nn.ModuleDict(
            {_name(k): nn.Linear(getattr(config, _feature(k)).shape[0], d) for k in self.one_d_keys}
        )
        self.one_d_bottleneck = nn.ModuleDict(
            {
                _name(k): GaussianBottleneck(d, config.latent_dim, logvar_init=config.posterior_logvar_init)
                for k in self.one_d_keys
            }
        )
        if self.one_d_keys:
            self.one_d_pos_embed = nn.Embedding(self.n_1d_tokens, d)
        self.latent_proj = nn.Linear(config.latent_dim, d)
        act_sizes = SimpleNamespace(
            n_encoder_layers=config.n_layers,
            n_decoder_layers=config.n_decoder_layers,
            dim_model=d,
            n_heads=config.n_heads,
            dim_feedforward=config.dim_feedforward,
            dropout=config.dropout,
            feedforward_activation=config.feedforward_activation,
            pre_norm=config.pre_norm,
        )
        self.encoder = ACTEncoder(act_sizes)
        self.decoder = ACTDecoder(act_sizes)
        self.action_queries = nn.Embedding(config.chunk_size, d)  # ACT's decoder position embedding
        self.action_head = nn.Linear(d, config.action_feature.shape[0])
        for module in (self.encoder, self.decoder):  # ACT's initialization
            for p in module.parameters():
                if p.dim() > 1:
                    nn.init.xavier_uniform_(p)

    @property
    def n_cells(self) -> int:
        cameras, height, width = self.map_shape
        return cameras * height * width

    @property
    def n_tokens(self) -> int:
        return self.n_1d_tokens + self.n_cells

    # ------------------------------------------------------------------------------------------ encoder

    def encode(self, batch: dict[str, Tensor]) -> Posterior:
        """Every token's posterior, (B, N, latent_dim) each, in token order."""
        means, logvars = [], []
        for key in self.one_d_keys:
            x = self.one_d_proj[_name(key)](batch[key]).unsqueeze(1)  # (B, 1, d)
            p = self.one_d_bottleneck[_name(key)].posterior(x)
            means.append(p.mean)
            logvars.append(p.logvar)
        if self.camera_keys:
            images = torch.cat([batch[key] for key in self.camera_keys])  # one trunk pass for all cameras
            cells = self.image_proj(self.backbone(images)["feature_map"]).flatten(2).transpose(1, 2)
            cells = torch.cat(cells.chunk(len(self.camera_keys)), dim=1)  # (B, cameras H' W', d)
            p = self.image_bottleneck.posterior(cells)
            means.append(p.mean)
            logvars.append(p.logvar)
        return Posterior(mean=torch.cat(means, dim=1), logvar=torch.cat(logvars, dim=1))

    def token_rates(self, posterior: Posterior) -> Tensor:
        """(B, N): each token's KL against its own marginal, summed over latent dims."""
        rates = []
        for i, key in enumerate(self.one_d_keys):
            one = Posterior(posterior.mean[:, i : i + 1], posterior.logvar[:, i : i + 1])
            rates.append(self.one_d_bottleneck[_name(key)].token_rates(one))
        if self.camera_keys:
            cells = Posterior(posterior.mean[:, self.n_1d_tokens :], posterior.logvar[:, self.n_1d_tokens :])
            rates.append(self.image_bottleneck.token_rates(cells))
        return torch.cat(rates, dim=1)

    def rate(self, posterior: Posterior) -> Tensor:
        """The paper's R per sample (B,): the mean of the token rates."""
        return self.token_rates(posterior).mean(dim=1)

    def rate_map(self, token_rates: Tensor) -> Tensor | None:
        """The image tokens' rates laid out over the images: (B, cameras, H', W'), None without a camera."""
        if not self.camera_keys:
            return None
        return token_rates[:, self.n_1d_tokens :].reshape(token_rates.shape[0], *self.map_shape)

    def embedding(self, posterior: Posterior) -> Tensor:
        """The observation embedding "embedding_rnd" reads: the 1D tokens' posterior means and the image
        tokens' mean posterior mean, side by side, (B, (n_1d + 1) * latent_dim) (without camera: n_1d)."""
        pieces = [posterior.mean[:, : self.n_1d_tokens].flatten(1)]
        if self.camera_keys:
            pieces.append(posterior.mean[:, self.n_1d_tokens :].mean(dim=1))
        return torch.cat(pieces, dim=1)

    @property
    def embedding_dim(self) -> int:
        return (self.n_1d_tokens + (1 if self.camera_keys else 0)) * self.config.latent_dim

    def observe(
        self,
        batch: dict[str, Tensor],
        cell_mean: Tensor,
        cell_std: Tensor,
        rnd: EmbeddingRND,
        wanted: str | None = None,
        keep_embedding: bool = False,
    ) -> Observation:
        """One encoder pass and the scores of scores.py: every fitted one, or with `wanted` that one beside
        the token rates' (the RND only when it is fitted and wanted). `cell_mean` / `cell_std`: the cells'
        training statistics of the map scores (NaN until calibrated)."""
        posterior = self.encode(batch)
        token_rates = self.token_rates(posterior)
        scores = token_scores(token_rates, self.n_1d_tokens, cell_mean, cell_std, self.config.map_top_k)
        rnd_wanted = rnd.fitted and wanted in (None, "embedding_rnd")
        embedding = self.embedding(posterior) if rnd_wanted or keep_embedding else None
        if rnd_wanted:
            scores["embedding_rnd"] = rnd.error(embedding)
        return Observation(posterior, scores, self.rate_map(token_rates), embedding if keep_embedding else None)

    # ------------------------------------------------------------------------------------------ decoder

    def position_embedding(self) -> Tensor:
        """(N, dim_model), in token order."""
        pieces = [self.one_d_pos_embed.weight] if self.one_d_keys else []
        if self.camera_keys:
            pieces.append(self.cell_pos_embed)
        return torch.cat(pieces, dim=0)

    def decode(self, z: Tensor) -> Tensor:
        """z: (B, N, latent_dim) -> actions (B, chunk_size, action_dim)."""
        batch_size = z.shape[0]
        pos = self.position_embedding().unsqueeze(1).to(z.dtype)  # (N, 1, d): ACT's layers are sequence-first
        memory = self.encoder(self.latent_proj(z).transpose(0, 1), pos_embed=pos)
        queries = torch.zeros(self.config.chunk_size, batch_size, self.config.dim_model, dtype=z.dtype, device=z.device)
        out = self.decoder(
            queries, memory, encoder_pos_embed=pos, decoder_pos_embed=self.action_queries.weight.unsqueeze(1)
        )
        return self.action_head(out.transpose(0, 1))

    def forward(self, batch: dict[str, Tensor], sample: bool) -> VIBOutput:
        posterior = self.encode(batch)
        z = posterior.sample() if sample else posterior.mean
        token_rates = self.token_rates(posterior)
        return VIBOutput(self.decode(z), posterior, token_rates.mean(dim=1), token_rates=token_rates)


def _name(key: str) -> str:
    """A module name for an input key (ModuleDict names cannot hold dots)."""
    return key.rsplit(".", 1)[-1]


def _feature(key: str) -> str:
    return "robot_state_feature" if key == OBS_STATE else "env_state_feature"
