"""`lerobot-vib-benchmark`: the paper's evaluation (Table I's rows, RND, perturbed conditions, uncertainty) in
one resumable command, for any recorded dataset and env.

    lerobot-vib-benchmark --dataset.repo_id=local/vib_arm_grasp_block_scripted --dataset.root=data/arm_grasp_block \
        --env.type=vib_arm --env.dataset_root=data/arm_grasp_block --profile=cpu-small --output_dir=outputs/bench_arm

Stages, each saved as it finishes so that a stopped benchmark resumes where it stopped:

For each training seed (`--train_seeds`):

1. train: every network the rows need (variants.NETWORKS: VIB from the profile's preset, VIB with beta = 0,
   ACT with the same sizes, recipe and budget, ACT with VIB's trunk treatment), each by `lerobot-train` (an
   interrupted training resumes with LeRobot's `--resume=true`); or given checkpoints (`--vib_checkpoint`,
   `--vib_tokens_checkpoint`, `--act_checkpoint`, one training seed only).
2. RND (rnd.py) on the training dataset, normalized by the VIB checkpoint's preprocessor, if a row needs it.
3. validation: clean rollouts on the validation seeds. Every choice is made here and only here: the run time
   of each row whose run time is chosen (among `--runtimes`, per trained network), and the thresholds of the
   scored rows (judged on these rollouts' u). The choices are written to `choices.json` with their seeds.
4. test: every row under every condition on the test seeds, the same seeds per condition for every row,
   through LeRobot's eval loop (`lerobot_eval.eval_policy`), recording u at every step. Nothing is chosen here.

Then the report (benchmark_report.py): `report.md`, `results.json` and the plots, with success pooled over the
training seeds (Wilson interval) and its mean and range over them. Validation and test seeds must not overlap:
a configuration whose choices would see test episodes is refused before any work.

Conditions: normal; gaussian (noise std drawn from {0, 0.05, 0.1}); color (jitter 0.2 with probability 0.5);
black, dim and frozen images; on the simulated arm also camera_shake, unseen_block and occlusion
(sim/perturbations.py).

Before evaluating, each VIB network is calibrated on the training data (`--calibrate`), so that its cells hold
every score per step; the report's failure prediction (failure_report.py) reads them.
"""

import contextlib
import dataclasses
import fcntl
import hashlib
import json
import logging
import math
import os
import platform
import shutil
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from lerobot import envs
from lerobot.configs import parser
from lerobot.configs.default import DatasetConfig
from lerobot.configs.policies import PreTrainedConfig
from lerobot.envs.factory import make_env, make_env_pre_post_processors
from lerobot.envs.utils import close_envs
from lerobot.policies.factory import make_pre_post_processors
from lerobot.scripts import lerobot_eval
from lerobot.utils.import_utils import register_third_party_plugins
from lerobot.utils.utils import init_logging
from tqdm import tqdm

from ..calibration import mean_plus_2std_gamma
from ..configuration_vib import VIBConfigError
from ..failure import BAND_FLAGS, AnyOf, CalibratedAnyOf, CalibratedMonitor, Monitor, evaluate, monitor_from_dict
from ..modeling_vib import VIBPolicy
from ..provenance import env_record, training_recording
from ..rnd import RND, RNDConfig, train_rnd
from ..sim import env_config  # noqa: F401  (registers --env.type=aloha_fast and vib_arm)
from ..sim.perturbations import CONDITIONS, SCENE_CONDITIONS
from ..variants import (
    ACT_TRUNK,
    ACT_TRUNK_L2,
    ACT_TRUNK_L3,
    CHOSEN,
    COLOUR_AUGMENTATION,
    COMPARISON,
    NARROW_LOGVAR_INIT,
    NETWORKS,
    TOKEN_COMPARISON,
    VARIANTS,
    VIB_TRUNK_L3,
    build_variant,
    parse_runtime,
    queue_steps,
    samples,
)
from .benchmark_report import runtime_of, write_report
from .calibrate import _write, calibrate, gamma_from_rollouts
from .eval_uncertainty import UncertaintyCapture, write_embeddings
from .failure_report import cell_episodes

logger = logging.getLogger(__name__)

CONFIGS = Path(__file__).resolve().parents[3] / "configs" / "policy"

# ACT's fields for VIB's, so that both train with one architecture and recipe.
ACT_FROM_VIB = {
    "chunk_size": "chunk_size",
    "n_action_steps": "n_action_steps",
    "dim_model": "dim_model",
    "n_heads": "n_heads",
    "dim_feedforward": "dim_feedforward",
    "n_layers": "n_encoder_layers",
    "dropout": "dropout",
    "optimizer_lr": "optimizer_lr",
    "optimizer_lr_backbone": "optimizer_lr_backbone",
    "optimizer_weight_decay": "optimizer_weight_decay",
}

VALIDATION = "validation"  # clean rollouts on the validation seeds: every choice, the thresholds included
PERTURBED = "validation:"  # + a condition: a scored VIB row's validation rollouts under it (failure prediction)
# Table I's rows that get `n_episodes` on every condition; the others get `n_episodes_other`. The comparison
# rows get `n_episodes` on the normal condition and `n_episodes_other` under each perturbation.
MAIN_VARIANTS = ("vib", "act")
GIVEN = ("vib", "vib_tokens", "act")  # the networks a trained checkpoint can be given for (--<network>_checkpoint)
DEFAULT_RUNTIMES = ("queue", "act:0.01", "act:0.3")


@dataclass(frozen=True)
class Profile:
    """A budget. `presets`: the VIB train config (in configs/policy/) per env type; `steps` None keeps the
    preset's."""

    presets: dict[str, str]
    steps: int | None
    n_episodes: int
    n_episodes_other: int
    validation_episodes: int
    rnd_steps: int
    device: str


_GPU_PRESETS = {
    "vib_arm": "vib_arm_sim.json",
    "aloha_fast": "vib_aloha_transfer_cube.json",
    "aloha_fast/AlohaInsertion-v0": "vib_aloha_insertion.json",
}
PROFILES = {
    # This 2-core CPU, the simulated arm: VIB's 7000 steps took 41 min (arm_learning_near_l2_ema_cpu_2core/).
    # On ALOHA (aloha_fast) the CPU recipe: 120x160, chunk 50, trunk from scratch.
    "cpu-small": Profile({"vib_arm": "vib_arm_sim.json", "aloha_fast": "vib_cpu.json"}, None, 50, 20, 20, 2000, "cpu"),
    # A lent H100 within 25 minutes of device time: the ALOHA preset shortened.
    "gpu": Profile(_GPU_PRESETS, 20000, 50, 20, 20, 5000, "cuda"),
    # The paper's settings: 480x640, its training length, 100 episodes per cell.
    "paper": Profile(_GPU_PRESETS, None, 100, 100, 40, 20000, "cuda"),
}


