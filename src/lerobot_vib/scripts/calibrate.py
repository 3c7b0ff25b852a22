"""`lerobot-vib-calibrate`: exact rate statistics and the stop threshold, written into a VIB checkpoint.

    lerobot-vib-calibrate --policy.path=outputs/train/vib/checkpoints/last/pretrained_model \
        --dataset.repo_id=local/aloha_sim_transfer_cube_scripted --dataset.root=data/transfer_cube \
        [--episodes='[0,1,...,39]'] [--conformal_alpha=0.05 --conformal_episodes='[40,...,49]'] \
        [--output_dir=... | --in_place=true]

R_bar (mean rate), its std and quantiles are computed in eval mode over `--episodes` (default: all) and
stored in the checkpoint's config (`calibration`), so `from_pretrained`, `lerobot-eval` and a Hub push carry
them. gamma is the paper's mean(u) + 2 std(u), or with `--conformal_alpha` the split-conformal threshold on
held-out `--conformal_episodes` (see `lerobot_vib.calibration`). The calibrated checkpoint is written to
`<checkpoint>_calibrated` (or `--output_dir`); `--in_place=true` updates the checkpoint itself, `config.json`
and `train_config.json` alike.

gamma from rollouts. u is highest in an episode's first steps, training episodes included, and a policy's
own rollouts drift from its data, so a threshold set on dataset frames can stop every rollout at step 1. The
benchmark judges thresholds on clean rollouts; the same is one command here: evaluate the calibrated
checkpoint with the stop off (`lerobot-vib-eval`), then

    lerobot-vib-calibrate --policy.path=<calibrated checkpoint> --in_place=true \
        --rollouts=<eval output_dir>/uncertainty_info.json --conformal_alpha=0.1

sets gamma to the split-conformal threshold on the rollouts' per-episode max u: a new clean rollout exceeds it
with probability at most alpha. R_bar and the rate statistics stay those of the dataset.
"""

import csv
import json
import logging
import math
import os
import shutil
import sys
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import huggingface_hub
import numpy as np
import torch
from lerobot.configs import parser
from lerobot.configs.policies import PreTrainedConfig
from lerobot.datasets.lerobot_dataset import LeRobotDataset, LeRobotDatasetMetadata
from lerobot.policies.factory import make_pre_post_processors
from lerobot.utils.import_utils import register_third_party_plugins
from tqdm import tqdm

from ..calibration import (
    QUANTILE_LEVELS,
    RateStatistics,
    conformal_gamma,
    conformal_min_scores,
    mean_plus_2std_gamma,
)
from ..configuration_vib import CalibrationConfig, VIBConfigError
from ..failure import windowed
from ..metrics import BANDS
from ..modeling_vib import VIBPolicy
from ..pooled_network import EncoderParts
from ..processor_vib import vib_dataset_stats
from ..provenance import dataset_mismatches, rollout_env_problems, training_recording
from ..scores import SCORES, episode_disagreement, fit_embedding_rnd, score_statistics, token_scores

logger = logging.getLogger(__name__)

ROLLOUT_EPISODES = ("all", "successes")  # which clean rollouts set a threshold (`--rollout_episodes`)


@dataclass
class CalibrationDataset:
    """Args:
    repo_id: LeRobot dataset id (the policy's training data, or data like it).
    root: Local directory of the dataset.
    revision: Hub revision, when the dataset comes from the Hub.
    video_backend: Video decoder (LeRobot's default when None).
    """

    repo_id: str
    root: str | None = None
    revision: str | None = None
    video_backend: str | None = None


