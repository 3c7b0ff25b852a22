"""Does Eq. 6 help on the arm? Its coefficient m swept against the action queue and ACT's ensembling, on one
checkpoint and the same seeds.

    python benchmarks/eq6_sweep.py --policy outputs/ckpt/floor/pretrained_model --dataset_root data/arm_near \
        --out outputs/eq6/floor --report benchmarks/results/eq6_sweep_arm_cpu_2core/report.md

Rows (runtime.py's modes; the stop is off, so only how the action is chosen differs):
    queue            a chunk every `n_action_steps` steps, executed open loop (the preset's mode)
    act m            ACT's temporal ensembling, w_j = exp(-m j), j = 0 the oldest candidate
    eq6 m            Eq. 6, w_j = exp(-m u_j j), u_j the shipped score's u of the pass that made candidate j
for m in --coeffs. Conditions: clean and occlusion (a board in front of the camera from a step in [10, 40) for
15-40 steps: the perturbation the shipped score sees, so where Eq. 6 has something to weigh).

Seeds: the project's plan (`lerobot_vib.seeds`): validation 400000.. (the choice of m for each ensembler and of
the preset's mode), test 600000.. (the reported numbers; nothing is chosen on them). The committed report was
made before the plan, with test 500000..; `--test_seed=500000` reruns it as it was. The checkpoint is first
calibrated with `lerobot-vib-calibrate`'s own computation (every score's mean), into <out>/calibrated. Every
cell is one file (<out>/<split>/<condition>/<row>.json), skipped when present, so a stopped run resumes.

How far Eq. 6 moves the weights is measured too: at each step, the L1 distance between Eq. 6's weights over
the candidates and ACT's at the same m (0 = identical, 2 = disjoint), from the u trace of the Eq. 6 rollout.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shlex
import sys
import time
from pathlib import Path

import numpy as np
import torch

os.environ.setdefault("MUJOCO_GL", "egl")

from lerobot.envs.utils import preprocess_observation
from lerobot.policies.factory import make_pre_post_processors
from report import cpu_name, emit
from uncertainty_scores import calibrated, load_policy

from lerobot_vib import seeds
from lerobot_vib.metrics import wilson_interval
from lerobot_vib.sim.arm_env import EPISODE_LENGTH, ArmGraspEnv
from lerobot_vib.sim.env_config import ArmGraspEnvConfig
from lerobot_vib.sim.perturbations import PerturbationConfig

DEFAULT_SPLIT_SEEDS = {"validation": seeds.VALIDATION, "test": seeds.TEST}
CONDITIONS = {"clean": {}, "occlusion": {"occlusion": True}}
SCORE = "low_image_rate"


def rows(coeffs: list[float]) -> dict[str, list[str]]:
    """Row name -> the policy overrides that make it."""
    out = {"queue": ["--temporal_ensemble=none"]}
    for kind, mode in (("act", "act"), ("eq6", "uncertainty")):
        for m in coeffs:
            out[f"{kind} m={m:g}"] = [
                f"--temporal_ensemble={mode}",
                "--n_action_steps=1",
                f"--temporal_ensemble_coeff={m}",
            ]
    return out


def weight_shift(u: np.ndarray, m: float, chunk_size: int) -> np.ndarray:
    """Per step, the L1 distance between Eq. 6's candidate weights and ACT's at the same m."""
    out = np.zeros(len(u))
    for t in range(len(u)):
        hist = u[max(0, t - chunk_size + 1) : t + 1]  # oldest first, as the ensembler holds them
        j = np.arange(len(hist))
        eq6 = np.exp(-m * hist * j - np.max(-m * hist * j))
        act = np.exp(-m * j)
        out[t] = np.abs(eq6 / eq6.sum() - act / act.sum()).sum()
    return out


@torch.no_grad()
def rollout(policy, processors, env: ArmGraspEnv, seed: int) -> dict:
    preprocessor, postprocessor = processors
    obs, _ = env.reset(seed=seed)
    policy.reset()
    u, success = [], False
    for _ in range(EPISODE_LENGTH):
        action = policy.select_action(preprocessor(preprocess_observation(obs)))
        u.append(float(policy.last_step.u[0]))
        obs, _, terminated, _, info = env.step(postprocessor(action)[0].numpy())
        success = success or bool(info.get("is_success", False))
        if terminated:
            break
    return {"seed": seed, "success": success, "u": u}


def run(args, path: Path, split: str, n_episodes: dict[str, int]) -> None:
    env_kwargs = ArmGraspEnvConfig(dataset_root=str(args.dataset_root)).gym_kwargs
    env_kwargs = {k: v for k, v in env_kwargs.items() if k not in ("render_mode", "perturbation", "max_episode_steps")}
    for condition, perturbation in CONDITIONS.items():
        env = None
        for row, overrides in rows(args.coeffs).items():
            target = args.out / split / condition / f"{row.replace(' ', '_')}.json"
            if target.is_file():
                continue
            env = env or ArmGraspEnv(**env_kwargs, perturbation=PerturbationConfig(**perturbation))
            policy, _ = load_policy(path, [f"--uncertainty_score={SCORE}", "--safety.enabled=false", *overrides])
            processors = make_pre_post_processors(policy.config, pretrained_path=str(path))
            episode_seeds = seeds.seed_range(split, n_episodes[condition], args.split_seeds[split])
            start = time.time()
            episodes = [rollout(policy, processors, env, s) for s in episode_seeds]
            cell = {"row": row, "overrides": overrides, "episodes": episodes, "wall_s": time.time() - start}
            target.parent.mkdir(parents=True, exist_ok=True)
            tmp = target.with_suffix(".tmp")
            tmp.write_text(json.dumps(cell))
            tmp.replace(target)  # whole cells only: a stopped run redoes the one it was in
            wins = sum(e["success"] for e in episodes)
            print(f"{split}/{condition}/{row}: {wins}/{len(episodes)}, {cell['wall_s']:.0f} s", flush=True)
        if env is not None:
            env.close()


def load(out: Path, split: str, coeffs: list[float]) -> dict[str, dict[str, dict]]:
    cells: dict[str, dict[str, dict]] = {}
    for condition in CONDITIONS:
        for row in rows(coeffs):
            path = out / split / condition / f"{row.replace(' ', '_')}.json"
            if path.is_file():
                cells.setdefault(row, {})[condition] = json.loads(path.read_text())
    return cells


def wins(cell: dict) -> tuple[int, int]:
    return sum(e["success"] for e in cell["episodes"]), len(cell["episodes"])


def pooled(cells: dict[str, dict]) -> tuple[int, int]:
    parts = [wins(c) for c in cells.values()]
    return sum(p[0] for p in parts), sum(p[1] for p in parts)


def choose(validation: dict[str, dict[str, dict]], coeffs: list[float]) -> dict[str, str]:
    """On validation only: each ensembler's m (most clean + occlusion successes; ties: the smaller m), and the
    preset's mode (most successes among the queue and the two chosen ensemblers; ties: the queue, the cheapest)."""
    chosen = {}
    for kind in ("act", "eq6"):
        candidates = [f"{kind} m={m:g}" for m in sorted(coeffs) if f"{kind} m={m:g}" in validation]
        if candidates:
            chosen[kind] = max(candidates, key=lambda r: (pooled(validation[r])[0], -candidates.index(r)))
    order = ["queue", *chosen.values()]
    order = [r for r in order if r in validation]
    if order:
        chosen["preset"] = max(order, key=lambda r: (pooled(validation[r])[0], -order.index(r)))
    return chosen