@dataclass
class BenchmarkConfig:
    """Args:
    dataset: The recorded training dataset (`--dataset.repo_id`, `--dataset.root`).
    env: The evaluation env (`--env.type=vib_arm --env.dataset_root=...` reuses a recording's settings).
    output_dir: Where checkpoints, cells, the report and the plots go; rerun the command to resume.
    profile: `cpu-small`, `gpu` or `paper` (PROFILES); the fields below left unset take the profile's value.
    variants: Rows (variants.VARIANTS); default the paper's Table I. `[comparison]` stands for the four rows
        that separate the bottleneck from VIB's other choices (variants.COMPARISON), `[tokens]` for the five
        that put it on ACT's token memory (variants.TOKEN_COMPARISON).
    conditions: Default: normal, gaussian, color, black, dim, frozen, and on the simulated arm camera_shake,
        unseen_block, occlusion.
    n_episodes: Test episodes per cell for VIB (Eq. 6), ACT and the comparison rows, and for every row on the
        normal condition.
    n_episodes_other: Test episodes per cell for the other rows and conditions.
    validation_episodes: Clean validation rollouts per row, run time and training seed: the run time is chosen
        on them, and the thresholds of a scored row are set on them.
    runtimes: The run times a comparison row chooses from on validation (variants.parse_runtime): "queue"
        (the checkpoint's action queue; half a chunk when the preset ensembles), "act:<m>" (ACT's temporal
        ensembling), "eq6:<m>" (Eq. 6, scored rows only), each with an optional "+sample" (a VIB network
        decodes a posterior sample at every step, its training input, instead of the posterior mean; ACT rows
        skip these). The most validation successes wins; a tie goes to the one listed first.
    preset: The VIB train config (`lerobot-train --config_path`); ACT copies its architecture and recipe.
    steps: Training steps of every network.
    save_freq: Steps between saved training checkpoints: an interrupted training resumes from the last one.
    rnd_steps: Training steps of the RND predictor.
    vib_checkpoint, vib_tokens_checkpoint, act_checkpoint: Trained `pretrained_model` folders to evaluate
        instead of training the network of that name (variants.NETWORKS).
    device: Where training and evaluation run.
    eval_batch_size: Envs per rollout batch.
    alpha: Level of the conformal thresholds (false-stop rate bound on in-distribution episodes).
    train_seeds: Training seeds: every network is trained once per seed, and every cell evaluated per seed.
    validation_seed: The first validation episode seed (every choice). test_seed: the first test episode seed
        (every reported number). The two ranges must not overlap.
    calibrate: Calibrate each trained VIB network on the training dataset before evaluating it (every score's
        training statistics and fitted parts, as `lerobot-vib-calibrate` does), so that every cell records every
        score per step and failure prediction can compare them. false: the rate only, normalized by
        training's running mean (runs made before this field).
    failure_alphas: The false-alarm levels swept for failure prediction's TPR-against-TNR curves; `alpha` is
        the level its tables report.
    failure_validation: Also roll out each scored VIB row under every perturbed condition on the first
        `n_episodes_other` validation seeds, so that failure prediction chooses its monitor seeing successes
        under perturbations the policy handles (negatives) and failures under those it does not. Thresholds
        are still set on successful clean validation rollouts only; the test seeds stay unseen.
    train_only: Train every network for every seed, then stop (train where a GPU is, evaluate elsewhere).
    report_only: Write the report from the cells on disk, running nothing (a partial run's report says which
        cells it lacks).
    """

    dataset: DatasetConfig
    env: envs.EnvConfig
    output_dir: Path = Path("outputs/benchmark")
    profile: str = "cpu-small"
    variants: list[str] = field(default_factory=lambda: list(VARIANTS))
    conditions: list[str] | None = None
    n_episodes: int | None = None
    n_episodes_other: int | None = None
    validation_episodes: int | None = None
    runtimes: list[str] = field(default_factory=lambda: list(DEFAULT_RUNTIMES))
    preset: Path | None = None
    steps: int | None = None
    save_freq: int = 1000
    rnd_steps: int | None = None
    vib_checkpoint: Path | None = None
    vib_tokens_checkpoint: Path | None = None
    act_checkpoint: Path | None = None
    device: str | None = None
    eval_batch_size: int = 10
    alpha: float = 0.1
    calibrate: bool = True
    failure_validation: bool = True
    failure_alphas: list[float] = field(default_factory=lambda: [0.02, 0.05, 0.1, 0.2, 0.3, 0.5])
    train_seeds: list[int] = field(default_factory=lambda: [1000])
    validation_seed: int = 400_000
    test_seed: int = 600_000
    train_only: bool = False
    report_only: bool = False

    def __post_init__(self):
        if self.profile not in PROFILES:
            raise VIBConfigError(f"Unknown --profile={self.profile!r}; choose from {sorted(PROFILES)}.")
        p = PROFILES[self.profile]
        for name in ("n_episodes", "n_episodes_other", "validation_episodes", "steps", "rnd_steps", "device"):
            if getattr(self, name) is None:
                setattr(self, name, getattr(p, name))
        if self.preset is None:
            env_type, task = getattr(self.env, "type", None), getattr(self.env, "task", None)
            name = p.presets.get(f"{env_type}/{task}", p.presets.get(env_type))
            if name is None:
                raise VIBConfigError(
                    f"--profile={self.profile} has no preset for --env.type={env_type}: give --preset=<train config>."
                )
            self.preset = CONFIGS / name
        if self.variants == ["comparison"]:
            self.variants = list(COMPARISON)
        elif self.variants == ["tokens"]:
            self.variants = list(TOKEN_COMPARISON)
        if unknown := sorted(set(self.variants) - set(VARIANTS)):
            raise VIBConfigError(
                f"Unknown variants {unknown}; choose from {sorted(VARIANTS)}, [comparison] or [tokens]."
            )
        scene = getattr(self.env, "type", None) == "vib_arm"
        if self.conditions is None:
            self.conditions = [c for c in CONDITIONS if scene or c not in SCENE_CONDITIONS]
        if unknown := sorted(set(self.conditions) - set(CONDITIONS)):
            raise VIBConfigError(f"Unknown conditions {unknown}; choose from {sorted(CONDITIONS)}.")
        if not scene and (needs_scene := [c for c in self.conditions if c in SCENE_CONDITIONS]):
            raise VIBConfigError(f"Conditions {needs_scene} need the simulated arm's scene (--env.type=vib_arm).")
        if not hasattr(self.env, "perturbation"):
            raise VIBConfigError(
                f"--env.type={self.env.type} takes no perturbations; use aloha_fast or vib_arm (lerobot_vib.sim)."
            )
        for name in ("n_episodes", "n_episodes_other", "validation_episodes", "eval_batch_size"):
            if getattr(self, name) < 1:
                raise VIBConfigError(f"--{name} must be >= 1, got {getattr(self, name)}.")
        self._check_protocol()
        for alpha in (self.alpha, *self.failure_alphas):
            if not 0 < alpha < 1:
                raise VIBConfigError(f"--alpha and --failure_alphas must be in (0, 1), got {alpha}.")
        if not self.preset.exists():
            raise VIBConfigError(f"The VIB preset {self.preset} does not exist: give --preset=<train config>.")
        if self.steps is None:
            self.steps = json.loads(self.preset.read_text())["steps"]

    def _check_protocol(self) -> None:
        """Choices on validation seeds, numbers on test seeds, never the same episodes; run times that parse."""
        if not self.train_seeds or len(set(self.train_seeds)) != len(self.train_seeds):
            raise VIBConfigError(f"--train_seeds must be distinct and at least one, got {self.train_seeds}.")
        validation, test = self.validation_seeds(), self.test_seeds()
        if shared := sorted(set(validation) & set(test)):
            raise VIBConfigError(
                f"The validation seeds {validation[0]}..{validation[-1]} overlap the test seeds "
                f"{test[0]}..{test[-1]} ({len(shared)} shared, from {shared[0]}): the run times and thresholds "
                "would be chosen on episodes the report measures. Give --validation_seed and --test_seed ranges "
                "that do not overlap."
            )
        if not self.runtimes:
            raise VIBConfigError("--runtimes must name at least one run time (queue, act:<m>, eq6:<m>).")
        for spec in self.runtimes:
            try:
                parse_runtime(spec)
            except ValueError as e:
                raise VIBConfigError(f"--runtimes: {e}") from None
        chosen_unscored = [v for v in self.variants if VARIANTS[v].ensemble == CHOSEN and VARIANTS[v].score is None]
        if chosen_unscored and any(spec.startswith("eq6") for spec in self.runtimes):
            raise VIBConfigError(f"Eq. 6 needs a u: rows {chosen_unscored} have none; drop eq6 from --runtimes.")
        given = [f"{n}_checkpoint" for n in GIVEN if getattr(self, f"{n}_checkpoint") is not None]
        if given and len(self.train_seeds) > 1:
            raise VIBConfigError(f"--{given[0]} is one trained network: it takes a single --train_seeds value.")

    def validation_seeds(self) -> list[int]:
        return list(range(self.validation_seed, self.validation_seed + self.validation_episodes))

    def test_seeds(self) -> list[int]:
        return list(range(self.test_seed, self.test_seed + max(self.n_episodes, self.n_episodes_other)))

    def networks(self) -> list[str]:
        """The trained networks the rows need, in NETWORKS' order."""
        used = {m for v in self.variants for m in (VARIANTS[v].chunks, VARIANTS[v].score)}
        return [n for n in NETWORKS if n in used]

    def needs(self, network: str) -> bool:
        if network == "rnd":
            return any(VARIANTS[v].score == "rnd" for v in self.variants)
        return network in self.networks()

    def episodes(self, variant: str, condition: str) -> int:
        if condition == VALIDATION:
            return self.validation_episodes
        if condition.startswith(PERTURBED):
            return min(self.n_episodes_other, self.validation_episodes)
        if variant in COMPARISON or variant in TOKEN_COMPARISON:  # the claims' rows: the most episodes
            return self.n_episodes if condition == "normal" else self.n_episodes_other
        return self.n_episodes if variant in MAIN_VARIANTS else self.n_episodes_other

    def validated(self, variant: str) -> list[str]:
        """The run times a row is rolled out with on validation: its candidates, or its own run time when it
        is scored (its thresholds are set there), or none."""
        v = VARIANTS[variant]
        if v.ensemble == CHOSEN:  # a "+sample" run time is a VIB network's only
            return [rt for rt in self.runtimes if NETWORKS[v.chunks] == "vib" or not samples(rt)]
        return [v.runtime()] if v.score is not None else []