@dataclass
class CalibrateConfig:
    """Args:
    dataset: The dataset to compute the rate statistics on (not with `rollouts`).
    policy: Set with `--policy.path=<checkpoint dir or Hub id>`.
    episodes: Episodes for R_bar and the statistics (default: all).
    conformal_alpha: Target per-episode false-stop rate; sets gamma by split conformal prediction.
    conformal_episodes: Held-out in-distribution episodes for the conformal threshold (not in `episodes`).
    rollouts: `uncertainty_info.json` of clean rollouts of this calibrated checkpoint (`lerobot-vib-eval`, stop
        off; its `uncertainty_trace.csv` beside it): gamma becomes the threshold `threshold` at `conformal_alpha`.
    batch_size: Frames per forward pass.
    threshold: With `rollouts` (None: "time_band"): "time_band", one threshold per episode step from the
        rollouts' per-step u (the best measured on the arm, docs/uncertainty.md; it needs twice the rollouts of
        "max", 18 at alpha = 0.1), "std_band", the same with FAIL-Detect's band (mean + q standard deviations
        per step, metrics.std_band: tight where clean rollouts agree), or "max", one gamma, the conformal
        threshold on each rollout's max u.
    window: With `rollouts`: the stop reads u aggregated over each env's last `window` steps, and the threshold
        is set on that (`calibration.window`; failure.py's windowed monitors). 1: u itself.
    window_aggregate: "mean" or "sum" over the window.
    rollout_episodes: With `rollouts`: "all" clean rollouts set the threshold, or only the "successes" (failure
        prediction's calibration, failure.py: false alarms are bounded on episodes that would have succeeded,
        and a failing episode's u is not taken for normal). `calibration.rollout_episodes`.
    and_scores: With `rollouts`: other scores the stop also needs above their own threshold (an AND, FIPER's
        combination), each set at `conformal_alpha` on the same rollouts' per-step u of that score over the same
        window (the `u_<score>` columns lerobot-vib-eval writes); `calibration.and_gammas`.
    or_scores: With `rollouts`: other scores any of which, above its own constant threshold, also stops (an OR,
        failure.AnyOf): each read over `or_window` steps, and every threshold, gamma's included, set at
        `conformal_alpha` / k for k members so that the OR keeps `conformal_alpha`; `calibration.or_gammas`.
        Not with `and_scores`.
    or_window: The window of the `or_scores`, in steps.
    or_margin: With `or_scores`: their thresholds at this many times their conformal ones (>= 1, so the OR still
        keeps `conformal_alpha`): a partner then fires only far outside the clean rollouts (failure.AnyOf);
        `calibration.or_margin`.
    rnd_steps: Training steps of the "embedding_rnd" score's predictor (batch 256, on the recorded embeddings).
    num_workers: DataLoader workers.
    output_dir: Where to write the calibrated checkpoint (default: `<checkpoint>_calibrated` beside a local
        checkpoint). An existing folder is only written if it is a calibrated checkpoint itself.
    in_place: Write the calibration into the checkpoint itself (`config.json` and `train_config.json`, so that
        `lerobot-train --resume=true` keeps it) instead of a new folder.
    push_to_hub: Push the calibrated checkpoint to the Hub under `repo_id` when it is written: the weights, the
        config with its calibration, the processors and a model card that states the calibration and the
        success measured on the rollouts (`lerobot-train` pushes the uncalibrated model).
    repo_id: The Hub repository to push to (`user/name`).
    """

    dataset: CalibrationDataset | None = None
    policy: PreTrainedConfig | None = None
    episodes: list[int] | None = None
    conformal_alpha: float | None = None
    conformal_episodes: list[int] | None = None
    rollouts: Path | None = None
    batch_size: int = 32
    num_workers: int = 0
    rnd_steps: int = 3000
    threshold: str | None = None
    window: int = 1
    window_aggregate: str = "mean"
    and_scores: list[str] = field(default_factory=list)
    or_scores: list[str] = field(default_factory=list)
    or_window: int = 1
    or_margin: float = 1.0
    rollout_episodes: str = "all"
    output_dir: Path | None = None
    in_place: bool = False
    push_to_hub: bool = False
    repo_id: str | None = None

    def __post_init__(self):
        # Arguments first: nothing below may cost minutes before a typo is reported.
        if self.push_to_hub:
            if not self.repo_id or self.repo_id.count("/") != 1:
                raise VIBConfigError(f"`--push_to_hub=true` needs `--repo_id=user/name`, got {self.repo_id!r}.")
            if huggingface_hub.constants.HF_HUB_OFFLINE:
                raise VIBConfigError(
                    "`--push_to_hub=true`, but the Hub is offline (HF_HUB_OFFLINE): calibrate without it, and push "
                    "later with the same command online (`--rollouts=...` again, or the last step you ran)."
                )
        if self.rollouts is not None:
            if self.dataset is not None or self.episodes is not None or self.conformal_episodes is not None:
                raise VIBConfigError(
                    "`--rollouts` sets gamma from rollouts of an already calibrated checkpoint: drop `--dataset.*`, "
                    "`--episodes` and `--conformal_episodes`."
                )
            if self.conformal_alpha is None:
                raise VIBConfigError("`--rollouts` needs `--conformal_alpha` (the false-stop rate to allow).")
            if not Path(self.rollouts).is_file():
                raise VIBConfigError(f"No rollouts file at {self.rollouts} (lerobot-vib-eval's uncertainty_info.json).")
        elif self.dataset is None:
            raise VIBConfigError("Give the dataset (`--dataset.repo_id=...`), or `--rollouts=` to set gamma only.")
        elif (self.conformal_alpha is None) != (self.conformal_episodes is None):
            raise VIBConfigError("`--conformal_alpha` and `--conformal_episodes` (held-out episodes) go together.")
        if self.conformal_alpha is not None:
            if not 0 < self.conformal_alpha < 1:
                raise VIBConfigError(f"`--conformal_alpha` must be in (0, 1), got {self.conformal_alpha}.")
            needed = conformal_min_scores(self.conformal_alpha)
            if self.conformal_episodes is not None and len(set(self.conformal_episodes)) < needed:
                raise VIBConfigError(
                    f"A conformal threshold at alpha={self.conformal_alpha} needs at least {needed} held-out "
                    f"episodes; `--conformal_episodes` has {len(set(self.conformal_episodes))}."
                )
            if self.episodes is not None and (both := sorted(set(self.conformal_episodes) & set(self.episodes))):
                raise VIBConfigError(f"Held-out conformal episodes must not be among `--episodes`: {both}.")
        if self.threshold is not None:
            if self.threshold not in ("max", *BANDS):
                raise VIBConfigError(f"`--threshold` must be one of max, {', '.join(BANDS)}, got {self.threshold!r}.")
            if self.rollouts is None:
                raise VIBConfigError("`--threshold` sets gamma from rollouts: give `--rollouts=` too.")
        elif self.rollouts is not None:
            self.threshold = "time_band"
        if self.window < 1 or self.window_aggregate not in ("mean", "sum"):
            raise VIBConfigError(
                f"`--window` must be >= 1 and `--window_aggregate` mean or sum, got {self.window} and "
                f"{self.window_aggregate!r}."
            )
        if self.rollout_episodes not in ROLLOUT_EPISODES:
            raise VIBConfigError(
                f"`--rollout_episodes` must be one of {ROLLOUT_EPISODES}, got {self.rollout_episodes!r}."
            )
        if self.rollout_episodes != "all" and self.rollouts is None:
            raise VIBConfigError("`--rollout_episodes` chooses among rollouts: give `--rollouts=` too.")
        if unknown := sorted(set(self.and_scores) - set(SCORES)):
            raise VIBConfigError(f"`--and_scores` must name scores of {SCORES}; unknown: {unknown}.")
        if unknown := sorted(set(self.or_scores) - set(SCORES)):
            raise VIBConfigError(f"`--or_scores` must name scores of {SCORES}; unknown: {unknown}.")
        if self.and_scores and self.or_scores:
            raise VIBConfigError("`--and_scores` and `--or_scores` are both given: the stop runs one of them.")
        if self.or_window < 1:
            raise VIBConfigError(f"`--or_window` must be >= 1, got {self.or_window}.")
        if not (math.isfinite(self.or_margin) and self.or_margin >= 1):
            raise VIBConfigError(
                f"`--or_margin` must be >= 1 (below the conformal thresholds the OR breaks alpha), got "
                f"{self.or_margin}."
            )
        if self.or_margin != 1 and not self.or_scores:
            raise VIBConfigError("`--or_margin` scales the `--or_scores` thresholds: give `--or_scores` too.")
        if (self.window > 1 or self.and_scores or self.or_scores) and self.rollouts is None:
            raise VIBConfigError(
                "`--window` sets the stop's window with its threshold from rollouts: give `--rollouts=`."
            )
        if self.batch_size < 1:
            raise VIBConfigError(f"`--batch_size` must be >= 1, got {self.batch_size}.")
        policy_path = parser.get_path_arg("policy")
        if policy_path:
            _check_checkpoint(policy_path)
            cli_overrides = parser.get_cli_overrides("policy") or []
            self.policy = PreTrainedConfig.from_pretrained(policy_path, cli_overrides=cli_overrides)
            self.policy.pretrained_path = Path(policy_path)

    @classmethod
    def __get_path_fields__(cls) -> list[str]:
        return ["policy"]


