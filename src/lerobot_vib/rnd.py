"""Random network distillation (Burda et al., 2019; the paper's [21]) as an uncertainty score beside the rate.

    e(s)  = mean_d (g_phi(s)_d - f(s)_d)^2      f: a fixed, randomly initialized target network
                                                g_phi: a predictor trained to match f on the training data
    u_RND = e(s) / e_bar,   e_bar = mean of e over the training frames (eval mode)

s is what the policy sees: its normalized camera images and `observation.state`, so the score can be computed
on the batch the policy's preprocessor already made. f and g share an architecture (a small conv trunk per
camera, shared across cameras, and a linear state embedding, summed); g has an extra MLP head, as in
Burda et al. Like R_bar, e_bar and the standard deviation of e are kept as buffers, so `u_RND` and the
paper's threshold mean(u) + 2 std(u) come with a saved model.
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch
from safetensors.torch import load_file, save_file
from torch import Tensor, nn

from .calibration import rate_statistics

logger = logging.getLogger(__name__)

CONFIG_NAME, WEIGHTS_NAME = "rnd_config.json", "rnd.safetensors"


@dataclass
class RNDConfig:
    """Args:
    image_keys: Camera features the score reads (normalized images, (3, H, W) each).
    image_shape: (3, H, W) of every camera.
    state_key: The state feature (None: images only).
    state_dim: Size of the state.
    embed_dim: Output size of target and predictor.
    steps, batch_size, lr: The predictor's training budget (Adam).
    seed: Initialization seed of both networks (RND is sensitive to it: keep it with the results).
    """

    image_keys: list[str] = field(default_factory=list)
    image_shape: list[int] = field(default_factory=list)
    state_key: str | None = "observation.state"
    state_dim: int = 0
    embed_dim: int = 64
    steps: int = 2000
    batch_size: int = 32
    lr: float = 1e-4
    seed: int = 0

    def __post_init__(self):
        if not self.image_keys and not self.state_key:
            raise ValueError("RND needs at least one camera or a state to score.")
        if self.image_keys and len(self.image_shape) != 3:
            raise ValueError(f"`image_shape` must be (3, H, W), got {self.image_shape}.")
        if self.state_key and self.state_dim < 1:
            raise ValueError(f"`state_dim` must be >= 1 when `state_key` is set, got {self.state_dim}.")


class _Embedding(nn.Module):
    def __init__(self, cfg: RNDConfig, head: bool):
        super().__init__()
        self.cfg = cfg
        d = cfg.embed_dim
        if cfg.image_keys:
            self.trunk = nn.Sequential(
                nn.Conv2d(3, 32, 5, stride=2, padding=2), nn.LeakyReLU(),
                nn.Conv2d(32, 64, 3, stride=2, padding=1), nn.LeakyReLU(),
                nn.Conv2d(64, 64, 3, stride=2, padding=1), nn.LeakyReLU(),
                nn.AdaptiveAvgPool2d((4, 4)), nn.Flatten(), nn.Linear(64 * 16, d),
            )  # fmt: skip
        if cfg.state_key:
            self.state = nn.Linear(cfg.state_dim, d)
        self.head = nn.Sequential(nn.ReLU(), nn.Linear(d, 4 * d), nn.ReLU(), nn.Linear(4 * d, d)) if head else None

    def forward(self, batch: dict[str, Tensor]) -> Tensor:
        parts = [self.trunk(batch[key]) for key in self.cfg.image_keys]
        if self.cfg.state_key:
            parts.append(self.state(batch[self.cfg.state_key]))
        out = torch.stack(parts).sum(0)
        return self.head(out) if self.head is not None else out


class RND(nn.Module):
    """Target f (frozen), predictor g, and the training statistics of the error e."""

    def __init__(self, cfg: RNDConfig):
        super().__init__()
        self.cfg = cfg
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(cfg.seed)
            self.target = _Embedding(cfg, head=False)
            self.predictor = _Embedding(cfg, head=True)
        self.target.requires_grad_(False)
        self.register_buffer("error_mean", torch.tensor(math.nan, dtype=torch.float64))
        self.register_buffer("error_std", torch.tensor(math.nan, dtype=torch.float64))

    def check(self, batch: dict[str, Tensor]) -> None:
        keys = [*self.cfg.image_keys, *([self.cfg.state_key] if self.cfg.state_key else [])]
        if missing := [k for k in keys if k not in batch]:
            raise KeyError(f"RND scores {keys}; the batch lacks {missing}.")
        for key in self.cfg.image_keys:
            if tuple(batch[key].shape[1:]) != tuple(self.cfg.image_shape):
                raise ValueError(
                    f"`{key}` has shape {tuple(batch[key].shape)}; RND was built for {self.cfg.image_shape}."
                )

    def error(self, batch: dict[str, Tensor]) -> Tensor:
        """e(s), (B,)."""
        self.check(batch)
        return (self.predictor(batch) - self.target(batch).detach()).pow(2).mean(-1)

    @torch.no_grad()
    def u(self, batch: dict[str, Tensor]) -> Tensor:
        """u_RND = e / e_bar, (B,)."""
        mean = float(self.error_mean)
        if not (math.isfinite(mean) and mean > 0):
            raise RuntimeError("This RND has no training statistics (e_bar): train it with `train_rnd`.")
        return self.error(batch) / mean

    def threshold(self) -> float:
        """The paper's gamma on u: mean(u) + 2 std(u) = 1 + 2 std(e) / e_bar."""
        return 1.0 + 2.0 * float(self.error_std) / float(self.error_mean)

    def save(self, directory: Path) -> None:
        directory.mkdir(parents=True, exist_ok=True)
        tmp = directory / (WEIGHTS_NAME + ".tmp")
        save_file({k: v.contiguous() for k, v in self.state_dict().items()}, str(tmp))
        (directory / CONFIG_NAME).write_text(json.dumps(asdict(self.cfg), indent=2))
        tmp.replace(directory / WEIGHTS_NAME)  # the weights file last: its presence means a complete save

    @classmethod
    def load(cls, directory: Path) -> RND:
        directory = Path(directory)
        if not (directory / WEIGHTS_NAME).exists():
            raise FileNotFoundError(f"No RND model in {directory} (expected {WEIGHTS_NAME} and {CONFIG_NAME}).")
        model = cls(RNDConfig(**json.loads((directory / CONFIG_NAME).read_text())))
        model.load_state_dict(load_file(str(directory / WEIGHTS_NAME)))
        return model.eval()


def train_rnd(
    model: RND,
    batches: Callable[[], Iterable[dict[str, Tensor]]],
    stats_batches: Iterable[dict[str, Tensor]],
    progress: Callable[[int, float], None] | None = None,
) -> list[float]:
    """Fit the predictor for `cfg.steps` steps on `batches()` (re-iterated as needed; normalized like the
    policy's input), then set e_bar and std(e) over `stats_batches` (every training frame, eval mode).
    Returns the training loss per step."""
    cfg = model.cfg
    optimizer = torch.optim.Adam(model.predictor.parameters(), lr=cfg.lr)
    model.train()
    losses: list[float] = []
    while len(losses) < cfg.steps:
        seen = len(losses)
        for batch in batches():
            loss = model.error(batch).mean()
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
            losses.append(float(loss.detach()))
            if progress is not None:
                progress(len(losses), losses[-1])
            if len(losses) >= cfg.steps:
                break
        if len(losses) == seen:
            raise ValueError("RND got no training batches: is the dataset empty?")
    model.eval()
    stats = rate_statistics(model.error, stats_batches)
    model.error_mean.fill_(stats.mean)
    model.error_std.fill_(stats.std)
    return losses
