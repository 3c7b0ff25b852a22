"""Uncertainty scores of VIBPolicy besides the paper's rate, and the rate taken apart.

The encoder sums a camera path and a state path, e = e_img + e_state, and the posterior head is affine in e:
mu = W_mu e + b_mu, log sigma^2 = clamp(W_v e + b_v). Every score here reads that one encoder pass:

    rate                 R(e)                       the paper's rate over the fused state tokens (bottleneck.py)
    image_rate           R(e_img + mean(e_state))   the rate with the state path held at its training mean,
                                                    so only the camera can move it
    low_image_rate       1 / image_rate             high when the camera path carries *less* information
                                                    than on the training frames: a dark, covered or
                                                    featureless view widens the posterior towards the
                                                    marginal, which lowers the rate instead of raising it
    embedding_rnd        |g(x) - f(x)|^2            random network distillation on the policy's own
                                                    observation embedding x (FIPER's RND-OE): f fixed and
                                                    random, g fitted to f on the training frames
    chunk_disagreement   mean_a std_j c_j[t, a]     the spread of the overlapping chunks' candidates c_j for
                                                    the current step (normalized action units), a
                                                    deterministic cousin of FIPER's action-chunk entropy

Each is normalized by its mean over the training frames (u = s / s_bar), as the rate is. The rate splits
exactly, per token k and latent dimension d, into a mean term and a variance term:

    KL_kd = 1/2 (mu_kd - mu_m,d)^2 / sigma_m,d^2                                          (mean term)
          + 1/2 [log sigma_m,d^2 - log sigma_kd^2 + sigma_kd^2 / sigma_m,d^2 - 1]          (variance term)

`rate_terms` returns both per token, which `benchmarks/rate_decomposition.py` reports.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

import torch
from torch import Tensor, nn
from tqdm import tqdm

from .bottleneck import Posterior

SCORES = (
    "rate", "image_rate", "low_image_rate", "embedding_rnd", "chunk_disagreement", "state_rate", "map_score",
    "low_map_score", "abs_map_score",
)  # fmt: skip
# Scores only the token network (`--policy.encoder=tokens`) has: its rates are per token.
TOKEN_SCORES = ("state_rate", "map_score", "low_map_score", "abs_map_score")
# Scores that read the rate map's per-cell training statistics (calibration).
MAP_SCORES = ("map_score", "low_map_score", "abs_map_score")
RND_INPUTS = ("fused", "pooled")


@dataclass
class Observation:
    """What one encoder pass tells about an observation: each network's `observe` returns it."""

    posterior: Posterior
    scores: dict[str, Tensor]  # (B,) raw value of every score computed, by name ("rate" always)
    rate_map: Tensor | None = None  # (B, cameras, H', W') the image cells' rates (token network only)
    embedding: Tensor | None = None  # (B, D) what "embedding_rnd" reads, when asked to keep it


def map_score(
    cell_rates: Tensor, cell_mean: Tensor, cell_std: Tensor, top_k: int = 1, two_sided: bool = False
) -> Tensor:
    """The token network's map score (B,): each image cell's rate as a z-score against that cell's training
    statistics, reduced by the mean of the `top_k` largest (1: the maximum); with `two_sided`, of the largest
    |z|. A cell that shows what it never showed in training stands out even when the image's mean rate does
    not move."""
    z = (cell_rates - cell_mean.to(cell_rates)) / cell_std.to(cell_rates).clamp_min(1e-6)
    if two_sided:
        z = z.abs()
    return z.topk(min(top_k, z.shape[1]), dim=1).values.mean(dim=1)