def _check_checkpoint(path: str) -> None:
    """A clear error for a checkpoint that is neither a local folder nor reachable on the Hub."""
    local = Path(path)
    if local.is_dir():
        if not (local / "config.json").is_file():
            raise VIBConfigError(
                f"No checkpoint at {path}: the folder has no config.json (a `pretrained_model` folder)."
            )
        return
    looks_like_repo_id = path.count("/") == 1 and not path.startswith((".", "/", "~"))
    if not looks_like_repo_id:
        raise VIBConfigError(f"No such checkpoint: {path} is not a folder (nor a Hub id like user/name).")
    if huggingface_hub.constants.HF_HUB_OFFLINE:
        raise VIBConfigError(
            f"No such checkpoint: {path} is not a local folder, and the Hub is offline (HF_HUB_OFFLINE)."
        )


def check_episodes(total_episodes: int, **named: list[int] | None) -> None:
    """Every requested episode must be in the dataset (episodes 0 .. total_episodes - 1)."""
    for name, episodes in named.items():
        missing = sorted(e for e in episodes or [] if not 0 <= e < total_episodes)
        if missing:
            listed = ", ".join(map(str, missing[:5])) + (" ..." if len(missing) > 5 else "")
            raise VIBConfigError(
                f"`--{name}`: episode{'s' if len(missing) > 1 else ''} {listed} "
                f"{'are' if len(missing) > 1 else 'is'} not in this dataset (it has 0-{total_episodes - 1})."
            )


def _output_dir(source: Path, output_dir: Path | None, in_place: bool) -> Path:
    """Where the calibrated checkpoint goes; never a folder this command did not write (or the source, if asked)."""
    if in_place:
        if output_dir is not None:
            raise VIBConfigError("Choose one of `--in_place=true` and `--output_dir`.")
        if not source.is_dir():
            raise VIBConfigError(f"{source} is not a local checkpoint: `--in_place` needs one.")
        return source
    if output_dir is None:
        if not source.is_dir():
            raise VIBConfigError(f"{source} is not a local checkpoint: pass `--output_dir` for the calibrated copy.")
        output_dir = source.with_name(source.name + "_calibrated")
    output_dir = Path(output_dir)
    if output_dir.exists() and any(output_dir.iterdir()):
        config = output_dir / "config.json"
        calibrated = config.is_file() and (json.loads(config.read_text()).get("calibration") or {}).get("rate_mean")
        if not calibrated:
            raise VIBConfigError(
                f"{output_dir} exists and is not a calibrated checkpoint; choose another `--output_dir` "
                "(or `--in_place=true` to calibrate the checkpoint itself)."
            )
    return output_dir


def _update_train_config(checkpoint: Path, policy_config: PreTrainedConfig) -> None:
    """Keep `train_config.json` (what `lerobot-train --resume=true` reads) consistent with `config.json`."""
    path = checkpoint / "train_config.json"
    if not path.is_file():
        return
    train_config = json.loads(path.read_text())
    if isinstance(train_config.get("policy"), dict):
        train_config["policy"]["calibration"] = asdict(policy_config.calibration)
        tmp = path.with_suffix(".json.tmp")
        tmp.write_text(json.dumps(train_config, indent=4))
        tmp.replace(path)


def _loader(repo_id: str, root, episodes, revision, video_backend, batch_size, num_workers, needed: list[str]):
    dataset = LeRobotDataset(repo_id, root=root, episodes=episodes, revision=revision, video_backend=video_backend)
    missing = [k for k in needed if k not in dataset.meta.features]
    if missing:
        raise KeyError(
            f"Dataset {repo_id} lacks {missing}, which the policy needs (it has {sorted(dataset.meta.features)})."
        )
    return torch.utils.data.DataLoader(dataset, batch_size=batch_size, num_workers=num_workers, shuffle=False)


