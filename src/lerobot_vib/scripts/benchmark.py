"""`lerobot-vib-benchmark`: the paper's evaluation (Table I's rows, RND, perturbed conditions, uncertainty) in
one resumable command, for any recorded dataset and env.

    lerobot-vib-benchmark --dataset.repo_id=local/vib_arm_grasp_block_scripted --dataset.root=data/arm_grasp_block \
        --env.type=vib_arm --env.dataset_root=data/arm_grasp_block --profile=cpu-small --output_dir=outputs/bench_arm

Stages, each saved as it finishes so that a stopped benchmark resumes where it stopped:

1. train: VIB from the profile's preset and ACT with the same architecture, recipe and budget, each by
   `lerobot-train` (an interrupted training resumes with LeRobot's `--resume=true`); or given checkpoints
   (`--vib_checkpoint`, `--act_checkpoint`).
2. RND (rnd.py) on the training dataset, normalized by the VIB checkpoint's preprocessor, if a row needs it.
3. cells: every variant (variants.py) under every condition, on the same episode seeds per condition, through
   LeRobot's eval loop (`lerobot_eval.eval_policy`), recording u at every step; plus clean calibration
   rollouts on other seeds for each row with a score (the thresholds are judged on rollouts).
4. report (benchmark_report.py): `report.md`, `results.json` and the plots.

Conditions: normal; gaussian (noise std drawn from {0, 0.05, 0.1}); color (jitter 0.2 with probability 0.5);
on the simulated arm also camera_shake, unseen_block and occlusion (sim/perturbations.py).
"""

import dataclasses
import json
import logging
import os
import platform
import subprocess
import sys
import threading
import time
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
from lerobot.policies.act.modeling_act import ACTPolicy
from lerobot.policies.factory import make_pre_post_processors
from lerobot.scripts import lerobot_eval
from lerobot.utils.import_utils import register_third_party_plugins
from lerobot.utils.utils import init_logging
from tqdm import tqdm

from ..calibration import mean_plus_2std_gamma
from ..configuration_vib import VIBConfigError
from ..modeling_vib import VIBPolicy
from ..rnd import RND, RNDConfig, train_rnd
from ..sim import env_config  # noqa: F401  (registers --env.type=aloha_fast and vib_arm)
from ..sim.perturbations import CONDITIONS, SCENE_CONDITIONS
from ..variants import VARIANTS, build_variant, queue_steps
from .benchmark_report import write_report
from .eval_uncertainty import UncertaintyCapture

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

CALIBRATION = "calibration"  # clean rollouts on their own seeds, for the thresholds
MAIN_VARIANTS = ("vib", "act")  # the rows that get `n_episodes`; the others get `n_episodes_other`


