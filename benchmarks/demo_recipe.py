"""The demo's recipe, chosen on validation seeds and reported on test seeds, at one training-time budget.

`make demo` has minutes, not hours: what matters is how many clean grasps a recipe reaches in the training
time the demo can spend, so every recipe gets about the same wall time on this machine (its steps are set
from its measured speed) rather than the same steps. The recipes, one training each (same data and
training seed):

    pooled        the arm preset (vib_arm_sim.json) with the floor on the action only: the demo until now
    pooled_lr3    the same at three times the learning rate (trunk included)
    tokens_l3     the token network starting narrow (vib_arm_tokens.json's fields) on a trunk cut after
                  layer3: 48 image cells instead of 192, so a step costs about a third less

Each checkpoint is rolled out by `lerobot-eval` with its own run time on the clean validation seeds, where the
recipe with the most successes is chosen (a tie goes to the one listed first), then on the test seeds, which
no choice saw. Every stage is saved as it finishes; rerun the command to resume.

    python benchmarks/demo_recipe.py --dataset_root data/arm_near --out outputs/demo_recipe \
        --output benchmarks/results/demo_recipe_cpu_2core/report.md
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
}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--dataset_root", type=Path, required=True)
    p.add_argument("--preset", type=Path, default=ROOT / "configs/policy/vib_arm_sim.json")
    p.add_argument("--recipes", nargs="+", default=list(RECIPES), choices=list(RECIPES))
    p.add_argument("--seed", type=int, default=1000)
    p.add_argument("--threads", type=int, default=2, help="torch threads per training or evaluation")
    p.add_argument("--val_seed", type=int, default=400000)
    p.add_argument("--val_episodes", type=int, default=20)
    p.add_argument("--test_seed", type=int, default=600000)
    p.add_argument("--test_episodes", type=int, default=50)
    p.add_argument("--out", type=Path, default=Path("outputs/demo_recipe"))
    p.add_argument("--output", type=Path, default=None, help="write the Markdown report here")
    args = p.parse_args()
    start = time.time()

    # One at a time, with both cores: the training minutes are the demo's.
    checkpoints = {r: train(r, args, extra=RECIPES[r][1], steps=RECIPES[r][2]) for r in args.recipes}
    base = {r: args.out / r / f"seed_{args.seed}" for r in args.recipes}
    val = {r: evaluate(checkpoints[r], base[r] / f"val_{args.val_seed}", args.val_seed, args.val_episodes, args)
           for r in args.recipes}  # fmt: skip
    chosen = max(args.recipes, key=lambda r: (val[r][0], -args.recipes.index(r)))
    (args.out / "choice.json").write_text(json.dumps({"chosen": chosen, "validation": val}, indent=2))
    test = {r: evaluate(checkpoints[r], base[r] / f"test_{args.test_seed}", args.test_seed, args.test_episodes, args)
            for r in args.recipes}  # fmt: skip

    rows = []
    for r in args.recipes:
        minutes, loss = training_summary(base[r])
        mark = " **(chosen)**" if r == chosen else ""
        what, _, steps = RECIPES[r]
        rows.append(
            f"| `{r}`{mark} | {what} | {steps} | {minutes:.1f} | {val[r][0]}/{val[r][1]} | {cell(*test[r])} | "
            f"{loss if loss is not None else '-'} |"
        )
    report = "\n".join(
        [
            "# The demo's recipe at one training-time budget, chosen on validation seeds",
            "",
            f"Machine: {cpu_name()}, {os.cpu_count()} CPUs, {platform.platform()}; torch {torch.__version__}. "
            f"One training at a time, {args.threads} torch threads.",
            f"Command: `python benchmarks/demo_recipe.py {' '.join(sys.argv[1:])}`",
            f"Training seed {args.seed}, one training per recipe. Each checkpoint acts with its own run time. "
            f"Validation: {args.val_episodes} clean episodes from seed {args.val_seed}, where the recipe was chosen "
            "(most successes; a tie goes to the one listed first). "
            f"Test: {args.test_episodes} clean episodes from seed {args.test_seed}, which no choice saw.",
            "",
            "| recipe | what | steps | training min | validation successes | test successes [95% Wilson] | "
            "last logged loss |",
            "| --- | --- | ---: | ---: | ---: | --- | ---: |",
            *rows,
        ]
    )
    write_report(report, base, start, args.output)


if __name__ == "__main__":
    main()