@dataclass
class FrameRecords:
    """What one encoder and decoder pass over dataset frames keeps, to compute every score (`scores.py`)."""

    episode_index: torch.Tensor  # (N,)
    frame_index: torch.Tensor  # (N,)
    rate: torch.Tensor  # (N,)
    image: torch.Tensor | None  # (N, K * d_token) the camera path
    state: torch.Tensor | None  # (N, K * d_token) the state path
    rnd_input: torch.Tensor  # (N, D) the embedding "embedding_rnd" reads
    chunks: torch.Tensor  # (N, chunk_size, A) the chunk decoded at each frame
    token_rates: torch.Tensor | None = None  # (N, tokens) the token network's per-token rates

    def fit(self, policy: VIBPolicy, rnd_steps: int = 3000) -> None:
        """Fit the scores' parts on these (training) frames: the pooled network's state-path mean or the token
        network's per-cell rate statistics, and the RND."""
        if self.token_rates is not None:
            cells = self.token_rates[:, policy.network.n_1d_tokens :]
            if cells.shape[1]:
                policy.map_cell_mean.copy_(cells.mean(0))
                policy.map_cell_std.copy_(cells.std(0) if len(cells) > 1 else torch.ones(cells.shape[1]))
        elif self.state is not None:
            policy.state_embedding_mean.copy_(self.state.mean(0))
        fit_embedding_rnd(policy.embedding_rnd, self.rnd_input, steps=rnd_steps, progress=True)

    @torch.no_grad()
    def scores(self, policy: VIBPolicy) -> dict[str, torch.Tensor]:
        """Every score that `policy` can compute, per frame (float64)."""
        network = policy.network
        out = {"rate": self.rate}
        if self.token_rates is not None:
            cell_mean, cell_std = policy.map_cell_mean, policy.map_cell_std
            rates = self.token_rates.double()
            out.update(token_scores(rates, network.n_1d_tokens, cell_mean, cell_std, policy.config.map_top_k))
        elif self.image is not None:
            if self.state is None:
                out["image_rate"] = self.rate
            elif torch.isfinite(policy.state_embedding_mean).all():
                held = self.image + policy.state_embedding_mean
                out["image_rate"] = torch.cat(
                    [network.bottleneck.rate(network.posterior_of(h)) for h in held.split(1024)]
                ).double()
        if "image_rate" in out:
            out["low_image_rate"] = 1.0 / out["image_rate"]
        if policy.embedding_rnd.fitted:
            out["embedding_rnd"] = torch.cat([policy.embedding_rnd.error(x) for x in self.rnd_input.split(4096)])
            out["embedding_rnd"] = out["embedding_rnd"].double()
        disagreement = torch.zeros_like(self.rate)
        for episode in torch.unique(self.episode_index):
            idx = torch.nonzero(self.episode_index == episode).flatten()
            idx = idx[torch.argsort(self.frame_index[idx])]  # in time order, whatever order the loader gave
            disagreement[idx] = episode_disagreement(self.chunks[idx], self.chunks.shape[1]).double()
        out["chunk_disagreement"] = disagreement
        return out


@torch.no_grad()
def record_frames(policy: VIBPolicy, preprocessor, batches) -> FrameRecords:
    """Encode and decode every frame (eval mode, the acting weights)."""
    policy.eval()
    network = policy.network
    tokens = policy.config.encoder == "tokens"
    keep: dict[str, list[torch.Tensor]] = {
        k: [] for k in ("episode", "frame", "rate", "image", "state", "rnd", "chunk", "token_rates")
    }
    for batch in batches:
        obs = preprocessor({k: v for k, v in batch.items() if k.startswith("observation")})
        policy._check_observation(obs)
        if tokens:
            posterior = network.encode(obs)
            token_rates = network.token_rates(posterior)
            rate = token_rates.mean(dim=1)
            parts = EncoderParts(image=None, state=None, pooled=None)
        else:
            parts = network.encoder.parts(obs)
            posterior = network.posterior_of(parts.fused)
            rate = network.bottleneck.rate(posterior)
            token_rates = None
        if not torch.isfinite(rate).all():
            raise ValueError(
                "Non-finite rate on calibration frames (episodes "
                f"{sorted(set(batch['episode_index'].reshape(-1).tolist()))}): check the dataset for NaN values."
            )
        keep["episode"].append(torch.as_tensor(batch["episode_index"]).reshape(-1).cpu())
        keep["frame"].append(torch.as_tensor(batch["frame_index"]).reshape(-1).cpu())
        keep["rate"].append(rate.double().cpu())
        keep["image"].append(None if parts.image is None else parts.image.cpu())
        keep["state"].append(None if parts.state is None else parts.state.cpu())
        keep["rnd"].append((network.embedding(posterior) if tokens else network.rnd_embedding(parts, obs)).cpu())
        # the chunks it acts on: with sample_latent_at_inference a posterior sample's, so that chunk disagreement's
        # statistics include the sampling noise the policy's own chunks carry
        z = posterior.sample() if policy.config.sample_latent_at_inference else posterior.mean
        keep["chunk"].append(network.decode(z).cpu())
        keep["token_rates"].append(None if token_rates is None else token_rates.cpu())
    if not keep["rate"]:
        raise ValueError("No frames to calibrate on.")

    def cat(name: str) -> torch.Tensor | None:
        return None if keep[name][0] is None else torch.cat(keep[name])

    return FrameRecords(
        cat("episode"), cat("frame"), cat("rate"), cat("image"), cat("state"), cat("rnd"), cat("chunk"),
        token_rates=cat("token_rates"),
    )  # fmt: skip


