"""Success rate of the scripted ALOHA demonstrations over consecutive seeds (physics only, no rendering).

A seed succeeds when the joint replay of its scripted episode reaches gym-aloha's maximum reward (4), the
criterion the recorder keeps episodes by.

    python benchmarks/scripted_success.py --num_seeds 50 --output benchmarks/results/scripted_success.md
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from report import emit

from lerobot_vib.sim.scripted import script_episode
from lerobot_vib.sim.sim_tasks import replay_max_reward


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tasks", nargs="+", default=["transfer_cube", "insertion"])
    parser.add_argument("--num_seeds", type=int, default=50)
    parser.add_argument("--first_seed", type=int, default=0)
    parser.add_argument("--output", type=Path, default=None)
    args = parser.parse_args()

    seeds = range(args.first_seed, args.first_seed + args.num_seeds)
    lines = [
        f"Command: python benchmarks/scripted_success.py {' '.join(sys.argv[1:])}",
        "",
        "| task | seeds | successes | rate | failed seeds |",
        "| --- | --- | ---: | ---: | --- |",
    ]
    for task in args.tasks:
        failed = [s for s in seeds if replay_max_reward(task, s, script_episode(task, s).joint_actions) < 4]
        n_ok = len(seeds) - len(failed)
        lines.append(
            f"| {task} | {seeds.start}-{seeds.stop - 1} | {n_ok} | {100 * n_ok / len(seeds):.0f}% | {failed} |"
        )
        print(lines[-1], file=sys.stderr)
    emit("\n".join(lines) + "\n", args.output)


if __name__ == "__main__":
    main()