# ----------------------------------------------------------------------------------------------------- training


def _bin(name: str) -> str:
    return str(Path(sys.executable).parent / name)


# What the ACT like VIB baseline copies from the VIB preset (baselines/configuration_act_like_vib.py).
LIKE_VIB_FIELDS = ("backbone_norm", "backbone_layer", "ema_decay", "normalization_floor")


def train_command(network: str, cfg: BenchmarkConfig, out: Path, seed: int) -> list[str]:
    """The `lerobot-train` command of one network (variants.NETWORKS) at one training seed."""
    common = [
        f"--dataset.repo_id={cfg.dataset.repo_id}",
        *([f"--dataset.root={cfg.dataset.root}"] if cfg.dataset.root else []),
        f"--output_dir={out}",
        f"--seed={seed}",
        f"--steps={cfg.steps}",
        f"--save_freq={min(cfg.save_freq, cfg.steps)}",
        "--env_eval_freq=0",
        f"--policy.device={cfg.device}",
    ]
    if network == "vib":
        return [_bin("lerobot-train"), f"--config_path={cfg.preset}", *common]
    if network == "vib_beta0":
        return [_bin("lerobot-train"), f"--config_path={cfg.preset}", "--policy.beta=0", *common]
    if network.startswith("vib_tokens"):
        narrow = [f"--policy.posterior_logvar_init={NARROW_LOGVAR_INIT}"]
        extra = {
            "vib_tokens": [],
            "vib_tokens_beta0": ["--policy.beta=0"],
            "vib_tokens_narrow": narrow,
            "vib_tokens_narrow_beta0": [*narrow, "--policy.beta=0"],
            "vib_tokens_narrow_act_trunk": [*narrow, *(f"--policy.{k}={v}" for k, v in ACT_TRUNK.items())],
            "vib_tokens_narrow_act_trunk_l3": [*narrow, *(f"--policy.{k}={v}" for k, v in ACT_TRUNK_L3.items())],
            "vib_tokens_narrow_act_trunk_l2": [*narrow, *(f"--policy.{k}={v}" for k, v in ACT_TRUNK_L2.items())],
            "vib_tokens_narrow_l3": [*narrow, *(f"--policy.{k}={v}" for k, v in VIB_TRUNK_L3.items())],
            "vib_tokens_narrow_act_trunk_l2_colour": [
                *narrow,
                *(f"--policy.{k}={v}" for k, v in ACT_TRUNK_L2.items()),
                *transform_flags(COLOUR_AUGMENTATION),
            ],
        }[network]
        return [_bin("lerobot-train"), f"--config_path={cfg.preset}", "--policy.encoder=tokens", *extra, *common]
    if network not in ("act", "act_colour", "act_like_vib", "act_like_vib_nofloor"):
        raise ValueError(f"Unknown network {network!r}; choose from {list(NETWORKS)}.")
    preset = json.loads(cfg.preset.read_text())
    run = [f"--{k}={preset[k]}" for k in ("batch_size", "num_workers", "log_freq") if k in preset]
    extra = []  # what the row changes in ACT as it is
    if network == "act_colour":  # the colour row's control: ACT on its randomized frames
        extra = transform_flags(COLOUR_AUGMENTATION)
    elif network != "act":
        policy = dict(preset["policy"])
        if network == "act_like_vib_nofloor":
            policy["normalization_floor"] = None
        extra = [
            f"--policy.{k}={'null' if policy.get(k) is None else policy[k]}" for k in LIKE_VIB_FIELDS if k in policy
        ]
    return [
        _bin("lerobot-train"),
        f"--policy.type={'act' if network in ('act', 'act_colour') else 'act_like_vib'}",
        "--policy.push_to_hub=false",
        "--policy.pretrained_backbone_weights=null",
        *act_recipe_flags(preset),
        *extra,
        *run,
        "--wandb.enable=false",
        *common,
    ]


