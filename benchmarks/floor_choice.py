"""Which features the normalization floor should cover, chosen on validation seeds and reported on test seeds.

The floor (`normalization.py`) lifts the scale of a dimension the demonstrations barely vary, so that a
deviation in it cannot dominate the inputs and u. On the arm it lifts joint 3 of the state and of the action,
and it also flattens that joint's twitch at contact, a cue the network may have read. The options, one
training each (same preset, budget and training seed):

    all      the floor on every feature (the preset's default)
    state    on the state vectors only (`--policy.normalization_floor_features=state`)
    action   on the action only (`--policy.normalization_floor_features=action`)
    off      no floor (`--policy.normalization_floor=null`)

`--encoder=tokens` trains the token network (`--policy.encoder=tokens`) instead of the pooled one.

Each training runs `lerobot-train` (two side by side, one torch thread each); each checkpoint is rolled out by
`lerobot-eval` with its own run time on the clean validation seeds, where the option with the most successes
is chosen (a tie goes to the one listed first), then on the test seeds, which no choice saw. Every stage is
saved as it finishes; rerun the command to resume.

    python benchmarks/floor_choice.py --dataset_root data/arm_near --out outputs/floor_choice \
        --output benchmarks/results/floor_choice_demo_budget_cpu_2core/report.md
    python benchmarks/floor_choice.py --dataset_root data/arm_near --encoder tokens --options all action off \
        --parallel 3 --out outputs/floor_choice_tokens \
        --output benchmarks/results/floor_choice_tokens_demo_budget_cpu_2core/report.md
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import torch
from arm_learning import training_runs
from report import as_typed, cpu_name

from lerobot_vib.metrics import wilson_interval

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
OPTIONS = {
    "all": ["--policy.normalization_floor_features=all"],
    "state": ["--policy.normalization_floor_features=state"],
    "action": ["--policy.normalization_floor_features=action"],
    "off": ["--policy.normalization_floor=null"],
}
ENCODER = {"pooled": [], "tokens": ["--policy.encoder=tokens"]}
MEANING = {
    "all": "every feature (the preset's default)",
    "state": "the state only",
    "action": "the action only",
    "off": "no floor",
}


def trained_step(train_dir: Path) -> int:
    state = train_dir / "checkpoints" / "last" / "training_state" / "training_step.json"
    return json.loads(state.read_text())["step"] if state.is_file() else 0


def train(option: str, args, extra: list[str] | None = None, steps: int | None = None) -> Path:
    """Train one option (`extra`: its flags, by default the floor's; `steps`: by default `args.steps`)."""
    extra = [*ENCODER[args.encoder], *OPTIONS[option]] if extra is None else extra
    steps = args.steps if steps is None else steps
    run_dir = args.out / option / f"seed_{args.seed}"
    train_dir = run_dir / "train"
    last = train_dir / "checkpoints" / "last" / "pretrained_model"
    if trained_step(train_dir) >= steps:
        return last
    if last.exists():  # an interrupted training: LeRobot resumes from its last checkpoint
        cmd = [str(BIN / "lerobot-train"), f"--config_path={last / 'train_config.json'}", "--resume=true"]
    else:
        cmd = [str(BIN / "lerobot-train"), f"--config_path={args.preset}", f"--dataset.root={args.dataset_root}"]
        cmd += [*extra, f"--steps={steps}", f"--save_freq={min(1000, steps)}"]
        cmd += [f"--seed={args.seed}", f"--output_dir={train_dir}"]
    run_dir.mkdir(parents=True, exist_ok=True)
    print(as_typed(cmd), flush=True)
    with (run_dir / "command.txt").open("a") as f:
        f.write(as_typed(cmd) + "\n")
    env = {**os.environ, "OMP_NUM_THREADS": str(args.threads), "MUJOCO_GL": "egl"}
    with (run_dir / "train.log").open("a") as log:
        subprocess.run(cmd, stdout=log, stderr=subprocess.STDOUT, check=True, env=env)
    return last


def evaluate(checkpoint: Path, out: Path, seed: int, episodes: int, args) -> tuple[int, int]:
    info = out / "eval_info.json"
    cmd = [str(BIN / "lerobot-eval"), f"--policy.path={checkpoint}", "--policy.device=cpu", "--env.type=vib_arm"]
    cmd += [f"--env.dataset_root={args.dataset_root}", f"--eval.n_episodes={episodes}", "--eval.batch_size=10"]
    cmd += ["--eval.use_async_envs=false", f"--seed={seed}", f"--output_dir={out}"]
    if not info.is_file():
        print(as_typed(cmd), flush=True)
        env = {**os.environ, "OMP_NUM_THREADS": str(args.threads), "MUJOCO_GL": "egl"}
        subprocess.run(cmd, check=True, capture_output=True, env=env)
        (out / "eval_command.txt").write_text(as_typed(cmd) + "\n")
    overall = json.loads(info.read_text())["overall"]
    return round(overall["pc_success"] * overall["n_episodes"] / 100), overall["n_episodes"]


def last_loss(log: Path) -> float | None:
    """The last `loss:` that lerobot-train logged."""
    losses = [w for w in log.read_text(errors="replace").split() if w.startswith("loss:")]
    return float(losses[-1].split(":")[1]) if losses else None


def training_summary(run_dir: Path) -> tuple[float, float | None]:
    """Minutes of training (over every lerobot-train run in its log) and the last logged loss."""
    runs = training_runs(run_dir / "train.log")
    return sum(last - first for first, last in runs) / 60, last_loss(run_dir / "train.log")


def cell(successes: int, n: int) -> str:
    low, high = wilson_interval(successes, n)
    return f"{successes}/{n} = {100 * successes / n:.0f}% [{100 * low:.0f}-{100 * high:.0f}]"


def write_report(table: str, runs: dict[str, Path], start: float, output: Path | None) -> None:
    """Print the report (its head and table, then each run's training command and this run's time); save it
    to `output` if given."""
    commands = "\n".join(f"- `{name}`: `{(d / 'command.txt').read_text().splitlines()[0]}`" for name, d in runs.items())
    report = "\n".join(
        [
            table,
            "",
            "Training commands:",
            "",
            commands,
            "",
            f"This run of the script: {(time.time() - start) / 60:.1f} min (stages already saved are not rerun).",
            "",
        ]
    )
    print(report)
    if output:
        output.parent.mkdir(parents=True, exist_ok=True)
        output.write_text(report)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--dataset_root", type=Path, required=True)
    p.add_argument("--preset", type=Path, default=ROOT / "configs/policy/vib_arm_sim.json")
    p.add_argument("--encoder", default="pooled", choices=list(ENCODER), help="the network every option trains")
    p.add_argument("--options", nargs="+", default=list(OPTIONS), choices=list(OPTIONS))
    p.add_argument("--steps", type=int, default=2000)
    p.add_argument("--seed", type=int, default=1000)
    p.add_argument("--threads", type=int, default=1, help="torch threads per training or evaluation")
    p.add_argument("--parallel", type=int, default=2, help="trainings and evaluations side by side")
    p.add_argument("--val_seed", type=int, default=400000)
    p.add_argument("--val_episodes", type=int, default=20)
    p.add_argument("--test_seed", type=int, default=600000)
    p.add_argument("--test_episodes", type=int, default=50)
    p.add_argument("--out", type=Path, default=Path("outputs/floor_choice"))
    p.add_argument("--output", type=Path, default=None, help="write the Markdown report here")
    args = p.parse_args()
    start = time.time()

    with ThreadPoolExecutor(args.parallel) as pool:
        checkpoints = dict(zip(args.options, pool.map(lambda o: train(o, args), args.options), strict=True))
        base = {o: args.out / o / f"seed_{args.seed}" for o in args.options}

        def rollouts(seed: int, episodes: int, name: str) -> dict[str, tuple[int, int]]:
            runs = pool.map(lambda o: evaluate(checkpoints[o], base[o] / f"{name}_{seed}", seed, episodes, args),
                            args.options)  # fmt: skip
            return dict(zip(args.options, runs, strict=True))

        val = rollouts(args.val_seed, args.val_episodes, "val")
        chosen = max(args.options, key=lambda o: (val[o][0], -args.options.index(o)))
        (args.out / "choice.json").write_text(json.dumps({"chosen": chosen, "validation": val}, indent=2))
        test = rollouts(args.test_seed, args.test_episodes, "test")

    rows = []
    for o in args.options:
        minutes, loss = training_summary(base[o])
        mark = " **(chosen)**" if o == chosen else ""
        rows.append(
            f"| `{o}`{mark} | {MEANING[o]} | {val[o][0]}/{val[o][1]} | {cell(*test[o])} | {minutes:.1f} | "
            f"{loss if loss is not None else '-'} |"
        )
    report = "\n".join(
        [
            "# The normalization floor: which features it covers, chosen on validation seeds",
            "",
            f"Machine: {cpu_name()}, {os.cpu_count()} CPUs, {platform.platform()}; torch {torch.__version__}. "
            f"Trainings {args.parallel} side by side, {args.threads} torch thread each.",
            f"Command: `python benchmarks/floor_choice.py {' '.join(sys.argv[1:])}`",
            f"Preset `{args.preset.relative_to(ROOT) if args.preset.is_relative_to(ROOT) else args.preset}`, "
            f"the {args.encoder} network, {args.steps} steps, training seed {args.seed} (one training per option). "
            f"Each checkpoint acts with its own run time (the preset's). Validation: {args.val_episodes} clean "
            f"episodes from seed {args.val_seed}, where the option was chosen (most successes; a tie goes to the "
            "one listed first). "
            f"Test: {args.test_episodes} clean episodes from seed {args.test_seed}, which no choice saw.",
            "",
            "| floor | on | validation successes | test successes [95% Wilson] | training min | last logged loss |",
            "| --- | --- | ---: | --- | ---: | ---: |",
            *rows,
        ]
    )
    write_report(report, base, start, args.output)


if __name__ == "__main__":
    main()
