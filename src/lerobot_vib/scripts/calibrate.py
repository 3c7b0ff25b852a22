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

import json
import logging
import math
import os
import shutil
import sys
from dataclasses import asdict, dataclass, replace
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
    conformal_gamma,
    conformal_min_scores,
    mean_plus_2std_gamma,
    rate_statistics,
)
from ..configuration_vib import CalibrationConfig, VIBConfigError
from ..modeling_vib import VIBPolicy

logger = logging.getLogger(__name__)


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
        off): gamma becomes the conformal threshold at `conformal_alpha` on their per-episode max u.
    batch_size: Frames per forward pass.
    num_workers: DataLoader workers.
    output_dir: Where to write the calibrated checkpoint (default: `<checkpoint>_calibrated` beside a local
        checkpoint). An existing folder is only written if it is a calibrated checkpoint itself.
    in_place: Write the calibration into the checkpoint itself (`config.json` and `train_config.json`, so that
        `lerobot-train --resume=true` keeps it) instead of a new folder.
    """

    dataset: CalibrationDataset | None = None
    policy: PreTrainedConfig | None = None
    episodes: list[int] | None = None
    conformal_alpha: float | None = None
    conformal_episodes: list[int] | None = None
    rollouts: Path | None = None
    batch_size: int = 32
    num_workers: int = 0
    output_dir: Path | None = None
    in_place: bool = False

    def __post_init__(self):
        # Arguments first: nothing below may cost minutes before a typo is reported.
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
) -> CalibrationConfig:
    """Rate statistics of `policy` (eval mode) over the dataset's episodes, and gamma."""
    if conformal_episodes is not None and episodes is not None and set(conformal_episodes) & set(episodes):
        raise ValueError(
            "Held-out conformal episodes must not be among the calibration episodes: "
            f"{sorted(set(conformal_episodes) & set(episodes))}."
        )
    policy.eval()
    needed = list(policy._used_inputs)

    def encode_rate(batch: dict) -> torch.Tensor:
        obs = preprocessor({k: v for k, v in batch.items() if k.startswith("observation")})
        policy._check_observation(obs)
        return policy._encode(obs)[1]

    common = dict(revision=revision, video_backend=video_backend, batch_size=batch_size, num_workers=num_workers)
    loader = _loader(repo_id, root, episodes, needed=needed, **common)
    stats = rate_statistics(encode_rate, tqdm(loader, desc="rate statistics", unit="batch"))
    calibration = CalibrationConfig(
        dataset_repo_id=repo_id,
        episodes=sorted(set(stats.episode_index.tolist())),
        n_frames=int(stats.rates.numel()),
        rate_mean=stats.mean,
        rate_std=stats.std,
        rate_quantiles=stats.quantiles(QUANTILE_LEVELS),
        gamma=mean_plus_2std_gamma(stats.mean, stats.std),
        gamma_method="mean_plus_2std",
    )
    if conformal_alpha is not None:
        loader = _loader(repo_id, root, conformal_episodes, needed=needed, **common)
        held_out = rate_statistics(encode_rate, tqdm(loader, desc="held-out episodes", unit="batch"))
        calibration.gamma = conformal_gamma(held_out.episode_max(scale=stats.mean), conformal_alpha)
        calibration.gamma_method = "conformal"
        calibration.conformal_alpha = conformal_alpha
        calibration.conformal_episodes = sorted(set(held_out.episode_index.tolist()))
    u = stats.rates / stats.mean
    calibration.frames_above_gamma = float((u > calibration.gamma).double().mean())
    calibration.episodes_above_gamma = float((stats.episode_max(stats.mean) > calibration.gamma).double().mean())
    return calibration


def gamma_from_rollouts(calibration: CalibrationConfig, info: dict, alpha: float, source: str) -> CalibrationConfig:
    """`calibration` with gamma = the split-conformal threshold on clean rollouts' per-episode max u."""
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
    rate_mean = info.get("rate_mean")
    if rate_mean is None or not math.isclose(rate_mean, calibration.rate_mean, rel_tol=1e-4):
        raise VIBConfigError(
            f"{source} holds u normalized by R_bar={rate_mean}, this checkpoint has R_bar={calibration.rate_mean:.6g}: "
            "evaluate this checkpoint (the calibrated one) and calibrate on those rollouts."
        )
    unknown = [ep.get("seed") for ep in info["per_episode"] if ep["u_max"] is None or not math.isfinite(ep["u_max"])]
    if unknown:
        # Dropping them would set gamma on the rollouts that went well; a clean rollout with no finite u is a bug.
        raise VIBConfigError(
            f"{source} has rollouts without a finite max u (seeds {unknown}): fix them, then calibrate."
        )
    scores = [ep["u_max"] for ep in info["per_episode"]]
    needed = conformal_min_scores(alpha)
    if len(scores) < needed:
        raise VIBConfigError(
            f"A conformal threshold at alpha={alpha} needs at least {needed} rollouts; {source} has {len(scores)}."
        )
    gamma = conformal_gamma(np.asarray(scores), alpha)
    return replace(
        calibration,
        gamma=gamma,
        gamma_method="conformal_rollouts",
        conformal_alpha=alpha,
        conformal_episodes=None,
        rollout_seeds=[ep["seed"] for ep in info["per_episode"] if ep.get("seed") is not None],
        frames_above_gamma=None,
        episodes_above_gamma=float(np.mean([s > gamma for s in scores])),
    )


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
    check_episodes(meta.total_episodes, episodes=cfg.episodes, conformal_episodes=cfg.conformal_episodes)
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
    )
    _write(policy, preprocessor, calibration, source, output_dir)
    quantiles = ", ".join(f"q{k}={v:.4g}" for k, v in calibration.rate_quantiles.items())
    print(
        f"Calibrated {output_dir} on {calibration.n_frames} frames of {len(calibration.episodes)} episodes of "
        f"{calibration.dataset_repo_id}:\n  R_bar={calibration.rate_mean:.6g}  std={calibration.rate_std:.4g}  "
        f"{quantiles}\n  gamma={calibration.gamma:.4f} ({calibration.gamma_method}"
        + (f", alpha={calibration.conformal_alpha}" if calibration.conformal_alpha is not None else "")
        + f")\n  on these frames: u > gamma on {100 * calibration.frames_above_gamma:.1f}% of frames and in "
        f"{100 * calibration.episodes_above_gamma:.0f}% of episodes (a stop would interrupt them)"
    )
    return calibration


def _calibrate_on_rollouts(cfg: CalibrateConfig) -> CalibrationConfig:
    source = Path(cfg.policy.pretrained_path)
    output_dir = _output_dir(source, cfg.output_dir, cfg.in_place)
    info = json.loads(Path(cfg.rollouts).read_text())
    calibration = gamma_from_rollouts(cfg.policy.calibration, info, cfg.conformal_alpha, str(cfg.rollouts))
    policy = VIBPolicy.from_pretrained(source, config=cfg.policy)
    preprocessor, _ = make_pre_post_processors(policy.config, pretrained_path=str(source))
    _write(policy, preprocessor, calibration, source, output_dir)
    print(
        f"Calibrated {output_dir}: gamma={calibration.gamma:.4f} (split conformal at alpha={cfg.conformal_alpha} on "
        f"the max u of {len(info['per_episode'])} rollouts in {cfg.rollouts}; "
        f"{100 * calibration.episodes_above_gamma:.0f}% of them exceed it). R_bar={calibration.rate_mean:.6g} "
        "is unchanged."
    )
    return calibration


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