def _episode_max(values: torch.Tensor, episode_index: torch.Tensor, scale: float) -> torch.Tensor:
    return torch.stack([(values[episode_index == e] / scale).max() for e in torch.unique(episode_index)])


def calibrate(
    policy: VIBPolicy,
    preprocessor,
    repo_id: str,
    root: str | Path | None = None,
    episodes: list[int] | None = None,
    conformal_alpha: float | None = None,
    conformal_episodes: list[int] | None = None,
    batch_size: int = 32,
    num_workers: int = 0,
    revision: str | None = None,
    video_backend: str | None = None,
    rnd_steps: int = 3000,
) -> CalibrationConfig:
    """Every score's statistics of `policy` (eval mode) over the dataset's episodes, the fitted parts of the
    scores (written into `policy`), and gamma on the configured score."""
    if conformal_episodes is not None and episodes is not None and set(conformal_episodes) & set(episodes):
        raise ValueError(
            "Held-out conformal episodes must not be among the calibration episodes: "
            f"{sorted(set(conformal_episodes) & set(episodes))}."
        )
    policy.eval()
    needed = list(policy._used_inputs)
    common = dict(revision=revision, video_backend=video_backend, batch_size=batch_size, num_workers=num_workers)
    loader = _loader(repo_id, root, episodes, needed=needed, **common)
    records = record_frames(policy, preprocessor, tqdm(loader, desc="score statistics", unit="batch"))
    records.fit(policy, rnd_steps=rnd_steps)
    values = records.scores(policy)
    stats = RateStatistics(records.rate, records.episode_index)
    score = policy.config.uncertainty_score
    moments = {name: score_statistics(v) for name, v in values.items()}
    mean, std = moments[score]
    calibration = CalibrationConfig(
        dataset_repo_id=repo_id,
        episodes=sorted(set(stats.episode_index.tolist())),
        n_frames=int(stats.rates.numel()),
        rate_mean=stats.mean,
        rate_std=stats.std,
        rate_quantiles=stats.quantiles(QUANTILE_LEVELS),
        score_means={name: m for name, (m, _) in moments.items() if name != "rate"},
        score_stds={name: s for name, (_, s) in moments.items() if name != "rate"},
        gamma=mean_plus_2std_gamma(mean, std),
        gamma_method="mean_plus_2std",
        gamma_score=score,
    )
    if conformal_alpha is not None:
        loader = _loader(repo_id, root, conformal_episodes, needed=needed, **common)
        held_out = record_frames(policy, preprocessor, tqdm(loader, desc="held-out episodes", unit="batch"))
        held_values = held_out.scores(policy)[score]
        calibration.gamma = conformal_gamma(_episode_max(held_values, held_out.episode_index, mean), conformal_alpha)
        calibration.gamma_method = "conformal"
        calibration.conformal_alpha = conformal_alpha
        calibration.conformal_episodes = sorted(set(held_out.episode_index.tolist()))
    u = values[score] / mean
    calibration.frames_above_gamma = float((u > calibration.gamma).double().mean())
    episode_max = _episode_max(values[score], records.episode_index, mean)
    calibration.episodes_above_gamma = float((episode_max > calibration.gamma).double().mean())
    return calibration