def cell_text(cell: dict | None) -> str:
    if cell is None:
        return "-"
    k, n = wins(cell)
    lo, hi = wilson_interval(k, n)
    return f"{k}/{n} = {k / n:.0%} [{lo:.0%}, {hi:.0%}]"


def report(args) -> str:
    validation, test = load(args.out, "validation", args.coeffs), load(args.out, "test", args.coeffs)
    chosen = choose(validation, args.coeffs)
    config = json.loads((args.out / "calibrated" / "config.json").read_text())
    chunk = config["chunk_size"]
    lines = [
        "# Eq. 6 on the simulated arm: m swept against the queue and ACT's ensembling",
        "",
        f"Checkpoint: `{args.policy_label or args.policy}`; score `{SCORE}` (u over its training mean); "
        f"chunk_size {chunk}, n_action_steps {config['n_action_steps']}; the stop off. Rollouts on {cpu_name()}, "
        f"torch {torch.__version__}. One training seed.",
        "",
        "Command: `python " + shlex.join(args.argv) + "`",
        "",
        f"Chosen on validation (seeds {args.split_seeds['validation']}..): "
        + ", ".join(f"{k}: **{v}**" for k, v in chosen.items())
        + ". Test seeds "
        + f"{args.split_seeds['test']}.. were read only for this table.",
        "",
        "| row | clean (test) | occlusion (test) | pooled (test) | pooled (validation) | "
        "weight shift vs ACT, mean / p99 (test, occlusion) |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for row in rows(args.coeffs):
        cells = test.get(row, {})
        k, n = pooled(cells) if cells else (0, 0)
        vk, vn = pooled(validation[row]) if row in validation else (0, 0)
        shift = "-"
        if row.startswith("eq6") and "occlusion" in cells:
            m = float(row.split("=")[1])
            s = np.concatenate([weight_shift(np.asarray(e["u"]), m, chunk) for e in cells["occlusion"]["episodes"]])
            shift = f"{s.mean():.3f} / {np.quantile(s, 0.99):.3f}"
        mark = " (chosen)" if row in chosen.values() else ""
        lines.append(
            f"| {row}{mark} | {cell_text(cells.get('clean'))} | {cell_text(cells.get('occlusion'))} | "
            f"{f'{k}/{n} = {k / n:.0%}' if n else '-'} | {f'{vk}/{vn}' if vn else '-'} | {shift} |"
        )
    lines += ["", "Weight shift: L1 distance between Eq. 6's weights over the candidates and ACT's at the same m "
              "(0: identical, 2: disjoint), over every step of the occlusion rollouts."]  # fmt: skip
    wall = sum(c["wall_s"] for split in (validation, test) for r in split.values() for c in r.values())
    lines += ["", f"Rollout wall time, every cell summed: {wall / 60:.1f} min."]
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--policy", type=Path, required=True, help="the trained checkpoint (pretrained_model)")
    parser.add_argument("--policy_label", default=None, help="how the report names the checkpoint")
    parser.add_argument("--dataset_root", type=Path, required=True)
    parser.add_argument("--repo_id", default="local/vib_arm_grasp_block_scripted")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--coeffs", type=float, nargs="+", default=[0.01, 0.05, 0.1, 0.3])
    parser.add_argument("--splits", nargs="*", default=["validation", "test"], choices=list(DEFAULT_SPLIT_SEEDS))
    for split, first in DEFAULT_SPLIT_SEEDS.items():
        parser.add_argument(f"--{split}_seed", type=int, default=first, help=f"first {split} episode seed")
    parser.add_argument("--episodes_clean", type=int, default=50, help="clean test episodes per row")
    parser.add_argument("--episodes_occlusion", type=int, default=25, help="occlusion test episodes per row")
    parser.add_argument("--episodes_validation", type=int, default=20, help="per condition and row")
    parser.add_argument("--rnd_input", default="fused")
    parser.add_argument("--report", type=Path, default=None)
    args = parser.parse_args()
    args.split_seeds = {split: getattr(args, f"{split}_seed") for split in DEFAULT_SPLIT_SEEDS}
    args.argv = ["benchmarks/eq6_sweep.py", *sys.argv[1:]]
    if any(not (math.isfinite(m) and m >= 0) for m in args.coeffs):
        parser.error(f"--coeffs must be finite and >= 0, got {args.coeffs}")
    path = calibrated(args)
    for split in args.splits:
        if split == "validation":
            n = {c: args.episodes_validation for c in CONDITIONS}
        else:
            n = {"clean": args.episodes_clean, "occlusion": args.episodes_occlusion}
        run(args, path, split, n)
    emit(report(args), args.report)
    if args.report:  # every episode's seed and outcome, beside the report (the u traces stay in --out)
        results = {
            split: {row: {c: [[e["seed"], e["success"]] for e in cell["episodes"]] for c, cell in cells.items()}
                    for row, cells in load(args.out, split, args.coeffs).items()}
            for split in DEFAULT_SPLIT_SEEDS
        }  # fmt: skip
        (args.report.parent / "results.json").write_text(json.dumps(results))


if __name__ == "__main__":
    main()
