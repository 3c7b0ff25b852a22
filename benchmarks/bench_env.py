"""Steps per second of gym-aloha's env against `FastAlohaEnv` and the simulated arm, in one run on one machine.

Each ALOHA env replays the same scripted transfer-cube joint actions from the same seed. gym-aloha renders
three 480x640 cameras per step (returning only `top`); FastAlohaEnv renders only what it returns. The arm
(`ArmGraspEnv`, `--env.type=vib_arm`) replays its own scripted grasp; the ratio is to gym-aloha's default.

    python benchmarks/bench_env.py --steps 100 --output benchmarks/results/env_cpu_2core.md
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

import gym_aloha  # noqa: F401  (registers gym_aloha/*)
import gymnasium as gym
from report import cpu_name, emit

from lerobot_vib.sim.aloha_env import FastAlohaEnv
from lerobot_vib.sim.arm_env import ArmGraspEnv
from lerobot_vib.sim.scripted import script_episode
from lerobot_vib.sim.sim_tasks import get_task

VARIANTS = [
    ("gym-aloha (3 cameras rendered, top returned)", "480x640", None),
    ("FastAlohaEnv top", "480x640", dict(cameras=["top"], observation_height=480, observation_width=640)),
    ("FastAlohaEnv top", "120x160", dict(cameras=["top"], observation_height=120, observation_width=160)),
    (
        "FastAlohaEnv top, shadows=false",
        "120x160",
        dict(cameras=["top"], observation_height=120, observation_width=160, shadows=False),
    ),
    ("FastAlohaEnv physics only (cameras=[])", "-", dict(cameras=[])),
]
ARM_VARIANTS = [
    ("ArmGraspEnv scene (default)", "96x128", dict(cameras=["scene"])),
    ("ArmGraspEnv scene + wrist", "96x128", dict(cameras=["scene", "wrist"])),
    ("ArmGraspEnv scene", "480x640", dict(cameras=["scene"], observation_height=480, observation_width=640)),
    ("ArmGraspEnv physics only (cameras=[])", "-", dict(cameras=[])),
]


def steps_per_second(env: gym.Env, actions, seed: int, limit: int | None = None) -> float:
    env.reset(seed=seed)
    env.step(actions[0])  # warm-up: first render creates the GL context
    steps = actions[1 : 1 + limit] if limit else actions[1:]
    t0 = time.perf_counter()
    for action in steps:
        env.step(action)
    return len(steps) / (time.perf_counter() - t0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--output", type=Path, default=None)
    args = parser.parse_args()

    actions = script_episode("transfer_cube", args.seed).joint_actions[: args.steps + 1]
    rows = []
    for name, size, kwargs in VARIANTS:
        if kwargs is None:
            env = gym.make("gym_aloha/AlohaTransferCube-v0", obs_type="pixels_agent_pos").unwrapped
        else:
            env = FastAlohaEnv("transfer_cube", **kwargs)
        sps = steps_per_second(env, actions, args.seed)
        rows.append((name, size, sps))
        print(f"{name} {size}: {sps:.1f} steps/s", file=sys.stderr)
    arm_actions = get_task("grasp_block").scripted_actions(args.seed)
    for name, size, kwargs in ARM_VARIANTS:
        env = ArmGraspEnv(**kwargs)
        # the grasp ends the episode at its success; replay from the start as many times as needed
        reps = -(-args.steps // len(arm_actions))
        sps = steps_per_second(env, list(arm_actions) * reps, args.seed, limit=args.steps)
        env.close()
        rows.append((name, size, sps))
        print(f"{name} {size}: {sps:.1f} steps/s", file=sys.stderr)

    base = rows[0][2]
    lines = [
        f"Machine: {cpu_name()}; MUJOCO_GL={os.environ['MUJOCO_GL']}; "
        f"{args.steps} steps of scripted actions (transfer-cube for ALOHA, the grasp for the arm), seed {args.seed}.",
        f"Command: python benchmarks/bench_env.py {' '.join(sys.argv[1:])}",
        "",
        "| env | image | steps/s | vs gym-aloha |",
        "| --- | --- | ---: | ---: |",
    ]
    lines += [f"| {name} | {size} | {sps:.1f} | {sps / base:.1f}x |" for name, size, sps in rows]
    emit("\n".join(lines) + "\n", args.output)


if __name__ == "__main__":
    main()