def gamma_from_rollouts(
    calibration: CalibrationConfig,
    info: dict,
    alpha: float,
    source: str,
    expected_score: str = "rate",
    threshold: str = "max",
    traces: list[np.ndarray] | None = None,
    policy_config: PreTrainedConfig | None = None,
    recording: dict | None = None,
    window: int = 1,
    window_aggregate: str = "mean",
    and_traces: dict[str, list[np.ndarray]] | None = None,
    episodes: str = "all",
    or_traces: dict[str, list[np.ndarray]] | None = None,
    or_window: int = 1,
    or_margin: float = 1.0,
) -> CalibrationConfig:
    """`calibration` with gamma = the split-conformal threshold on clean rollouts' per-episode max u of the
    score the checkpoint reads u from (`expected_score`); with `threshold="time_band"` or `"std_band"`, a
    time-indexed band from the rollouts' per-step u `traces` (metrics.time_indexed_band, metrics.std_band: the
    first half of the rollouts sets the band's shape, the second half its conformal level).

    Refused unless the rollouts are clean ones of this checkpoint: the stop off, no perturbation, the env's
    cameras and image size those of `policy_config`, its task and workspace those of the training `recording`
    (provenance.py), u normalized as this checkpoint normalizes it. With `window` > 1 both thresholds are set on
    u aggregated over the last `window` steps (failure.windowed), from the per-step `traces`. `and_traces`
    ({score: per-step u of each rollout}) adds an AND: each score's threshold, conformal at `alpha` on its
    windowed maxima, into `and_gammas`. `or_traces` adds an OR instead: each score's threshold on its maxima
    over `or_window` steps into `or_gammas`, and every threshold, gamma's included, at alpha / k for k members,
    the partners' at `or_margin` times theirs.
    `episodes="successes"` sets every threshold on the successful rollouts only (failure prediction's
    calibration)."""
    if and_traces and or_traces:
        raise VIBConfigError("An AND and an OR of scores were both given: the stop runs one of them.")
    # the union bound: k members each at alpha / k alarm together on at most alpha of clean rollouts
    member_alpha = alpha / (1 + len(or_traces)) if or_traces else alpha
    if calibration.rate_mean is None:
        raise VIBConfigError(
            "The checkpoint has no R_bar: calibrate it on its dataset first, evaluate that checkpoint, then use "
            "`--rollouts`."
        )
    if info.get("safety_enabled"):
        raise VIBConfigError(
            f"{source} was evaluated with the safety stop on, so its episodes are not clean rollouts: evaluate "
            "with `--policy.safety.enabled=false`."
        )
    if problems := rollout_env_problems(info, policy_config, recording):
        raise VIBConfigError(
            f"{source} holds no clean rollouts of this checkpoint: {'; '.join(problems)}. A threshold is set on "
            "clean rollouts in the env the policy was trained for: evaluate it there with lerobot-vib-eval "
            "(no --env.perturbation.*, --env.dataset_root=<its training data>) and calibrate on those."
        )
    score = info.get("score") or "rate"
    if score != expected_score:
        raise VIBConfigError(
            f"{source} holds u of the {score} score, this checkpoint reads u from {expected_score}: evaluate it "
            "with the score it will run with, then calibrate on those rollouts."
        )
    if score == "rate":
        rate_mean, expected_mean, name = info.get("rate_mean"), calibration.rate_mean, "R_bar"
    else:
        rate_mean, expected_mean, name = info.get("score_mean"), calibration.score_means.get(score), f"{score}'s mean"
    if rate_mean is None or expected_mean is None or not math.isclose(rate_mean, expected_mean, rel_tol=1e-4):
        raise VIBConfigError(
            f"{source} holds u normalized by {name}={rate_mean}, this checkpoint has {name}={expected_mean}: "
            "evaluate this checkpoint (the calibrated one) and calibrate on those rollouts."
        )
    unknown = [ep.get("seed") for ep in info["per_episode"] if ep["u_max"] is None or not math.isfinite(ep["u_max"])]
    if unknown:
        # Dropping them would set gamma on the rollouts that went well; a clean rollout with no finite u is a bug.
        raise VIBConfigError(
            f"{source} has rollouts without a finite max u (seeds {unknown}): fix them, then calibrate."
        )
    scores = [ep["u_max"] for ep in info["per_episode"]]
    if episodes == "successes":
        if not all("success" in ep for ep in info["per_episode"]):
            raise VIBConfigError(
                f"{source} does not say which rollouts succeeded: `--rollout_episodes=successes` needs "
                "lerobot-vib-eval's uncertainty_info.json."
            )
        n = len(info["per_episode"])
        partner_traces = [*(and_traces or {}).values(), *(or_traces or {}).values()]
        if any(len(t) != n for t in [*([traces] if traces is not None else []), *partner_traces]):
            raise VIBConfigError(f"{source}'s per-step traces do not hold one record per rollout ({n}).")
        kept = [i for i, ep in enumerate(info["per_episode"]) if ep["success"]]
        scores = [scores[i] for i in kept]
        traces = None if traces is None else [traces[i] for i in kept]
        and_traces = {k: [v[i] for i in kept] for k, v in (and_traces or {}).items()} or None
        or_traces = {k: [v[i] for i in kept] for k, v in (or_traces or {}).items()} or None
    elif episodes != "all":
        raise ValueError(f"`episodes` must be one of {ROLLOUT_EPISODES}, got {episodes!r}.")
    what = "successful rollouts" if episodes == "successes" else "rollouts"
    if window > 1 or and_traces or or_traces:
        if traces is None or len(traces) != len(scores):
            what = f"A window of {window} steps" if window > 1 else "A combination of scores"
            raise VIBConfigError(f"{what} needs the per-step u of every rollout in {source}.")
        traces = [windowed(t, window, window_aggregate) for t in traces]
        scores = [float(np.max(t)) for t in traces]
    and_gammas = _and_gammas(calibration, info, and_traces or {}, score, len(scores), alpha, source, window,
                             window_aggregate)  # fmt: skip
    or_gammas = _and_gammas(calibration, info, or_traces or {}, score, len(scores), member_alpha, source, or_window,
                            window_aggregate, flag="--or_scores")  # fmt: skip
    or_gammas = {name: or_margin * g for name, g in or_gammas.items()}
    is_band = threshold in BANDS
    needed = conformal_min_scores(member_alpha) * (2 if is_band else 1)
    if len(scores) < needed:
        raise VIBConfigError(
            f"A {'time-indexed band' if is_band else 'conformal threshold'} at "
            f"alpha={member_alpha:.3g} needs "
            f"at least {needed} {what}; {source} has {len(scores)}."
            + (" Evaluate more clean rollouts, or use `--threshold=max`." if is_band else "")
        )
    band = None
    if is_band:
        if traces is None or len(traces) != len(scores):
            raise VIBConfigError(f"The time-indexed band needs the per-step u of every rollout in {source}.")
        half = len(traces) // 2
        try:
            band = [float(g) for g in BANDS[threshold](traces[:half], traces[half:], member_alpha)]
        except ValueError as e:
            raise VIBConfigError(f"No {threshold} from {source}: {e}") from e
        gamma = max(band)
        above = [bool(np.any(t > np.asarray(band)[: len(t)])) for t in traces]
    else:
        gamma = conformal_gamma(np.asarray(scores), member_alpha)
        above = [s > gamma for s in scores]
    if and_gammas:  # an episode the AND stops: at some step every member is above its threshold
        above = []
        for i, t in enumerate(traces):
            hit = t > (gamma if band is None else np.asarray(band)[: len(t)])
            for name, g in and_gammas.items():
                hit &= windowed(and_traces[name][i], window, window_aggregate)[: len(t)] > g
            above.append(bool(hit.any()))
    if or_gammas:  # an episode the OR stops: at some step any member is above its threshold
        for i in range(len(traces)):
            for name, g in or_gammas.items():
                above[i] = bool(above[i] or np.any(windowed(or_traces[name][i], or_window, window_aggregate) > g))
    return replace(
        calibration,
        gamma=gamma,
        gamma_band=band,
        gamma_method=f"{threshold}_rollouts" if band else "conformal_rollouts",
        gamma_score=score,
        conformal_alpha=alpha,
        conformal_episodes=None,
        rollout_seeds=[ep["seed"] for ep in info["per_episode"] if ep.get("seed") is not None],
        rollout_successes=sum(bool(ep["success"]) for ep in info["per_episode"])
        if all("success" in ep for ep in info["per_episode"])
        else None,
        rollout_command=info.get("command"),
        rollout_episodes=episodes,
        frames_above_gamma=None,
        episodes_above_gamma=float(np.mean(above)),
        window=window,
        window_aggregate=window_aggregate,
        and_gammas=and_gammas,
        or_gammas=or_gammas,
        or_window=or_window,
        or_margin=or_margin,
    )