def act_recipe_flags(preset: dict) -> list[str]:
    """`lerobot-train` flags that give ACT the VIB preset's sizes and training recipe.

    The sizes and learning rates through `ACT_FROM_VIB`; the preset's image augmentation
    (`dataset.image_transforms`) as it is; and its learning-rate schedule, which ACT's own preset lacks, as an
    explicit optimizer and scheduler (`use_policy_training_preset=false`), so both networks see the same
    learning rate at every step.
    """
    policy = dict(preset["policy"])
    # ACT's own row runs its action queue: a preset that ensembles (n_action_steps 1) gives it half a chunk.
    ensembles = policy.get("temporal_ensemble", "none") != "none"
    policy["n_action_steps"] = queue_steps(policy["chunk_size"], policy.get("n_action_steps", 1), ensembles)
    flags = [f"--policy.{ACT_FROM_VIB[k]}={v}" for k, v in policy.items() if k in ACT_FROM_VIB]
    flags += transform_flags(preset.get("dataset", {}).get("image_transforms") or {})
    if policy.get("scheduler_warmup_steps") is not None:
        flags += [
            "--use_policy_training_preset=false",
            "--optimizer.type=adamw",
            f"--optimizer.lr={policy['optimizer_lr']}",
            f"--optimizer.weight_decay={policy['optimizer_weight_decay']}",
            "--scheduler.type=cosine_annealing_with_warmup",
            f"--scheduler.num_warmup_steps={policy['scheduler_warmup_steps']}",
        ]
    return flags


def transform_flags(transforms: dict) -> list[str]:
    """`lerobot-train` flags that set LeRobot's `dataset.image_transforms` fields to `transforms`."""
    return [
        f"--dataset.image_transforms.{k}={json.dumps(v) if isinstance(v, dict) else str(v).lower()}"
        for k, v in transforms.items()
    ]


def given_checkpoint(network: str, cfg: BenchmarkConfig) -> Path | None:
    return getattr(cfg, f"{network}_checkpoint") if network in GIVEN else None


def train_dir(cfg: BenchmarkConfig, network: str, seed: int) -> Path:
    return cfg.output_dir / "train" / network / f"seed_{seed}"


def train(network: str, cfg: BenchmarkConfig, seed: int) -> Path:
    """The trained checkpoint's `pretrained_model`, training (or resuming) with `lerobot-train` if needed."""
    given = given_checkpoint(network, cfg)
    if given is not None:
        check_given_checkpoint(Path(given), cfg)
        return Path(given)
    out = train_dir(cfg, network, seed)
    # Another invocation on this output dir may be training the same network: wait for it, then reuse it.
    with _locked(out.parent, f"{out.name}.lock"):
        return _train(network, cfg, seed, out)


def _train(network: str, cfg: BenchmarkConfig, seed: int, out: Path) -> Path:
    final = out / "checkpoints" / f"{cfg.steps:06d}" / "pretrained_model"
    if final.exists():
        return final
    last = out / "checkpoints" / "last" / "pretrained_model"
    cmd = train_command(network, cfg, out, seed)
    if last.exists():  # an interrupted training
        cmd = [cmd[0], f"--config_path={last / 'train_config.json'}", "--resume=true"]
    elif out.exists():  # lerobot-train refuses an existing output dir without a checkpoint to resume
        raise VIBConfigError(f"{out} exists without a checkpoint to resume from: move it away and rerun.")
    log = out.with_name(f"{out.name}.log")
    log.parent.mkdir(parents=True, exist_ok=True)
    with out.with_name(f"{out.name}_command.txt").open("a") as f:
        # as a user types it: the command's name, paths under the project relative to it
        shown = [Path(cmd[0]).name] + [
            f"{k}={_portable(v)}" if v.startswith("/") else a for a in cmd[1:] for k, _, v in [a.partition("=")]
        ]
        f.write(" ".join(shown) + "\n")
    logger.info("Training %s, seed %d (log: %s): %s", network, seed, log, " ".join(cmd))
    with log.open("a") as f:
        result = subprocess.run(cmd, stdout=f, stderr=subprocess.STDOUT, env={**os.environ})
    if result.returncode != 0 or not final.exists():
        raise RuntimeError(f"Training {network}, seed {seed} failed (exit {result.returncode}); see {log}.")
    return final


def calibrated(network: str, cfg: BenchmarkConfig, seed: int, path: Path) -> Path:
    """The VIB checkpoint with every score's training statistics: itself when it is calibrated already, else a
    calibrated copy under calibrated/<network>/seed_<seed>/ (made once; the trained checkpoint is left as it is)."""
    if (PreTrainedConfig.from_pretrained(path).calibration.score_means or {}) != {}:
        return path
    out = cfg.output_dir / "calibrated" / network / f"seed_{seed}"
    with _locked(out.parent, f"{out.name}.lock"):
        if (out / "config.json").exists():
            return out
        logger.info("Calibrating %s, seed %d, on %s (every score's statistics).", network, seed, cfg.dataset.repo_id)
        policy = VIBPolicy.from_pretrained(path)
        preprocessor, _ = make_pre_post_processors(policy.config, pretrained_path=str(path))
        calibration = calibrate(
            policy, preprocessor, cfg.dataset.repo_id, root=cfg.dataset.root, rnd_steps=cfg.rnd_steps
        )
        staging = out.with_name(f"{out.name}.partial")
        shutil.rmtree(staging, ignore_errors=True)  # an interrupted calibration of this same copy
        _write(policy, preprocessor, calibration, path, staging)
        staging.replace(out)  # the folder exists only when complete
    return out


def check_given_checkpoint(path: Path, cfg: BenchmarkConfig) -> None:
    """Refuse a given checkpoint whose recorded choices (its threshold's rollouts) saw this run's test seeds."""
    config_file = path / "config.json"
    if not config_file.exists():
        raise VIBConfigError(f"{path} is not a trained policy folder: it has no config.json.")
    calibration = json.loads(config_file.read_text()).get("calibration") or {}
    seen = set(calibration.get("rollout_seeds") or [])
    if shared := sorted(seen & set(cfg.test_seeds())):
        raise VIBConfigError(
            f"{path}'s stop threshold was set on rollouts with {len(shared)} of this run's test seeds (from "
            f"{shared[0]}): it was chosen on the episodes the report would measure. Give --test_seed a range it "
            "has not seen."
        )