@dataclass(frozen=True)
class Profile:
    """A budget. `presets`: the VIB train config (in configs/policy/) per env type; `steps` None keeps the
    preset's."""

    presets: dict[str, str]
    steps: int | None
    n_episodes: int
    n_episodes_other: int
    calibration_episodes: int
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
    variants: Rows of Table I (variants.VARIANTS); default all.
    conditions: Default: normal, gaussian, color, and on the simulated arm camera_shake, unseen_block, occlusion.
    n_episodes: Episodes per cell for VIB (Eq. 6) and ACT.
    n_episodes_other: Episodes per cell for the other rows.
    calibration_episodes: Clean rollouts per scored row on their own seeds, for the thresholds.
    preset: The VIB train config (`lerobot-train --config_path`); ACT copies its architecture and recipe.
    steps: Training steps of VIB and ACT.
    save_freq: Steps between saved training checkpoints: an interrupted training resumes from the last one.
    rnd_steps: Training steps of the RND predictor.
    vib_checkpoint, act_checkpoint: Trained `pretrained_model` folders to evaluate instead of training.
    device: Where training and evaluation run.
    eval_batch_size: Envs per rollout batch.
    alpha: Level of the conformal thresholds (false-stop rate bound on in-distribution episodes).
    seed: Training seed. eval_seed, calibration_seed: the first episode seed of the cells and of calibration.
    """

    dataset: DatasetConfig
    env: envs.EnvConfig
    output_dir: Path = Path("outputs/benchmark")
    profile: str = "cpu-small"
    variants: list[str] = field(default_factory=lambda: list(VARIANTS))
    conditions: list[str] | None = None
    n_episodes: int | None = None
    n_episodes_other: int | None = None
    calibration_episodes: int | None = None
    preset: Path | None = None
    steps: int | None = None
    save_freq: int = 1000
    rnd_steps: int | None = None
    vib_checkpoint: Path | None = None
    act_checkpoint: Path | None = None
    device: str | None = None
    eval_batch_size: int = 10
    alpha: float = 0.1
    seed: int = 1000
    eval_seed: int = 100_000
    calibration_seed: int = 200_000

    def __post_init__(self):
        if self.profile not in PROFILES:
            raise VIBConfigError(f"Unknown --profile={self.profile!r}; choose from {sorted(PROFILES)}.")
        p = PROFILES[self.profile]
        for name in ("n_episodes", "n_episodes_other", "calibration_episodes", "steps", "rnd_steps", "device"):
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
        if unknown := sorted(set(self.variants) - set(VARIANTS)):
            raise VIBConfigError(f"Unknown variants {unknown}; choose from {sorted(VARIANTS)}.")
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
        for name in ("n_episodes", "n_episodes_other", "calibration_episodes", "eval_batch_size"):
            if getattr(self, name) < 1:
                raise VIBConfigError(f"--{name} must be >= 1, got {getattr(self, name)}.")
        if not 0 < self.alpha < 1:
            raise VIBConfigError(f"--alpha must be in (0, 1), got {self.alpha}.")
        if not self.preset.exists():
            raise VIBConfigError(f"The VIB preset {self.preset} does not exist: give --preset=<train config>.")
        if self.steps is None:
            self.steps = json.loads(self.preset.read_text())["steps"]

    def needs(self, network: str) -> bool:
        return any(network in (VARIANTS[v].chunks, VARIANTS[v].score) for v in self.variants)

    def episodes(self, variant: str, condition: str) -> int:
        if condition == CALIBRATION:
            return self.calibration_episodes
        return self.n_episodes if variant in MAIN_VARIANTS else self.n_episodes_other


# ----------------------------------------------------------------------------------------------------- training


def _bin(name: str) -> str:
    return str(Path(sys.executable).parent / name)


def train_command(network: str, cfg: BenchmarkConfig, out: Path) -> list[str]:
    common = [
        f"--dataset.repo_id={cfg.dataset.repo_id}",
        *([f"--dataset.root={cfg.dataset.root}"] if cfg.dataset.root else []),
        f"--output_dir={out}",
        f"--seed={cfg.seed}",
        f"--steps={cfg.steps}",
        f"--save_freq={min(cfg.save_freq, cfg.steps)}",
        "--env_eval_freq=0",
        f"--policy.device={cfg.device}",
    ]
    if network == "vib":
        return [_bin("lerobot-train"), f"--config_path={cfg.preset}", *common]
    preset = json.loads(cfg.preset.read_text())
    run = [f"--{k}={preset[k]}" for k in ("batch_size", "num_workers", "log_freq") if k in preset]
    return [
        _bin("lerobot-train"),
        "--policy.type=act",
        "--policy.push_to_hub=false",
        "--policy.pretrained_backbone_weights=null",
        *act_recipe_flags(preset),
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
    transforms = preset.get("dataset", {}).get("image_transforms")
    if transforms:
        flags += [
            f"--dataset.image_transforms.{k}={json.dumps(v) if isinstance(v, dict) else str(v).lower()}"
            for k, v in transforms.items()
        ]
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


def train(network: str, cfg: BenchmarkConfig) -> Path:
    """The trained checkpoint's `pretrained_model`, training (or resuming) with `lerobot-train` if needed."""
    given = cfg.vib_checkpoint if network == "vib" else cfg.act_checkpoint
    if given is not None:
        return Path(given)
    out = cfg.output_dir / "train" / network
    final = out / "checkpoints" / f"{cfg.steps:06d}" / "pretrained_model"
    if final.exists():
        return final
    last = out / "checkpoints" / "last" / "pretrained_model"
    cmd = train_command(network, cfg, out)
    if last.exists():  # an interrupted training
        cmd = [cmd[0], f"--config_path={last / 'train_config.json'}", "--resume=true"]
    elif out.exists():  # lerobot-train refuses an existing output dir without a checkpoint to resume
        raise VIBConfigError(f"{out} exists without a checkpoint to resume from: move it away and rerun.")
    log = cfg.output_dir / "train" / f"{network}.log"
    log.parent.mkdir(parents=True, exist_ok=True)
    with (cfg.output_dir / "train" / f"{network}_command.txt").open("a") as f:
        f.write(" ".join(cmd) + "\n")
    logger.info("Training %s (log: %s): %s", network.upper(), log, " ".join(cmd))
    with log.open("a") as f:
        result = subprocess.run(cmd, stdout=f, stderr=subprocess.STDOUT, env={**os.environ})
    if result.returncode != 0 or not final.exists():
        raise RuntimeError(f"Training {network.upper()} failed (exit {result.returncode}); see {log}.")
    return final