def _and_gammas(
    calibration: CalibrationConfig,
    info: dict,
    and_traces: dict[str, list[np.ndarray]],
    score: str,
    n: int,
    alpha: float,
    source: str,
    window: int,
    window_aggregate: str,
    flag: str = "--and_scores",
) -> dict[str, float]:
    """Each AND (or OR) member's threshold on the rollouts, refused unless its u was normalized as this
    checkpoint normalizes it and every rollout has its trace."""
    out = {}
    for name, traces in and_traces.items():
        if name == score:
            raise VIBConfigError(f"`{flag}` repeats the stop's own score {score!r}.")
        expected = calibration.rate_mean if name == "rate" else calibration.score_means.get(name)
        recorded = (info.get("score_means") or {}).get(name)
        if expected is None or recorded is None or not math.isclose(recorded, expected, rel_tol=1e-4):
            raise VIBConfigError(
                f"{source} holds u of {name} normalized by {recorded}, this checkpoint's mean is {expected}: "
                "evaluate this calibrated checkpoint with lerobot-vib-eval, which records every score's u."
            )
        if len(traces) != n:
            raise VIBConfigError(f"{source} has {len(traces)} traces of {name} for {n} rollouts.")
        maxima = [float(np.max(windowed(t, window, window_aggregate))) for t in traces]
        out[name] = conformal_gamma(np.asarray(maxima), alpha)
    return out


@parser.wrap()
def calibrate_main(cfg: CalibrateConfig) -> CalibrationConfig:
    if cfg.policy is None:
        raise VIBConfigError("Pass the checkpoint to calibrate with `--policy.path=...`.")
    if cfg.policy.type != "vib":
        raise VIBConfigError(
            f"lerobot-vib-calibrate calibrates VIB policies; {cfg.policy.pretrained_path} is a "
            f"{cfg.policy.type!r} policy."
        )
    if cfg.rollouts is not None:
        return _calibrate_on_rollouts(cfg)
    meta = LeRobotDatasetMetadata(cfg.dataset.repo_id, root=cfg.dataset.root, revision=cfg.dataset.revision)
    if problems := dataset_mismatches(cfg.policy, meta.features):
        raise VIBConfigError(
            f"{cfg.dataset.repo_id} is not data this policy reads: it has {'; '.join(problems)}. Calibrate on the "
            "policy's training data, or data recorded with the same cameras and image size."
        )
    check_episodes(meta.total_episodes, episodes=cfg.episodes, conformal_episodes=cfg.conformal_episodes)
    vib_dataset_stats(cfg.policy, meta.stats, context=f"lerobot-vib-calibrate, {cfg.dataset.repo_id}")
    source = Path(cfg.policy.pretrained_path)
    output_dir = _output_dir(source, cfg.output_dir, cfg.in_place)
    policy = VIBPolicy.from_pretrained(source, config=cfg.policy)
    preprocessor, _ = make_pre_post_processors(policy.config, pretrained_path=str(source))
    calibration = calibrate(
        policy,
        preprocessor,
        cfg.dataset.repo_id,
        root=cfg.dataset.root,
        episodes=cfg.episodes,
        conformal_alpha=cfg.conformal_alpha,
        conformal_episodes=cfg.conformal_episodes,
        batch_size=cfg.batch_size,
        num_workers=cfg.num_workers,
        revision=cfg.dataset.revision,
        video_backend=cfg.dataset.video_backend,
        rnd_steps=cfg.rnd_steps,
    )
    _write(policy, preprocessor, calibration, source, output_dir)
    if cfg.push_to_hub:
        push_calibrated(output_dir, cfg.repo_id)
    quantiles = ", ".join(f"q{k}={v:.4g}" for k, v in calibration.rate_quantiles.items())
    print(
        f"Calibrated {output_dir} on {calibration.n_frames} frames of {len(calibration.episodes)} episodes of "
        f"{calibration.dataset_repo_id}:\n  R_bar={calibration.rate_mean:.6g}  std={calibration.rate_std:.4g}  "
        f"{quantiles}\n  gamma={calibration.gamma:.4f} ({calibration.gamma_method}"
        + (f", alpha={calibration.conformal_alpha}" if calibration.conformal_alpha is not None else "")
        + f", on {calibration.gamma_score})\n  other scores' means: "
        + ", ".join(f"{k}={v:.4g}" for k, v in calibration.score_means.items())
        + f"\n  on these frames: u > gamma on {100 * calibration.frames_above_gamma:.1f}% of frames and in "
        f"{100 * calibration.episodes_above_gamma:.0f}% of episodes (a stop would interrupt them)"
    )
    return calibration