def fit_rnd(cfg: BenchmarkConfig, vib_path: Path, vib: VIBPolicy, seed: int) -> RND:
    """RND on the training frames as the VIB policy sees them (its preprocessor), saved under rnd/seed_<seed>/."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    directory = cfg.output_dir / "rnd" / f"seed_{seed}"
    if (directory / "rnd.safetensors").exists():
        return RND.load(directory)
    preprocessor, _ = make_pre_post_processors(vib.config, pretrained_path=str(vib_path))
    dataset = LeRobotDataset(cfg.dataset.repo_id, root=cfg.dataset.root)
    image_keys = list(vib.config.image_features)
    state = vib.config.robot_state_feature
    rnd_cfg = RNDConfig(
        image_keys=image_keys,
        image_shape=list(vib.config.image_features[image_keys[0]].shape) if image_keys else [],
        state_key="observation.state" if state else None,
        state_dim=state.shape[0] if state else 0,
        steps=cfg.rnd_steps,
        seed=seed,
    )
    model = RND(rnd_cfg).to(cfg.device)

    def loader(shuffle: bool):
        generator = torch.Generator().manual_seed(seed)
        data = torch.utils.data.DataLoader(dataset, batch_size=rnd_cfg.batch_size, shuffle=shuffle, generator=generator)
        for batch in data:
            yield preprocessor(batch)

    bar = tqdm(total=rnd_cfg.steps, desc="RND", unit="step")
    train_rnd(
        model, lambda: loader(True), loader(False), lambda step, loss: (bar.update(1), bar.set_postfix(loss=loss))
    )
    bar.close()
    model.save(directory)
    return model.cpu() if cfg.device == "cpu" else model


# -------------------------------------------------------------------------------------------------------- cells


def cell_path(cfg: BenchmarkConfig, variant: str, condition: str, seed: int, runtime: str | None = None) -> Path:
    """A test cell: cells/<condition>/<variant>/seed_<seed>.json; a validation cell:
    validation/<variant>/seed_<seed>/<run time>.json; a perturbed validation cell (failure prediction):
    validation_perturbed/<condition>/<variant>/seed_<seed>.json."""
    if condition == VALIDATION:
        return cfg.output_dir / VALIDATION / variant / f"seed_{seed}" / f"{runtime.replace(':', '_')}.json"
    if condition.startswith(PERTURBED):
        return (
            cfg.output_dir / "validation_perturbed" / condition.removeprefix(PERTURBED) / variant / f"seed_{seed}.json"
        )
    return cfg.output_dir / "cells" / condition / variant / f"seed_{seed}.json"


def embeddings_path(cell_file: Path) -> Path:
    """Beside a traced VIB cell: its rollouts' observation embeddings per step (an RND fitted on clean
    rollouts reads them; failure_report.py)."""
    return cell_file.with_suffix(".embeddings.safetensors")


def env_condition(condition: str) -> str:
    """The perturbation (sim/perturbations.CONDITIONS) a cell's condition rolls out under."""
    if condition == VALIDATION:
        return "normal"
    return condition.removeprefix(PERTURBED)


def cell_seeds(cfg: BenchmarkConfig, variant: str, condition: str) -> list[int]:
    if condition == VALIDATION:
        return cfg.validation_seeds()
    if condition.startswith(PERTURBED):
        return cfg.validation_seeds()[: cfg.episodes(variant, condition)]
    return cfg.test_seeds()[: cfg.episodes(variant, condition)]


def run_cell(cfg: BenchmarkConfig, variant: str, condition: str, policy, processors: tuple) -> dict:
    """Evaluate one row under one condition with LeRobot's eval loop; u per step of every episode."""
    env_cfg = dataclasses.replace(cfg.env, perturbation=CONDITIONS[env_condition(condition)])
    seeds = cell_seeds(cfg, variant, condition)
    batch = min(cfg.eval_batch_size, len(seeds))
    vec_envs = make_env(env_cfg, n_envs=batch, use_async_envs=False)
    env = next(iter(next(iter(vec_envs.values())).values()))
    env_pre, env_post = make_env_pre_post_processors(env_cfg=env_cfg, policy_cfg=policy.config)
    start = time.time()
    try:
        with torch.no_grad(), UncertaintyCapture().capture() as record:
            info = lerobot_eval.eval_policy(
                env, policy, env_pre, env_post, *processors, n_episodes=len(seeds), start_seed=seeds[0]
            )
    finally:
        close_envs(vec_envs)
    episodes = record.kept(len(seeds), batch)
    per_episode = info["per_episode"]
    if [e["seed"] for e in per_episode] != seeds or [e["seed"] for e in episodes] != seeds:
        raise RuntimeError(f"Cell {condition}/{variant}: the evaluated seeds differ from {seeds[0]}..{seeds[-1]}.")
    scored = VARIANTS[variant].score is not None
    return {
        "variant": variant,
        "condition": condition,
        "seeds": seeds,
        "success": [bool(e["success"]) for e in per_episode],
        "max_reward": [float(e["max_reward"]) for e in per_episode],
        "steps": [len(e["u"]) for e in episodes],
        "score": VARIANTS[variant].score,
        "u": [np.round(e["u"].astype(float), 5).tolist() for e in episodes] if scored else None,
        "scores": _every_score(policy, episodes),
        "grasp_missed_at": [e.get("grasp_missed_at") for e in episodes],
        "wall_s": round(time.time() - start, 1),
        # popped before the cell is saved: they go to a file of their own (`embeddings_path`)
        "episodes": episodes,
    }


def _every_score(policy, episodes: list[dict]) -> dict[str, list[list[float]]] | None:
    """Every score a traced VIB row computed, as u = s / s_bar per step of each episode (None: not traced)."""
    if not getattr(policy, "trace_all_scores", False) or not episodes:
        return None
    out = {}
    for name in episodes[0]["scores"]:
        mean = policy.score_mean(name)
        if math.isfinite(mean) and mean > 0 and all(name in e["scores"] for e in episodes):
            out[name] = [np.round(e["scores"][name].astype(float) / mean, 5).tolist() for e in episodes]
    return out


def _write_json(path: Path, data: Any) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(data))
    tmp.replace(path)  # a cell file exists only when complete


def _merge_json(path: Path, entries: dict, lock_folder: Path) -> None:
    """Add `entries` to the JSON object at `path`: an invocation on other rows of the same output dir keeps the
    entries it wrote (an invocation on ACT rows alone has no score to record, and must not erase VIB's)."""
    with _locked(lock_folder):
        data = json.loads(path.read_text()) if path.exists() else {}
        _write_json(path, {**data, **entries})


Cell = tuple[str, str, int, str | None]  # (variant, condition, training seed, run time of a validation cell)


def planned_cells(cfg: BenchmarkConfig, seeds: list[int] | None = None) -> list[Cell]:
    """Per training seed: the validation cells, then the test cells (whose run times they choose), then the
    perturbed validation cells, which only the report's failure prediction reads (so that a run cut short
    has its success numbers first)."""
    cells: list[Cell] = []
    for seed in cfg.train_seeds if seeds is None else seeds:
        cells += [(v, VALIDATION, seed, rt) for v in cfg.variants for rt in cfg.validated(v)]
        cells += [(v, c, seed, None) for c in cfg.conditions for v in cfg.variants]
        if cfg.failure_validation and cfg.calibrate:
            scored = [v for v in cfg.variants if VARIANTS[v].score is not None and NETWORKS[VARIANTS[v].score] == "vib"]
            cells += [(v, PERTURBED + c, seed, None) for c in cfg.conditions if c != "normal" for v in scored]
    return cells


def choose_runtime(cfg: BenchmarkConfig, variant: str, seed: int) -> dict:
    """A row's run time at one training seed: its own, or the candidate (`--runtimes`) with the most validation
    successes, a tie going to the one listed first. Reads only validation cells."""
    v = VARIANTS[variant]
    if v.ensemble != CHOSEN:
        return {"runtime": v.runtime(), "chosen_on": None}
    successes = {}
    candidates = cfg.validated(variant)
    for rt in candidates:
        cell = json.loads(cell_path(cfg, variant, VALIDATION, seed, rt).read_text())
        successes[rt] = [sum(cell["success"]), len(cell["success"])]
    best = max(candidates, key=lambda rt: (successes[rt][0], -candidates.index(rt)))
    return {"runtime": best, "chosen_on": successes}