def fit_rnd(cfg: BenchmarkConfig, vib_path: Path, vib: VIBPolicy) -> RND:
    """RND on the training frames as the VIB policy sees them (its preprocessor), saved under rnd/."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    directory = cfg.output_dir / "rnd"
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
        seed=cfg.seed,
    )
    model = RND(rnd_cfg).to(cfg.device)

    def loader(shuffle: bool):
        generator = torch.Generator().manual_seed(cfg.seed)
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


def cell_path(cfg: BenchmarkConfig, variant: str, condition: str) -> Path:
    return cfg.output_dir / "cells" / condition / f"{variant}.json"


def cell_seeds(cfg: BenchmarkConfig, variant: str, condition: str) -> list[int]:
    start = cfg.calibration_seed if condition == CALIBRATION else cfg.eval_seed
    return list(range(start, start + cfg.episodes(variant, condition)))


def run_cell(cfg: BenchmarkConfig, variant: str, condition: str, policy, processors: tuple) -> dict:
    """Evaluate one row under one condition with LeRobot's eval loop; u per step of every episode."""
    env_cfg = dataclasses.replace(cfg.env, perturbation=CONDITIONS["normal" if condition == CALIBRATION else condition])
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
        "wall_s": round(time.time() - start, 1),
    }


def _write_json(path: Path, data: Any) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(data))
    tmp.replace(path)  # a cell file exists only when complete


def planned_cells(cfg: BenchmarkConfig) -> list[tuple[str, str]]:
    cells = [(v, c) for c in cfg.conditions for v in cfg.variants]
    cells += [(v, CALIBRATION) for v in cfg.variants if VARIANTS[v].score is not None]
    return cells


def run_benchmark(cfg: BenchmarkConfig) -> dict:
    cfg.output_dir.mkdir(parents=True, exist_ok=True)
    check_resumable(cfg)
    with WallClock(cfg.output_dir / "wall_time.json") as clock:
        _run_cells(cfg, clock)
    cells = {(v, c): json.loads(cell_path(cfg, v, c).read_text()) for v, c in planned_cells(cfg)}
    return write_report(cfg, cells, WallClock.total(cfg.output_dir / "wall_time.json"))


def _run_cells(cfg: BenchmarkConfig, clock: "WallClock") -> None:
    _write_json(cfg.output_dir / "config.json", _config_record(cfg))
    todo = [(v, c) for v, c in planned_cells(cfg) if not cell_path(cfg, v, c).exists()]
    logger.info("%d cells planned, %d to run.", len(planned_cells(cfg)), len(todo))
    if todo:
        paths = {n: train(n, cfg) for n in ("vib", "act") if cfg.needs(n)}
        vib = None
        if "vib" in paths:
            vib_config = PreTrainedConfig.from_pretrained(paths["vib"])
            # Table I's rows are the paper's: VIB's u is its rate (benchmarks/uncertainty_scores.py compares scores).
            vib_config.uncertainty_score = "rate"
            vib = VIBPolicy.from_pretrained(paths["vib"], config=vib_config).to(cfg.device).eval()
        act = ACTPolicy.from_pretrained(paths["act"]).to(cfg.device).eval() if "act" in paths else None
        rnd = fit_rnd(cfg, paths["vib"], vib).to(cfg.device) if cfg.needs("rnd") else None
        _write_json(cfg.output_dir / "scores.json", score_statistics(vib, rnd))
        processors = {}
        for name, policy in (("vib", vib), ("act", act)):
            if policy is not None:
                processors[name] = make_pre_post_processors(
                    policy.config,
                    pretrained_path=str(paths[name]),
                    preprocessor_overrides={"device_processor": {"device": cfg.device}},
                )
        for variant, condition in tqdm(todo, desc="cells", unit="cell"):
            policy = build_variant(variant, vib, act, rnd)
            cell = run_cell(cfg, variant, condition, policy, processors[VARIANTS[variant].chunks])
            _write_json(cell_path(cfg, variant, condition), cell)
            clock.tick()
            logger.info(
                "%s / %s: %d/%d in %.0f s",
                condition,
                variant,
                sum(cell["success"]),
                len(cell["success"]),
                cell["wall_s"],
            )