def read_traces(path: Path, column: str = "u") -> list[np.ndarray]:
    """Per-episode values of `column` (u, or u_<score>), in step order, from `lerobot-vib-eval`'s
    uncertainty_trace.csv."""
    if not path.is_file():
        raise VIBConfigError(f"The per-step u is needed from {path} (lerobot-vib-eval writes it).")
    rows: dict[int, list[tuple[int, float]]] = {}
    with path.open() as f:
        reader = csv.DictReader(f)
        if column not in (reader.fieldnames or []):
            raise VIBConfigError(
                f"{path} has no {column} column: evaluate the calibrated checkpoint with lerobot-vib-eval, which "
                "writes every score's u."
            )
        for row in reader:
            rows.setdefault(int(row["episode"]), []).append((int(row["step"]), float(row[column])))
    return [np.array([u for _, u in sorted(steps)]) for _, steps in sorted(rows.items())]


def _calibrate_on_rollouts(cfg: CalibrateConfig) -> CalibrationConfig:
    source = Path(cfg.policy.pretrained_path)
    output_dir = _output_dir(source, cfg.output_dir, cfg.in_place)
    info = json.loads(Path(cfg.rollouts).read_text())
    traces, and_traces = None, None
    trace_file = Path(cfg.rollouts).with_name("uncertainty_trace.csv")
    if cfg.threshold in BANDS or cfg.window > 1 or cfg.and_scores or cfg.or_scores:
        traces = read_traces(trace_file)
    if cfg.and_scores:
        and_traces = {name: read_traces(trace_file, f"u_{name}") for name in cfg.and_scores}
    or_traces = {name: read_traces(trace_file, f"u_{name}") for name in cfg.or_scores} or None
    calibration = gamma_from_rollouts(
        cfg.policy.calibration,
        info,
        cfg.conformal_alpha,
        str(cfg.rollouts),
        cfg.policy.uncertainty_score,
        threshold=cfg.threshold,
        traces=traces,
        policy_config=cfg.policy,
        recording=recorded[1] if (recorded := training_recording(source)) else None,
        window=cfg.window,
        window_aggregate=cfg.window_aggregate,
        and_traces=and_traces,
        episodes=cfg.rollout_episodes,
        or_traces=or_traces,
        or_window=cfg.or_window,
        or_margin=cfg.or_margin,
    )
    policy = VIBPolicy.from_pretrained(source, config=cfg.policy)
    preprocessor, _ = make_pre_post_processors(policy.config, pretrained_path=str(source))
    _write(policy, preprocessor, calibration, source, output_dir)
    if cfg.push_to_hub:
        push_calibrated(output_dir, cfg.repo_id)
    print(
        f"Calibrated {output_dir}: gamma={calibration.gamma:.4f} "
        + (
            f"(the largest value of a time-indexed band over {len(calibration.gamma_band)} steps, alpha="
            f"{cfg.conformal_alpha}, from the per-step u of {len(info['per_episode'])} rollouts in {cfg.rollouts}; "
            if calibration.gamma_band
            else f"(split conformal at alpha={cfg.conformal_alpha} on the max u of {len(info['per_episode'])} "
            f"rollouts in {cfg.rollouts}; "
        )
        + f"{100 * calibration.episodes_above_gamma:.0f}% of them exceed it"
        + (f"; on u's {cfg.window_aggregate} over {cfg.window} steps" if cfg.window > 1 else "")
        + (
            f"; OR {', '.join(f'{k} above {g:.4g}' for k, g in calibration.or_gammas.items())}, every threshold at "
            f"alpha / {len(calibration.or_gammas) + 1}"
            + (f", the OR's at {cfg.or_margin:g} times theirs" if cfg.or_margin != 1 else "")
            if calibration.or_gammas
            else ""
        )
        + "). R_bar={calibration.rate_mean:.6g} "
        "is unchanged."
    )
    return calibration


def push_calibrated(checkpoint: Path, repo_id: str) -> None:
    """Push a calibrated checkpoint folder to the Hub as LeRobot pushes a trained one: weights, config (with the
    calibration), train config, model card, processors."""
    from lerobot.configs.train import TrainPipelineConfig

    if not (checkpoint / "train_config.json").is_file():
        raise VIBConfigError(f"{checkpoint} has no train_config.json, which LeRobot's Hub push writes with the model.")
    policy = VIBPolicy.from_pretrained(checkpoint)
    policy.config.repo_id = repo_id
    policy.push_model_to_hub(TrainPipelineConfig.from_pretrained(checkpoint))
    preprocessor, postprocessor = make_pre_post_processors(policy.config, pretrained_path=str(checkpoint))
    preprocessor.push_to_hub(repo_id)
    postprocessor.push_to_hub(repo_id)
    print(f"Pushed {checkpoint} to {huggingface_hub.constants.ENDPOINT}/{repo_id}")


def _write(policy: VIBPolicy, preprocessor, calibration: CalibrationConfig, source: Path, output_dir: Path) -> None:
    policy.config.calibration = calibration
    if output_dir != source:
        if source.is_dir():
            shutil.copytree(source, output_dir, dirs_exist_ok=True)
        else:  # a Hub checkpoint: the processors come along with the policy files
            preprocessor.save_pretrained(output_dir)
            _, postprocessor = make_pre_post_processors(policy.config, pretrained_path=str(source))
            postprocessor.save_pretrained(output_dir)
    policy.save_pretrained(output_dir)
    _update_train_config(output_dir, policy.config)


def main() -> None:
    os.environ.setdefault("MUJOCO_GL", "egl")
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
    register_third_party_plugins()
    try:
        calibrate_main()
    except VIBConfigError as e:
        sys.exit(f"lerobot-vib-calibrate: {e}")


if __name__ == "__main__":
    main()