def record_choice(cfg: BenchmarkConfig, variant: str, seed: int) -> dict:
    """Choose a row's run time at one seed (`choose_runtime`) and keep it in `choices.json`."""
    choice = {**choose_runtime(cfg, variant, seed), "validation_seeds": cfg.validation_seeds()}
    with _locked(cfg.output_dir):
        choices_file = cfg.output_dir / "choices.json"
        choices = json.loads(choices_file.read_text()) if choices_file.exists() else {}
        choices.setdefault(variant, {})[str(seed)] = choice
        _write_json(choices_file, choices)
    return choice


def load_network(network: str, path: Path, device: str):
    """A trained network in eval mode; a VIB one records the paper's rate as u (Table I's score)."""
    from lerobot.policies.factory import get_policy_class

    config = PreTrainedConfig.from_pretrained(path)
    if NETWORKS[network] == "vib":
        # Table I's rows are the paper's: VIB's u is its rate (benchmarks/uncertainty_scores.py compares scores).
        config.uncertainty_score = "rate"
        return VIBPolicy.from_pretrained(path, config=config).to(device).eval()
    return get_policy_class(config.type).from_pretrained(path, config=config).to(device).eval()


def run_benchmark(cfg: BenchmarkConfig, report_only: bool = False) -> dict | None:
    for network in GIVEN:
        if (given := given_checkpoint(network, cfg)) is not None:
            check_given_checkpoint(Path(given), cfg)
    cfg.output_dir.mkdir(parents=True, exist_ok=True)
    check_resumable(cfg)
    if not report_only:
        with WallClock(cfg.output_dir / "wall_time.json") as clock:
            _run_cells(cfg, clock)
        if cfg.train_only:
            return None
    else:
        _complete_records(cfg)
    cells = {}
    for cell in planned_cells(cfg):
        path = cell_path(cfg, *cell)
        if path.exists():
            cells[cell] = json.loads(path.read_text())
            if embeddings_path(path).exists():
                cells[cell]["embeddings_file"] = str(embeddings_path(path))
    results = write_report(
        cfg, cells, WallClock.total(cfg.output_dir / "wall_time.json"), planned=len(planned_cells(cfg))
    )
    ship_checkpoints(cfg, cells, results)
    return results


def ship_checkpoints(cfg: BenchmarkConfig, cells: dict, results: dict) -> list[Path]:
    """Per scored VIB row and training seed, its calibrated checkpoint with the report's shipped monitor in its
    stop, under shipped/<variant>/seed_<s>/ (rewritten with the report; the checkpoint it copies is left as it
    is). The thresholds are set exactly as `lerobot-vib-calibrate --rollouts=... --rollout_episodes=successes`
    sets them (`gamma_from_rollouts`), on the row's clean validation rollouts at its chosen run time; the row's
    run time comes along; and what that stop measured on the test rollouts, which set nothing, goes into
    `calibration.monitor_metrics` and the model card."""
    choices_file = cfg.output_dir / "choices.json"
    choices = json.loads(choices_file.read_text()) if choices_file.exists() else {}
    written = []
    for variant, result in (results.get("failure_prediction") or {}).items():
        if "shipped" not in result:
            continue
        monitor = monitor_from_dict(result["shipped"]["monitor"])
        network = VARIANTS[variant].chunks
        for seed in cfg.train_seeds:
            runtime = runtime_of(choices, variant, seed)
            validation = cells.get((variant, VALIDATION, seed, runtime))
            tests = [cells[(variant, c, seed, None)] for c in cfg.conditions if (variant, c, seed, None) in cells]
            source = _calibrated_path(cfg, network, seed)
            if validation is None or not tests or source is None:
                continue
            out = cfg.output_dir / "shipped" / variant / f"seed_{seed}"
            try:
                policy = _shipped_policy(cfg, variant, network, source, runtime, monitor, validation, tests, seed)
            except VIBConfigError as e:  # the report stands without it; say why there is no checkpoint
                logger.warning("No shipped checkpoint for %s, seed %d: %s", variant, seed, e)
                continue
            preprocessor, _ = make_pre_post_processors(policy.config, pretrained_path=str(source))
            staging = out.with_name(f"{out.name}.partial")
            shutil.rmtree(staging, ignore_errors=True)
            _write(policy, preprocessor, policy.config.calibration, source, staging)
            if out.exists() and not _shipped_by_us(out):
                shutil.rmtree(staging, ignore_errors=True)
                raise VIBConfigError(f"{out} exists and is not a checkpoint this benchmark shipped: move it away.")
            shutil.rmtree(out, ignore_errors=True)  # this command's own output, rewritten with each report
            staging.replace(out)
            written.append(out)
            logger.info("Shipped %s, seed %d, with its monitor (%s): %s", variant, seed, monitor.name, out)
    return written


def _shipped_by_us(path: Path) -> bool:
    config = path / "config.json"
    return config.is_file() and bool(
        (json.loads(config.read_text()).get("calibration") or {}).get("monitor_measured_on")
    )


def _calibrated_path(cfg: BenchmarkConfig, network: str, seed: int) -> Path | None:
    """The calibrated checkpoint a row's cells were recorded with (`calibrated`), None where there is none."""
    for path in (
        given_checkpoint(network, cfg),
        cfg.output_dir / "calibrated" / network / f"seed_{seed}",
        train_dir(cfg, network, seed) / "checkpoints" / f"{cfg.steps:06d}" / "pretrained_model",
    ):
        calibrated = path is not None and (Path(path) / "config.json").exists()
        if calibrated and PreTrainedConfig.from_pretrained(path).calibration.score_means:
            return Path(path)
    return None