def token_scores(
    token_rates: Tensor, n_1d_tokens: int, cell_mean: Tensor | None, cell_std: Tensor | None, top_k: int = 1
) -> dict[str, Tensor]:
    """The token network's rate-based scores, each (B,), from its per-token rates (B, N) (1D tokens first):

    rate            mean over all tokens (the paper's R)
    image_rate      mean over the image cells, exactly: no counterfactual state is needed
    low_image_rate  1 / image_rate
    state_rate      mean over the state tokens
    map_score       `map_score` over the cells, once their training statistics are known (calibration)
    low_map_score   `map_score` of the cells' negated z-scores: the cell whose rate fell furthest below
                    what it showed in training. A board in front of the camera hides what its cells
                    usually carry and lowers their rates (benchmarks/rate_map_pointing.py)
    abs_map_score   `map_score` of |z|: the cell that moved furthest from its training statistics, either way.
                    Which way a board moves the cells depends on the trunk and even on the training seed
                    (benchmarks/two_sided_map.py); this score does not need to know
    """
    scores = {"rate": token_rates.mean(dim=1)}
    cells = token_rates[:, n_1d_tokens:]
    if cells.shape[1]:
        scores["image_rate"] = cells.mean(dim=1)
        scores["low_image_rate"] = 1.0 / scores["image_rate"]
        if cell_mean is not None and torch.isfinite(cell_mean).all() and torch.isfinite(cell_std).all():
            scores["map_score"] = map_score(cells, cell_mean, cell_std, top_k)
            scores["low_map_score"] = map_score(-cells, -cell_mean, cell_std, top_k)
            scores["abs_map_score"] = map_score(cells, cell_mean, cell_std, top_k, two_sided=True)
    if n_1d_tokens:
        scores["state_rate"] = token_rates[:, :n_1d_tokens].mean(dim=1)
    return scores


def rate_terms(posterior: Posterior, marginal_mean: Tensor, marginal_logvar: Tensor) -> tuple[Tensor, Tensor]:
    """(mean term, variance term) of the KL per sample and token, each (B, K); their sum over K / K is R."""
    mean_term = 0.5 * ((posterior.mean - marginal_mean) ** 2 * torch.exp(-marginal_logvar)).sum(-1)
    var = torch.exp(posterior.logvar - marginal_logvar)
    var_term = 0.5 * (marginal_logvar - posterior.logvar + var - 1.0).sum(-1)
    return mean_term, var_term


class EmbeddingRND(nn.Module):
    """RND on an embedding vector: a fixed random MLP f and a predictor g with an extra layer (Burda et al.).

    The input is standardized with the training frames' mean and std (buffers), so that no embedding
    dimension's scale decides the error. `error_mean` / `error_std` are e's training statistics; NaN until
    `fit_embedding_rnd` ran.
    """

    def __init__(self, in_dim: int, hidden_dim: int = 256, out_dim: int = 64, seed: int = 0):
        super().__init__()
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            self.target = nn.Sequential(nn.Linear(in_dim, hidden_dim), nn.LeakyReLU(), nn.Linear(hidden_dim, out_dim))
            self.predictor = nn.Sequential(
                nn.Linear(in_dim, hidden_dim), nn.ReLU(), nn.Linear(hidden_dim, hidden_dim), nn.ReLU(),
                nn.Linear(hidden_dim, out_dim),
            )  # fmt: skip
        self.requires_grad_(False)  # only `fit_embedding_rnd` trains the predictor, never the policy's optimizer
        self.register_buffer("input_mean", torch.zeros(in_dim))
        self.register_buffer("input_std", torch.ones(in_dim))
        self.register_buffer("error_mean", torch.tensor(math.nan, dtype=torch.float64))
        self.register_buffer("error_std", torch.tensor(math.nan, dtype=torch.float64))

    @property
    def fitted(self) -> bool:
        return bool(torch.isfinite(self.error_mean)) and float(self.error_mean) > 0

    def error(self, x: Tensor) -> Tensor:
        """e(x) per sample, (B,)."""
        x = (x - self.input_mean) / self.input_std
        return (self.predictor(x) - self.target(x)).pow(2).mean(-1)