def score_statistics(vib: VIBPolicy | None, rnd: RND | None) -> dict:
    """Each score's training mean and the paper's threshold mean(u) + 2 std(u) on it."""
    stats = {}
    if vib is not None:
        c = vib.config.calibration
        mean, std = (
            (c.rate_mean, c.rate_std) if c.rate_mean is not None else (vib.rate_tracker.mean, vib.rate_tracker.std)
        )
        stats["vib"] = {"mean": mean, "std": std, "mean_2std": mean_plus_2std_gamma(mean, std)}
    if rnd is not None:
        stats["rnd"] = {"mean": float(rnd.error_mean), "std": float(rnd.error_std), "mean_2std": rnd.threshold()}
    return stats


# What a saved cell depends on: a rerun with other values must not mix its cells with the saved ones.
RESUME_KEYS = ("dataset", "env", "preset", "steps", "rnd_steps", "vib_checkpoint", "act_checkpoint", "seed", "device")


def check_resumable(cfg: BenchmarkConfig) -> None:
    """Refuse to resume into an output dir whose saved cells came from other settings or other seeds."""
    path = cfg.output_dir / "config.json"
    if path.exists():
        saved, now = json.loads(path.read_text()), _config_record(cfg)
        if changed := [k for k in RESUME_KEYS if saved.get(k) != now.get(k)]:
            raise VIBConfigError(
                f"{cfg.output_dir} holds a benchmark run with other {', '.join(changed)}; its cells would mix with "
                "this run's. Use another --output_dir, or rerun with the same settings to resume."
            )
    for variant, condition in planned_cells(cfg):
        cell = cell_path(cfg, variant, condition)
        if cell.exists() and json.loads(cell.read_text())["seeds"] != cell_seeds(cfg, variant, condition):
            raise VIBConfigError(
                f"{cell} was evaluated on other episode seeds (another --n_episodes, --n_episodes_other, "
                "--calibration_episodes or seed): use another --output_dir, or the settings it was made with."
            )


class WallClock:
    """Wall time over every invocation of a benchmark, killed ones included.

    Each invocation appends its own record, {"start", "end", "finished"}, to `wall_time.json` when it starts,
    and keeps its "end" current: every `beat` seconds from a background thread, after every finished cell, and
    when it ends. An invocation killed at any point (SIGKILL included) thus counts up to its last beat, at
    most `beat` seconds short. The total is the sum of (end - start) over the records.
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
        self.record = self.load(self.path)
        now = time.time()
        self.record["invocations"].append({"start": now, "end": now, "finished": False})
        self._write()
        self._thread = threading.Thread(target=self._beat, daemon=True)
        self._thread.start()
        return self

    def _beat(self) -> None:
        while not self._stop.wait(self.beat):
            self.tick()

    def tick(self, finished: bool = False) -> None:
        with self._lock:
            self.record["invocations"][-1].update(end=time.time(), finished=finished)
            self._write()

    def _write(self) -> None:
        _write_json(self.path, self.record)

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


def _config_record(cfg: BenchmarkConfig) -> dict:
    record = json.loads(json.dumps(dataclasses.asdict(cfg), default=str))
    record["preset"] = _portable(cfg.preset)
    record["env_type"] = cfg.env.type
    record["command"] = " ".join(["lerobot-vib-benchmark", *sys.argv[1:]])
    record["machine"] = {"platform": platform.platform(), "processor": platform.processor(), "cpus": os.cpu_count()}
    return record


@parser.wrap()
def benchmark(cfg: BenchmarkConfig) -> dict:
    return run_benchmark(cfg)


def main() -> None:
    init_logging()
    register_third_party_plugins()
    try:
        benchmark()
    except VIBConfigError as e:
        raise SystemExit(f"lerobot-vib-benchmark: {e}") from None


if __name__ == "__main__":
    main()
