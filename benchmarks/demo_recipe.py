"""The demo's recipe, chosen on validation seeds and reported on test seeds, at one training-time budget.

`make demo` has minutes, not hours: what matters is how many clean grasps a recipe reaches in the training
time the demo can spend, so every recipe gets about the same wall time on this machine (its steps are set
from its measured speed) rather than the same steps. The recipes, one training per training seed (same data and
seeds):

    pooled        the arm preset (vib_arm_sim.json) with the floor on the action only: the demo until now
    pooled_lr3    the same at three times the learning rate (trunk included)
    tokens_l3     the token network starting narrow (vib_arm_tokens.json's fields) on a trunk cut after
                  layer3: 48 image cells instead of 192, so a step costs about a third less
    tokens_48x64  the same token network on the layer2 trunk, trained and rolled out on the task recorded at
                  48x64 (`--small_dataset_root`): 48 image cells too, and a step costs about 30% of one at 96x128

Each checkpoint is rolled out by `lerobot-eval` with its own run time on the clean validation seeds, where the
recipe with the most successes is chosen (a tie goes to the one listed first), then on the test seeds, which
no choice saw. Every stage is saved as it finishes; rerun the command to resume.

    python benchmarks/demo_recipe.py --dataset_root data/arm_near --out outputs/demo_recipe \
        --output benchmarks/results/demo_recipe_cpu_2core/report.md
    python benchmarks/demo_recipe.py --dataset_root data/arm_near --small_dataset_root data/arm_near_48x64 \
        --recipes pooled tokens_48x64 --seeds 1000 2000 --out outputs/demo_recipe \
        --output benchmarks/results/demo_recipe_48x64_cpu_2core/report.md
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import torch
from floor_choice import cell, evaluate, train, training_summary, write_report
from report import cpu_name

ROOT = Path(__file__).resolve().parents[1]
TOKENS = ["--policy.encoder=tokens", "--policy.posterior_logvar_init=-6.0", "--policy.sample_latent_at_inference=true"]
FLOOR_ACTION = ["--policy.normalization_floor_features=action"]
# name: (what it is, its flags on top of vib_arm_sim.json, its steps)
RECIPES = {
    "pooled": ("the demo until now", FLOOR_ACTION, 2000),
    "pooled_lr3": (
        "learning rate 3e-4",
        [*FLOOR_ACTION, "--policy.optimizer_lr=3e-4", "--policy.optimizer_lr_backbone=3e-4"],
        2000,
    ),
    "tokens_l3": ("token network, narrow start, trunk to layer3", [*TOKENS, "--policy.backbone_layer=layer3"], 1500),
    "tokens_48x64": ("token network, narrow start, trunk to layer2, images 48x64", TOKENS, 3000),
}
SMALL = {"tokens_48x64"}  # recipes that train and act on `--small_dataset_root`


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--dataset_root", type=Path, required=True)
    p.add_argument(
        "--small_dataset_root",
        type=Path,
        default=None,
        help="the same task recorded at 48x64 (lerobot-vib-record-sim --image_height=48 --image_width=64), "
        f"for {sorted(SMALL)}",
    )
    p.add_argument("--preset", type=Path, default=ROOT / "configs/policy/vib_arm_sim.json")
    p.add_argument("--recipes", nargs="+", default=list(RECIPES), choices=list(RECIPES))
    p.add_argument("--seeds", type=int, nargs="+", default=[1000], help="training seeds, one training each")
    p.add_argument("--threads", type=int, default=2, help="torch threads per training or evaluation")
    p.add_argument("--val_seed", type=int, default=400000)
    p.add_argument("--val_episodes", type=int, default=20)
    p.add_argument("--test_seed", type=int, default=600000)
    p.add_argument("--test_episodes", type=int, default=50)
    p.add_argument("--out", type=Path, default=Path("outputs/demo_recipe"))
    p.add_argument("--output", type=Path, default=None, help="write the Markdown report here")
    args = p.parse_args()
    if SMALL & set(args.recipes) and args.small_dataset_root is None:
        p.error(f"{sorted(SMALL & set(args.recipes))} need --small_dataset_root (the task recorded at 48x64)")
    start = time.time()
    runs = [(r, seed) for seed in args.seeds for r in args.recipes]

    def run_args(r: str, seed: int) -> argparse.Namespace:
        """Each recipe trains and acts on its own recording (the env takes its image size from it)."""
        root = args.small_dataset_root if r in SMALL else args.dataset_root
        return argparse.Namespace(**{**vars(args), "dataset_root": root, "seed": seed})

    # One at a time, with both cores: the training minutes are the demo's.
    checkpoints = {(r, s): train(r, run_args(r, s), extra=RECIPES[r][1], steps=RECIPES[r][2]) for r, s in runs}
    base = {(r, s): args.out / r / f"seed_{s}" for r, s in runs}

    def rollouts(split: str, seed: int, episodes: int) -> dict[tuple[str, int], tuple[int, int]]:
        return {run: evaluate(checkpoints[run], base[run] / f"{split}_{seed}", seed, episodes, run_args(*run))
                for run in runs}  # fmt: skip

    val = rollouts("val", args.val_seed, args.val_episodes)
    pooled_val = {r: sum(val[r, s][0] for s in args.seeds) for r in args.recipes}
    chosen = max(args.recipes, key=lambda r: (pooled_val[r], -args.recipes.index(r)))
    choice = {"chosen": chosen, "validation": {f"{r} seed {s}": val[r, s] for r, s in runs}}
    (args.out / "choice.json").write_text(json.dumps(choice, indent=2))
    test = rollouts("test", args.test_seed, args.test_episodes)

    rows = []
    for r in args.recipes:
        what, _, steps = RECIPES[r]
        mark = " **(chosen)**" if r == chosen else ""
        for s in args.seeds:
            minutes, loss = training_summary(base[r, s])
            rows.append(
                f"| `{r}`{mark} | {what} | {s} | {steps} | {minutes:.1f} | {val[r, s][0]}/{val[r, s][1]} | "
                f"{cell(*test[r, s])} | {loss if loss is not None else '-'} |"
            )
        if len(args.seeds) > 1:
            n_val, n_test = len(args.seeds) * args.val_episodes, len(args.seeds) * args.test_episodes
            rows.append(
                f"| `{r}` | all seeds | | | | {pooled_val[r]}/{n_val} | "
                f"{cell(sum(test[r, s][0] for s in args.seeds), n_test)} | |"
            )
    report = "\n".join(
        [
            "# The demo's recipe at one training-time budget, chosen on validation seeds",
            "",
            f"Machine: {cpu_name()}, {os.cpu_count()} CPUs, {platform.platform()}; torch {torch.__version__}. "
            f"One training at a time, {args.threads} torch threads.",
            f"Command: `python benchmarks/demo_recipe.py {' '.join(sys.argv[1:])}`",
            f"Training seeds {', '.join(map(str, args.seeds))}, one training per recipe and seed. Each checkpoint "
            f"acts with its own run time. Validation: {args.val_episodes} clean episodes from seed {args.val_seed} "
            "per training, where the recipe was chosen (most successes over the training seeds; a tie goes to the "
            f"one listed first). Test: {args.test_episodes} clean episodes from seed {args.test_seed} per training, "
            "which no choice saw.",
            "",
            "| recipe | what | training seed | steps | training min | validation successes | "
            "test successes [95% Wilson] | last logged loss |",
            "| --- | --- | ---: | ---: | ---: | ---: | --- | ---: |",
            *rows,
        ]
    )
    write_report(report, {f"{r}, seed {s}": d for (r, s), d in base.items()}, start, args.output)


if __name__ == "__main__":
    main()