def _shipped_policy(
    cfg: BenchmarkConfig, variant, network, source: Path, runtime, monitor: Monitor | AnyOf, validation, tests, seed
) -> VIBPolicy:
    policy = build_variant(variant, {network: VIBPolicy.from_pretrained(source)}, runtime=runtime)
    config = policy.config
    # an OR: its first member is the stop's own score (with its window and threshold), the others its OR partners
    primary = monitor.members[0] if isinstance(monitor, AnyOf) else monitor
    others = list(monitor.members[1:]) if isinstance(monitor, AnyOf) else []
    if len({m.window for m in others}) > 1 or any(m.threshold != "constant" or len(m.scores) > 1 for m in others):
        raise VIBConfigError(f"The policy's stop cannot run {monitor.name}: its OR partners need one window.")
    score, partners = primary.scores[0], list(primary.scores[1:])
    config.uncertainty_score = score
    calibration = config.calibration
    means = {"rate": calibration.rate_mean, **calibration.score_means}
    traces = {name: [np.asarray(t, dtype=np.float64) for t in validation["scores"][name]] for name in monitor.scores}
    info = {
        "rate_mean": calibration.rate_mean,
        "score": score,
        "score_mean": means.get(score),
        "score_means": {name: means.get(name) for name in monitor.scores},
        "safety_enabled": False,
        "env": env_record(cfg.env),
        "per_episode": [
            {"seed": s, "success": bool(ok), "u_max": float(np.max(t))}
            for s, ok, t in zip(validation["seeds"], validation["success"], traces[score], strict=True)
        ],
        "command": f"lerobot-vib-benchmark validation rollouts, run time {runtime} ({cfg.output_dir})",
    }
    recorded = training_recording(source)
    calibration = gamma_from_rollouts(
        calibration, info, cfg.alpha, f"{variant}'s validation rollouts (seed {seed})", score,
        threshold=BAND_FLAGS[monitor.threshold], traces=traces[score],
        policy_config=config, recording=recorded[1] if recorded else None, window=primary.window,
        window_aggregate=primary.aggregate, and_traces={name: traces[name] for name in partners},
        episodes="successes", or_traces={m.scores[0]: traces[m.scores[0]] for m in others} or None,
        or_window=others[0].window if others else 1, or_margin=monitor.margin if others else 1.0,
    )  # fmt: skip
    # What this stop, with these very thresholds, predicts on the test rollouts
    thresholds = {score: np.asarray(calibration.gamma_band) if calibration.gamma_band else calibration.gamma}
    thresholds.update(calibration.and_gammas)
    n = calibration.rollout_successes or 0
    stop: CalibratedMonitor | CalibratedAnyOf = CalibratedMonitor(primary, cfg.alpha, thresholds, n)
    if others:
        share = cfg.alpha / len(monitor.members)
        members = [CalibratedMonitor(primary, share, thresholds, n)]
        members += [CalibratedMonitor(m, share, {m.scores[0]: calibration.or_gammas[m.scores[0]]}, n) for m in others]
        stop = CalibratedAnyOf(monitor, cfg.alpha, members)
    metrics = evaluate(stop, [e for c in tests for e in cell_episodes(c)]).as_dict()
    seeds = sorted({s for c in tests for s in c["seeds"]})
    config.calibration = dataclasses.replace(
        calibration,
        monitor_metrics={k: float(metrics[k]) for k in MONITOR_METRICS if metrics.get(k) is not None},
        monitor_measured_on=(
            f"lerobot-vib-benchmark test seeds {seeds[0]}-{seeds[-1]} under "
            f"{', '.join(c['condition'] for c in tests)}, training seed {seed}, alpha = {cfg.alpha}; "
            f"{cfg.output_dir / 'report.md'}"
        ),
    )
    return policy


MONITOR_METRICS = ("tpr", "tnr", "detection_time", "median_lead_time", "n_failed", "n_succeeded")


def _run_cells(cfg: BenchmarkConfig, clock: "WallClock") -> None:
    _save_config_record(cfg)
    if cfg.train_only:
        for seed in cfg.train_seeds:
            for network in cfg.networks():
                train(network, cfg, seed)
                clock.tick()
        return
    for seed in cfg.train_seeds:
        todo = [c for c in planned_cells(cfg, [seed]) if not cell_path(cfg, *c).exists()]
        logger.info("Training seed %d: %d cells planned, %d to run.", seed, len(planned_cells(cfg, [seed])), len(todo))
        if todo:
            _run_seed(cfg, seed, todo, clock)


def _run_seed(cfg: BenchmarkConfig, seed: int, todo: list[Cell], clock: "WallClock") -> None:
    paths = {}
    for network in cfg.networks():
        paths[network] = train(network, cfg, seed)
        if cfg.calibrate and NETWORKS[network] == "vib":
            paths[network] = calibrated(network, cfg, seed, paths[network])
        clock.tick()
    nets = {n: load_network(n, p, cfg.device) for n, p in paths.items()}
    rnd = fit_rnd(cfg, paths["vib"], nets["vib"], seed).to(cfg.device) if cfg.needs("rnd") else None
    _merge_json(cfg.output_dir / "scores" / f"seed_{seed}.json", score_statistics(nets, rnd), cfg.output_dir)
    processors = {
        n: make_pre_post_processors(
            policy.config,
            pretrained_path=str(paths[n]),
            preprocessor_overrides={"device_processor": {"device": cfg.device}},
        )
        for n, policy in nets.items()
    }
    for variant, condition, _, runtime in tqdm(todo, desc=f"cells, seed {seed}", unit="cell"):
        if cell_path(cfg, variant, condition, seed, runtime).exists():
            continue  # saved meanwhile by another invocation on other rows of the same output dir
        # a test cell runs at the run time its row chose on validation; a validation cell at its own
        runtime_used = record_choice(cfg, variant, seed)["runtime"] if condition != VALIDATION else runtime
        policy = build_variant(variant, nets, rnd, runtime_used)
        if cfg.calibrate and isinstance(policy, VIBPolicy):
            policy.trace_all_scores = True  # every score per step, for failure prediction (failure.py)
        cell = run_cell(cfg, variant, condition, policy, processors[VARIANTS[variant].chunks])
        cell.update(train_seed=seed, runtime=runtime_used)
        path = cell_path(cfg, variant, condition, seed, runtime)
        write_embeddings(cell.pop("episodes"), embeddings_path(path))  # first: a cell file means complete
        _write_json(path, cell)
        clock.tick()
        logger.info(
            "seed %d, %s / %s (%s): %d/%d in %.0f s",
            seed,
            condition,
            variant,
            runtime_used,
            sum(cell["success"]),
            len(cell["success"]),
            cell["wall_s"],
        )


def score_statistics(nets: dict, rnd: RND | None) -> dict:
    """Each score's training mean and the paper's threshold mean(u) + 2 std(u) on it, keyed as the rows'
    `score` (a VIB network's name, or "rnd")."""
    stats = {}
    for name, vib in nets.items():
        if NETWORKS[name] != "vib":
            continue
        c = vib.config.calibration
        mean, std = (
            (c.rate_mean, c.rate_std) if c.rate_mean is not None else (vib.rate_tracker.mean, vib.rate_tracker.std)
        )
        stats[name] = {"mean": mean, "std": std, "mean_2std": mean_plus_2std_gamma(mean, std)}
    if rnd is not None:
        stats["rnd"] = {"mean": float(rnd.error_mean), "std": float(rnd.error_std), "mean_2std": rnd.threshold()}
    return stats


# What a saved cell depends on: a rerun with other values must not mix its cells with the saved ones.
RESUME_KEYS = (
    "dataset", "env", "preset", "steps", "rnd_steps", "vib_checkpoint", "act_checkpoint", "device",
    "vib_tokens_checkpoint",
    "validation_seed", "test_seed", "runtimes", "calibrate",
)  # fmt: skip


# What a run saved before a resume key existed did: it did not calibrate (the rate only, as u).
BEFORE_THE_FIELD = {"calibrate": False}


