"""The demo's stop score, chosen on validation rollouts by the rule that chose the policy's default score.

For each training of the demo's recipe (`benchmarks/demo_recipe.py`'s checkpoints): calibrate it on its
recording, roll it out on clean and on occluded validation episodes with `lerobot-vib-eval` (every traced score
per step), and apply `choose_score_on_validation`: each (score, threshold) set on the first half of the clean
rollouts and judged on the other half and on the occluded ones; among those that stop at most 10% of the clean
half, the one that stops the most occlusions within 5 steps of the board's entry. The trainings' rows are pooled
by summing each pair's counts. Every stage is saved as it finishes; rerun the command to resume.

    python benchmarks/demo_score.py --recipe_out outputs/demo_recipe --recipe tokens_48x64 \
        --dataset_root data/arm_near_48x64 --seeds 1000 2000 \
        --output benchmarks/results/demo_recipe_48x64_cpu_2core/score_choice.md
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import subprocess
import sys
from collections import defaultdict
from pathlib import Path

from report import as_typed, cpu_name

from lerobot_vib.scripts.benchmark_report import STOP_WITHIN, _episodes, score_stops

BIN = Path(sys.executable).parent
REPO_ID = "local/vib_arm_grasp_block_scripted"
ALPHA, MAX_FALSE = 0.1, 0.1


def run(cmd: list[str], done: Path) -> None:
    if done.exists():
        return
    print(as_typed(cmd), flush=True)
    env = {**os.environ, "MUJOCO_GL": "egl"}
    subprocess.run(cmd, check=True, capture_output=True, env=env)


def cell(eval_dir: Path) -> dict:
    """A benchmark cell from lerobot-vib-eval's trace: seeds, u, every score's u and success per episode."""
    info = json.loads((eval_dir / "uncertainty_info.json").read_text())
    rows = defaultdict(list)
    with (eval_dir / "uncertainty_trace.csv").open() as f:
        for row in csv.DictReader(f):
            rows[int(row["episode"])].append(row)
    episodes = [rows[e["episode_ix"]] for e in info["per_episode"]]
    names = [k.removeprefix("u_") for k in episodes[0][0] if k.startswith("u_")]
    return {
        "seeds": [e["seed"] for e in info["per_episode"]],
        "success": [e["success"] for e in info["per_episode"]],
        "u": [[float(r["u"]) for r in ep] for ep in episodes],
        "scores": {n: [[float(r[f"u_{n}"]) for r in ep] for ep in episodes] for n in names},
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--recipe_out", type=Path, required=True)
    p.add_argument("--recipe", default="tokens_48x64")
    p.add_argument("--dataset_root", type=Path, required=True)
    p.add_argument("--seeds", type=int, nargs="+", default=[1000, 2000])
    p.add_argument("--val_seed", type=int, default=400000)
    p.add_argument("--episodes", type=int, default=20, help="occluded validation episodes per training")
    p.add_argument(
        "--clean_episodes", type=int, default=40, help="clean ones: half set each threshold (a band needs 18)"
    )
    p.add_argument(
        "--policy_flag",
        dest="policy_flags",
        action="append",
        default=[],
        help="a run-time override for the rollouts, as --policy_flag=--policy.temporal_ensemble_coeff=3.0",
    )
    p.add_argument("--tag", default="", help="a suffix for the rollouts' folders, for a set of --policy_flag")
    p.add_argument("--output", type=Path, default=None)
    args = p.parse_args()

    pooled: dict[tuple[str, str], dict[str, int]] = {}
    for seed in args.seeds:
        base = args.recipe_out / args.recipe / f"seed_{seed}"
        trained = base / "train" / "checkpoints" / "last" / "pretrained_model"
        ckpt = trained.with_name("pretrained_model_calibrated")
        run(
            [str(BIN / "lerobot-vib-calibrate"), f"--policy.path={trained}", f"--dataset.repo_id={REPO_ID}",
             f"--dataset.root={args.dataset_root}"],
            ckpt / "model.safetensors",
        )  # fmt: skip
        cells = {}
        occluded = ["--env.perturbation.occlusion=true"]
        kinds = {"clean": ([], args.clean_episodes), "occlusion": (occluded, args.episodes)}
        for name, (flags, episodes) in kinds.items():
            out = base / f"score_{name}_{args.val_seed}_{episodes}{args.tag}"
            run(
                [str(BIN / "lerobot-vib-eval"), f"--policy.path={ckpt}", "--policy.device=cpu", *args.policy_flags,
                 "--env.type=vib_arm",
                 f"--env.dataset_root={args.dataset_root}", *flags, f"--eval.n_episodes={episodes}",
                 "--eval.batch_size=10", "--eval.use_async_envs=false", f"--seed={args.val_seed}",
                 f"--output_dir={out}"],
                out / "uncertainty_info.json",
            )  # fmt: skip
            cells[name] = cell(out)
        half = len(cells["clean"]["seeds"]) // 2
        judged = {"normal": _episodes(cells["clean"], slice(half, None)), "occlusion": cells["occlusion"]}
        for score, by_threshold in score_stops(judged, _episodes(cells["clean"], slice(None, half)), ALPHA).items():
            for threshold, row in by_threshold.items():
                if "occlusion_episodes" not in row:
                    continue
                total = pooled.setdefault((score, threshold), defaultdict(int))
                for key in ("in_time", "occlusion_episodes", "false_stops", "clean_episodes"):
                    total[key] += row[key]
    allowed = {k: v for k, v in pooled.items() if v["false_stops"] <= MAX_FALSE * v["clean_episodes"]}
    order = list(pooled)
    if not allowed:
        sys.exit(f"No score and threshold stops at most {MAX_FALSE:.0%} of the judged clean rollouts: none to choose.")
    chosen = max(allowed, key=lambda k: (allowed[k]["in_time"], -allowed[k]["false_stops"], -order.index(k)))
    lines = [
        "# The demo's stop score, chosen on validation rollouts",
        "",
        f"Machine: {cpu_name()}, {os.cpu_count()} CPUs. Command: `python benchmarks/demo_score.py "
        f"{' '.join(sys.argv[1:])}`",
        f"Recipe `{args.recipe}`, training seeds {', '.join(map(str, args.seeds))}; per training "
        f"{args.clean_episodes} clean and {args.episodes} occluded validation episodes from seed {args.val_seed}. "
        f"Each threshold is set at alpha = {ALPHA} on the first half of the clean rollouts, judged on the "
        "other half and the occluded ones; counts summed over the trainings. Chosen: the most occlusions "
        f"stopped within {STOP_WITHIN} steps of the board's entry among those stopping at most "
        f"{MAX_FALSE:.0%} of the judged clean rollouts (ties: fewer clean stops, then the order below).",
        "",
        f"**Chosen: `{chosen[0]}` with the `{chosen[1]}` threshold.**",
        "",
        "| score | threshold | occlusions stopped in time | clean rollouts stopped |",
        "| --- | --- | ---: | ---: |",
    ]
    for (score, threshold), v in pooled.items():
        mark = " **(chosen)**" if (score, threshold) == chosen else ""
        lines.append(
            f"| `{score}`{mark} | {threshold} | {v['in_time']}/{v['occlusion_episodes']} | "
            f"{v['false_stops']}/{v['clean_episodes']} |"
        )
    text = "\n".join(lines) + "\n"
    print(text)
    if args.output:
        args.output.parent.mkdir(parents=True, exist_ok=True)
        args.output.write_text(text)


if __name__ == "__main__":
    main()