def fit_embedding_rnd(
    rnd: EmbeddingRND,
    embeddings: Tensor,
    steps: int = 3000,
    batch_size: int = 256,
    lr: float = 1e-3,
    seed: int = 0,
    progress: bool = False,
) -> list[float]:
    """Fit the predictor to the target on the training frames' embeddings (N, D), then set e's statistics
    over all of them (eval mode). Returns the loss per step; `progress` shows a bar (minutes on a CPU)."""
    if embeddings.ndim != 2 or embeddings.shape[0] < 2:
        raise ValueError(f"Need (N >= 2, D) training embeddings, got {tuple(embeddings.shape)}.")
    if not torch.isfinite(embeddings).all():
        raise ValueError("Training embeddings hold NaN or inf: check the dataset.")
    embeddings = embeddings.to(rnd.input_mean)
    rnd.input_mean.copy_(embeddings.mean(0))
    rnd.input_std.copy_(embeddings.std(0).clamp_min(1e-6))
    generator = torch.Generator().manual_seed(seed)
    params = list(rnd.predictor.parameters())
    for p in params:
        p.requires_grad_(True)
    optimizer = torch.optim.Adam(params, lr=lr)
    losses = []
    rnd.train()
    try:
        for _ in tqdm(range(steps), desc="fitting the RND score", unit="step", disable=not progress):
            idx = torch.randint(0, embeddings.shape[0], (min(batch_size, embeddings.shape[0]),), generator=generator)
            loss = rnd.error(embeddings[idx]).mean()
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
            losses.append(loss.item())
    finally:
        for p in params:
            p.requires_grad_(False)
        rnd.eval()
    with torch.no_grad():
        errors = torch.cat([rnd.error(chunk) for chunk in embeddings.split(4096)]).double()
    rnd.error_mean.fill_(float(errors.mean()))
    rnd.error_std.fill_(float(errors.std(unbiased=False)))
    return losses


class ChunkDisagreement:
    """Per-env history of predicted chunks; `update(chunk)` returns how much the chunks that overlap the
    current step disagree about it.

    The chunk predicted k steps ago proposes its action k for now. The score is the standard deviation across
    those candidates (at most `chunk_size`), averaged over action dimensions, in the policy's normalized
    action units. With a single candidate (the episode's first step) it is 0: no evidence yet.
    """

    def __init__(self, chunk_size: int):
        self.chunk_size = chunk_size
        self.reset()

    def reset(self) -> None:
        self._chunks: list[Tensor] = []

    def update(self, chunk: Tensor) -> Tensor:
        """chunk: (B, chunk_size, A) predicted at this step -> (B,) disagreement about this step's action."""
        if chunk.ndim != 3 or chunk.shape[1] != self.chunk_size:
            raise ValueError(f"Expected a (batch, {self.chunk_size}, action_dim) chunk, got {tuple(chunk.shape)}.")
        if self._chunks and self._chunks[-1].shape[0] != chunk.shape[0]:
            raise ValueError("The batch size changed without reset().")
        self._chunks.append(chunk)
        if len(self._chunks) > self.chunk_size:
            self._chunks.pop(0)
        n = len(self._chunks)
        candidates = torch.stack([c[:, n - 1 - i] for i, c in enumerate(self._chunks)], dim=1)  # (B, n, A)
        if n < 2:
            return torch.zeros(chunk.shape[0], dtype=chunk.dtype, device=chunk.device)
        return candidates.std(dim=1, unbiased=False).mean(-1)


def episode_disagreement(chunks: Iterable[Tensor], chunk_size: int) -> Tensor:
    """The disagreement score along one episode's frames in order, from the chunk predicted at each: (T,)."""
    tracker = ChunkDisagreement(chunk_size)
    return torch.cat([tracker.update(c.unsqueeze(0)) for c in chunks])


def score_statistics(values: Tensor) -> tuple[float, float]:
    """(mean, std) of a score over training frames, refusing non-finite or non-positive means."""
    values = values.double()
    if not torch.isfinite(values).all():
        raise ValueError("A score is not finite on some training frames.")
    mean = float(values.mean())
    if not mean > 0:
        raise ValueError(f"A score's mean over the training frames is {mean}; it cannot normalize u.")
    return mean, float(values.std(unbiased=False))