def checkpoint_fingerprint(path: Path) -> str:
    """SHA-256 over a checkpoint folder's top-level files (config, weights, processors and their statistics):
    a checkpoint recalibrated or retrained in place under the same path gets another fingerprint."""
    digest = hashlib.sha256()
    for file in sorted(p for p in Path(path).iterdir() if p.is_file() and p.suffix in (".json", ".safetensors")):
        digest.update(file.name.encode() + b"\0")
        with file.open("rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                digest.update(block)
    return digest.hexdigest()


def _given_fingerprints(cfg: BenchmarkConfig) -> dict[str, str]:
    return {
        f"{network}_checkpoint": checkpoint_fingerprint(Path(given))
        for network in GIVEN
        if (given := given_checkpoint(network, cfg)) is not None
    }


def check_resumable(cfg: BenchmarkConfig) -> None:
    """Refuse to resume into an output dir whose saved cells came from other settings, other seeds, or a given
    checkpoint that changed since (same path, other config or weights)."""
    path = cfg.output_dir / "config.json"
    if path.exists():
        saved, now = json.loads(path.read_text()), _config_record(cfg)
        before = saved.get("checkpoint_fingerprints")
        for name, fingerprint in now["checkpoint_fingerprints"].items():
            if before is None and saved.get(name):
                raise VIBConfigError(
                    f"{cfg.output_dir} was evaluated with --{name} before checkpoints were fingerprinted, so whether "
                    f"{_portable(getattr(cfg, name))} is still that checkpoint cannot be told: use another "
                    "--output_dir."
                )
            if (before or {}).get(name, fingerprint) != fingerprint:
                raise VIBConfigError(
                    f"--{name}={_portable(getattr(cfg, name))} is not the checkpoint {cfg.output_dir}'s cells were "
                    "evaluated with: its config or weights changed since (recalibrated or retrained in place), so "
                    "its thresholds and u would mix with the saved ones. Use another --output_dir, or a copy of the "
                    "checkpoint as it was."
                )
        if changed := [k for k in RESUME_KEYS if saved.get(k, BEFORE_THE_FIELD.get(k)) != now.get(k)]:
            raise VIBConfigError(
                f"{cfg.output_dir} holds a benchmark run with other {', '.join(changed)}; its cells would mix with "
                "this run's. Use another --output_dir, or rerun with the same settings to resume."
            )
    for cell in planned_cells(cfg):
        file = cell_path(cfg, *cell)
        if file.exists() and json.loads(file.read_text())["seeds"] != cell_seeds(cfg, cell[0], cell[1]):
            raise VIBConfigError(
                f"{file} was evaluated on other episode seeds (another --n_episodes, --n_episodes_other, "
                "--validation_episodes or seed): use another --output_dir, or the settings it was made with."
            )


class WallClock:
    """Wall time over every invocation of a benchmark, killed ones included.

    Each invocation appends its own record, {"start", "end", "finished"}, to `wall_time.json` when it starts,
    and keeps its "end" current: every `beat` seconds from a background thread, after every finished cell, and
    when it ends. An invocation killed at any point (SIGKILL included) thus counts up to its last beat, at
    most `beat` seconds short. Invocations may run side by side (say, one per group of rows): each rewrites
    only its own record, under a file lock. The total is the sum of (end - start) over the records, so
    invocations that overlap in time count once each: it is machine time spent, not elapsed time.
    """

    def __init__(self, path: Path, beat: float = 30.0):
        self.path, self.beat = path, beat
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    @staticmethod
    def load(path: Path) -> dict:
        record = json.loads(path.read_text()) if path.exists() else {}
        record.setdefault("invocations", [])
        # Written before invocations were recorded: the seconds of the ones that finished.
        record.setdefault("seconds_unrecorded", record.pop("seconds", 0.0))
        return record

    @staticmethod
    def total(path: Path) -> float:
        record = WallClock.load(path)
        return record["seconds_unrecorded"] + sum(i["end"] - i["start"] for i in record["invocations"])

    def __enter__(self) -> "WallClock":
        now = time.time()
        self.mine = {"start": now, "end": now, "finished": False, "pid": os.getpid()}
        with _locked(self.path.parent):
            record = self.load(self.path)
            record["invocations"].append(self.mine)
            _write_json(self.path, record)
        self._thread = threading.Thread(target=self._beat, daemon=True)
        self._thread.start()
        return self

    def _beat(self) -> None:
        while not self._stop.wait(self.beat):
            self.tick()

    def tick(self, finished: bool = False) -> None:
        with self._lock, _locked(self.path.parent):
            record = self.load(self.path)
            ours = [
                i for i in record["invocations"] if (i["start"], i.get("pid")) == (self.mine["start"], self.mine["pid"])
            ]
            if not ours:  # the file was replaced meanwhile: put this invocation back
                ours = [self.mine]
                record["invocations"].append(self.mine)
            ours[0].update(end=time.time(), finished=finished)
            self.mine = ours[0]
            _write_json(self.path, record)

    def __exit__(self, exc_type, exc, tb) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        self.tick(finished=exc_type is None)


def _portable(path: Path | str | None) -> str | None:
    """A path under the project relative to it, so that a committed report names no machine's folders."""
    if path is None:
        return None
    try:
        return Path(path).resolve().relative_to(CONFIGS.parents[1]).as_posix()
    except ValueError:
        return str(path)


@contextlib.contextmanager
def _locked(folder: Path, name: str = ".lock") -> Iterator[None]:
    """An exclusive lock on `<folder>/<name>` (flock; released if the process dies), for what invocations side by
    side share: files they rewrite, and trainings."""
    folder.mkdir(parents=True, exist_ok=True)
    with (folder / name).open("a") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


def _complete_records(cfg: BenchmarkConfig) -> None:
    """What a report needs beside the cells, for a folder assembled from other runs' cells (seeds run apart,
    merged): the settings, as this command's; and each chosen row's run time, chosen again on its validation
    cells (the same rule, so the same choice), where `choices.json` lacks it. Without them the report would
    leave out every row's uncertainty without a word."""
    if not (cfg.output_dir / "config.json").exists():
        _save_config_record(cfg)
    choices_file = cfg.output_dir / "choices.json"
    choices = json.loads(choices_file.read_text()) if choices_file.exists() else {}
    for variant in cfg.variants:
        for seed in cfg.train_seeds:
            validated = cfg.validated(variant)
            if str(seed) in choices.get(variant, {}) or VARIANTS[variant].ensemble != CHOSEN or not validated:
                continue
            if all(cell_path(cfg, variant, VALIDATION, seed, rt).exists() for rt in validated):
                record_choice(cfg, variant, seed)


def _save_config_record(cfg: BenchmarkConfig) -> None:
    """config.json: this invocation's settings, and every command run on this output dir so far."""
    with _locked(cfg.output_dir):
        path = cfg.output_dir / "config.json"
        record = _config_record(cfg)
        saved = json.loads(path.read_text()) if path.exists() else {}
        commands = saved.get("commands") or ([saved["command"]] if "command" in saved else [])
        record["commands"] = commands + [c for c in [record["command"]] if c not in commands]
        _write_json(path, record)


def _config_record(cfg: BenchmarkConfig) -> dict:
    record = json.loads(json.dumps(dataclasses.asdict(cfg), default=str))
    record["preset"] = _portable(cfg.preset)
    record["env_type"] = cfg.env.type
    record["command"] = " ".join(["lerobot-vib-benchmark", *sys.argv[1:]])
    record["checkpoint_fingerprints"] = _given_fingerprints(cfg)
    record["machine"] = {"platform": platform.platform(), "processor": platform.processor(), "cpus": os.cpu_count()}
    return record


@parser.wrap()
def benchmark(cfg: BenchmarkConfig) -> dict | None:
    return run_benchmark(cfg, report_only=cfg.report_only)


def main() -> None:
    init_logging()
    register_third_party_plugins()
    try:
        benchmark()
    except VIBConfigError as e:
        raise SystemExit(f"lerobot-vib-benchmark: {e}") from None


if __name__ == "__main__":
    main()
