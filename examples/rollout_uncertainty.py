"""Roll a VIB checkpoint out in simulation (ALOHA or the 6-DoF arm) and trace its uncertainty step by step
(paper Fig. 3).

Writes, under --out:
  trace.csv    one row per step: step, rate, u, gamma, stopped, occluded, reward
  summary.json the run's settings, the threshold in force and where it comes from, success, every stop and
               what ended it (the scene clearing, u falling while the board was in view, the halt), and mean
               u on clean vs occluded steps
  trace.png    u over time with the threshold in force at each step, stop intervals and occlusion shaded,
               and key frames
               (needs matplotlib: pip install 'lerobot_policy_vib[examples]')

An occlusion can be placed on a range of steps, as in the paper's Fig. 3c, and the safety stop switched on
for the run. On ALOHA the occlusion is a grey block over the middle of every camera image; on the arm
(`--task=grasp_block`) it is a board that enters the scene between the camera and the workspace:

    python examples/rollout_uncertainty.py --policy_path=outputs/demo/train/checkpoints/last/pretrained_model \
        --occlude=150:230 --safety --out=outputs/uncertainty
    python examples/rollout_uncertainty.py --task=grasp_block \
        --policy_path=outputs/arm/checkpoints/last/pretrained_model --occlude=30:60 --safety --out=outputs/arm_occlusion

The loop is a plain gym loop around `policy.select_action`: the safety stop and `policy.last_step` need
nothing from lerobot-eval.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

os.environ.setdefault("MUJOCO_GL", "egl")

from lerobot.envs.utils import preprocess_observation
from lerobot.policies.factory import make_pre_post_processors

from lerobot_vib.modeling_vib import VIBPolicy
from lerobot_vib.sim.aloha_env import FastAlohaEnv
from lerobot_vib.sim.arm_env import DEFAULT_WORKSPACE, WORKSPACES, ArmGraspEnv
from lerobot_vib.sim.arm_env import EPISODE_LENGTH as ARM_EPISODE_LENGTH
from lerobot_vib.sim.perturbations import PerturbationConfig

TASKS = ("transfer_cube", "insertion", "grasp_block")


def occlude(image: np.ndarray, fraction: float = 0.4) -> np.ndarray:
    """A grey block over the middle `fraction` of the image (height and width)."""
    h, w = image.shape[:2]
    dh, dw = int(h * fraction / 2), int(w * fraction / 2)
    out = image.copy()
    out[h // 2 - dh : h // 2 + dh, w // 2 - dw : w // 2 + dw] = 128
    return out


def stop_intervals(stopped: list[bool]) -> list[tuple[int, int]]:
    intervals, start = [], None
    for t, s in enumerate([*stopped, False]):
        if s and start is None:
            start = t
        elif not s and start is not None:
            intervals.append((start, t - 1))
            start = None
    return intervals


def what_ended(first: int, last: int, rows: list[dict], occluded_steps: set[int]) -> dict:
    """A stop from step `first` to `last` (both stopped) and what ended it, in words."""
    if rows[last]["halted"]:
        ended = "halted: held safety.max_hold_steps steps; only policy.resume() ends it"
    elif last == len(rows) - 1:
        ended = "still stopped when the episode ended"
    elif occluded_steps and min(occluded_steps) <= first <= max(occluded_steps):
        cleared = last + 1 > max(occluded_steps)
        ended = (
            "the scene cleared: u fell below the threshold after the board left"
            if cleared
            else "u fell below the threshold while the board was still in view"
        )
    else:
        ended = "u fell below the threshold"
    return {"first_step": first, "last_step": last, "ended": ended}


def rollout(args: argparse.Namespace) -> dict:
    overrides = []
    if args.safety:
        overrides.append("--safety.enabled=true")
    if args.gamma is not None:
        overrides.append(f"--safety.gamma={args.gamma}")
    from lerobot.configs.policies import PreTrainedConfig

    config = PreTrainedConfig.from_pretrained(args.policy_path, cli_overrides=overrides)
    config.device = args.device
    policy = VIBPolicy.from_pretrained(args.policy_path, config=config)
    preprocessor, postprocessor = make_pre_post_processors(policy.config, pretrained_path=str(args.policy_path))

    cameras = [key.removeprefix("observation.images.") for key in policy.config.image_features]
    _, height, width = next(iter(policy.config.image_features.values())).shape
    occluded_steps = set(range(*args.occlude)) if args.occlude else set()
    arm = args.task == "grasp_block"
    shadows = arm if args.shadows is None else args.shadows  # the recorders' defaults
    if arm:  # the occluder is a body in the scene, rendered by MuJoCo
        occlusion = {}
        if args.occlude:
            occlusion = dict(occlusion=True, occlusion_start=args.occlude[0], occlusion_duration=len(occluded_steps))
        env = ArmGraspEnv(
            observation_height=height, observation_width=width, cameras=cameras, shadows=shadows,
            workspace=args.workspace, perturbation=PerturbationConfig(**occlusion),
        )  # fmt: skip
    else:
        env = FastAlohaEnv(
            args.task, cameras=cameras, observation_height=height, observation_width=width, shadows=shadows
        )
    steps = args.steps or (ARM_EPISODE_LENGTH if arm else 400)

    obs, _ = env.reset(seed=args.seed)
    policy.reset()
    rows, frames, max_reward, success = [], {}, 0.0, False
    for t in tqdm(range(steps), desc="rollout", unit="step"):
        occluded = t in occluded_steps
        if occluded and not arm:
            obs = {**obs, "pixels": {cam: occlude(img) for cam, img in obs["pixels"].items()}}
        batch = preprocessor(preprocess_observation(obs))
        with torch.inference_mode():
            action = postprocessor(policy.select_action(batch))
        step = policy.last_step.row(0)
        key_frame = step["just_stopped"] or step["resumed"] or t in (0, steps - 1, min(occluded_steps, default=-1))
        if key_frame and len(frames) < 8:
            frames[t] = obs["pixels"][cameras[0]]
        obs, reward, terminated, _, info = env.step(action[0].numpy())
        max_reward = max(max_reward, float(reward))
        success = success or bool(info.get("is_success", False))
        rows.append({"step": t, **step, "occluded": occluded, "reward": float(reward)})
        if terminated:  # as lerobot-eval: the episode ends at success
            frames.setdefault(t, obs["pixels"][cameras[0]])
            break
    env.close()

    u = np.array([r["u"] for r in rows])
    occl = np.array([r["occluded"] for r in rows])
    intervals = stop_intervals([r["stopped"] for r in rows])
    summary = {
        "policy": str(args.policy_path),
        "task": args.task,
        "seed": args.seed,
        "steps": len(rows),
        "occluded_steps": [min(occluded_steps), max(occluded_steps)] if occluded_steps else None,
        "safety_enabled": policy.config.safety.enabled,
        "score": policy.last_step.score,
        "threshold": policy.threshold_in_force(step=0)["source"],
        "gamma": rows[0]["gamma"],  # at the first step; trace.csv has the threshold in force at every step
        "success": success,
        "max_reward": max_reward,
        "stop_intervals": intervals,
        "stops": [what_ended(a, b, rows, occluded_steps) for a, b in intervals],
        "mean_u_clean": float(u[~occl].mean()) if (~occl).any() else None,
        "mean_u_occluded": float(u[occl].mean()) if occl.any() else None,
    }
    args.out.mkdir(parents=True, exist_ok=True)
    with open(args.out / "trace.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    (args.out / "summary.json").write_text(json.dumps(summary, indent=2))
    plot(rows, summary, frames, args.out / "trace.png")
    return summary


def plot(rows: list[dict], summary: dict, frames: dict[int, np.ndarray], path: Path) -> None:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib is not installed: trace.csv and summary.json written, no plot.")
        return
    steps = [r["step"] for r in rows]
    keys = sorted(frames)
    fig = plt.figure(figsize=(11, 5.5))
    grid = fig.add_gridspec(2, max(len(keys), 1), height_ratios=[2.2, 1])
    ax = fig.add_subplot(grid[0, :])
    ax.plot(steps, [r["u"] for r in rows], color="tab:blue", lw=1.5, label=f"u = {summary['score']} / its mean")
    # the threshold in force at each step: a time band moves it (and stands still while the arm holds)
    ax.step(steps, [r["gamma"] for r in rows], where="post", color="tab:red", ls="--", lw=1.2, label="threshold")
    if summary["occluded_steps"]:
        a, b = summary["occluded_steps"]
        ax.axvspan(a, b + 1, color="grey", alpha=0.2, label="occluded")
    for i, (a, b) in enumerate(summary["stop_intervals"]):
        ax.axvspan(a, b + 1, color="tab:red", alpha=0.15, label="safety stop" if i == 0 else None)
    for k in keys:
        ax.axvline(k, color="black", lw=0.5, alpha=0.4)
    ax.set_xlabel("step")
    ax.set_ylabel("normalized uncertainty u")
    outcome = "success" if summary["success"] else "failure"
    ax.set_title(f"{summary['task']}, seed {summary['seed']}: {outcome}")
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)  # outside: u peaks at the first steps
    for i, k in enumerate(keys):
        sub = fig.add_subplot(grid[1, i])
        sub.imshow(frames[k])
        sub.set_title(f"t={k}", fontsize=8)
        sub.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--policy_path", type=Path, required=True)
    parser.add_argument("--task", choices=TASKS, default="transfer_cube")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--steps", type=int, default=None, help="default: the task's episode length")
    parser.add_argument(
        "--occlude",
        type=lambda s: tuple(int(x) for x in s.split(":")),
        default=None,
        help="start:stop steps to occlude (stop excluded)",
    )
    parser.add_argument("--safety", action="store_true", help="enable the threshold stop for this run")
    parser.add_argument("--gamma", type=float, default=None, help="override the stop threshold")
    parser.add_argument(
        "--shadows",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="render shadows (use the setting the training data was recorded with; default: the recorder's, "
        "off for ALOHA, on for the arm)",
    )
    parser.add_argument(
        "--workspace",
        choices=list(WORKSPACES),
        default=DEFAULT_WORKSPACE,
        help="the arm's block placement ranges (use the one the training data was recorded in)",
    )
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--out", type=Path, default=Path("outputs/uncertainty"))
    args = parser.parse_args()
    print(json.dumps(rollout(args), indent=2))


if __name__ == "__main__":
    main()
