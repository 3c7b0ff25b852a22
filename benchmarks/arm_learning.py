"""VIB and ACT on the simulated arm with one budget: success over training, through LeRobot's own commands.

Each variant is trained by `lerobot-train` (VIB from the preset, ACT with the same architecture, recipe and
budget: `benchmark.act_recipe_flags`), saving a checkpoint every `save_freq` steps. Every checkpoint is then
evaluated by `lerobot-eval` on `--env.type=vib_arm` with the recording's settings, on the same episode seeds;
the final VIB checkpoint also with black images (a policy that ignores vision would not notice). Wall time of
a checkpoint: the time its training processes ran until its file was written, read from the timestamps of the
training log; a run that was stopped and resumed is charged for each of its runs, up to its last log line,
and not for the time between them. Everything is saved as it finishes, so a stopped run resumes
(`lerobot-train --resume=true` for an unfinished training). The training
commands that were run are kept in `<out>/<variant>/command.txt` and listed in the report. `--eval_only
--eval_seed=N` scores the same checkpoints on other episodes (`<out>/<variant>/seedN/`), to check a result
that was chosen on the default seeds.

    python benchmarks/arm_learning.py --dataset_root data/arm_grasp_block --out outputs/arm_learning \
        --output benchmarks/results/arm_learning_cpu_2core.md
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
from datetime import datetime
from pathlib import Path

import torch
from report import as_typed, cpu_name, emit

from lerobot_vib.metrics import wilson_interval
from lerobot_vib.scripts.benchmark import act_recipe_flags

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
DEFAULT_EVAL_SEED = 100000


def eval_dir(args, variant: str, name: str) -> Path:
    """Where one evaluation is kept: evaluations on other episode seeds go to their own folder, so a cached
    result is never read back for seeds it was not run on."""
    base = args.out / variant
    return base / name if args.eval_seed == DEFAULT_EVAL_SEED else base / f"seed{args.eval_seed}" / name


def train_command(variant: str, preset_path: Path, preset: dict, args, out: Path) -> list[str]:
    common = [
        f"--dataset.repo_id={args.repo_id}",
        f"--dataset.root={args.dataset_root}",
        f"--output_dir={out}",
        f"--seed={args.seed}",
    ]
    if variant == "vib":
        return [str(BIN / "lerobot-train"), f"--config_path={preset_path}", *common]
    run = [f"--{k}={preset[k]}" for k in ("batch_size", "steps", "num_workers", "log_freq", "save_freq")]
    return [
        str(BIN / "lerobot-train"),
        "--policy.type=act",
        "--policy.device=cpu",
        "--policy.push_to_hub=false",
        "--policy.pretrained_backbone_weights=null",
        *act_recipe_flags(preset),
        *run,
        "--wandb.enable=false",
        *common,
    ]


def train(variant: str, preset_path: Path, preset: dict, args) -> Path:
    out = args.out / variant / "train"
    last = out / "checkpoints" / "last" / "pretrained_model"
    log = args.out / variant / "train.log"
    if last.exists() and _step(last.parent) >= preset["steps"]:
        return out
    cmd = train_command(variant, preset_path, preset, args, out)
    if last.exists():  # an interrupted training: LeRobot resumes from its last checkpoint
        cmd = [cmd[0], f"--config_path={last / 'train_config.json'}", "--resume=true"]
    print(f"{variant}: {as_typed(cmd)}", flush=True)
    log.parent.mkdir(parents=True, exist_ok=True)
    with (args.out / variant / "command.txt").open("a") as f:
        f.write(as_typed(cmd) + "\n")
    with log.open("a") as f:
        subprocess.run(cmd, stdout=f, stderr=subprocess.STDOUT, check=True, env={**os.environ, "MUJOCO_GL": "egl"})
    return out


def _step(checkpoint: Path) -> int:
    state = checkpoint / "training_state" / "training_step.json"
    return json.loads(state.read_text())["step"] if state.exists() else int(checkpoint.name)


def evaluate(checkpoint: Path, args, out: Path, extra: list[str] = ()) -> dict:
    info_path = out / "eval_info.json"
    cmd = [
        str(BIN / "lerobot-eval"),
        f"--policy.path={checkpoint}",
        "--policy.device=cpu",
        "--env.type=vib_arm",
        f"--env.dataset_root={args.dataset_root}",
        f"--eval.n_episodes={args.eval_episodes}",
        f"--eval.batch_size={args.eval_batch_size}",
        "--eval.use_async_envs=false",
        f"--seed={args.eval_seed}",
        f"--output_dir={out}",
        *extra,
    ]
    kept = out / "eval_command.txt"
    if info_path.exists():
        if kept.exists() and kept.read_text().strip() not in (as_typed(cmd), " ".join(cmd)):
            raise SystemExit(f"{out} holds an evaluation made with other flags:\n{kept.read_text()}")
    else:
        print(as_typed(cmd), flush=True)
        subprocess.run(cmd, check=True, capture_output=True, env={**os.environ, "MUJOCO_GL": "egl"})
        kept.write_text(as_typed(cmd) + "\n")
    overall = json.loads(info_path.read_text())["overall"]
    return dict(success=round(overall["pc_success"] * overall["n_episodes"] / 100), n=overall["n_episodes"])


def training_runs(log: Path) -> list[tuple[float, float]]:
    """(first, last) timestamp of each lerobot-train run in the log (`INFO 2026-11-22 21:28:56 ...` lines)."""
    runs: list[list[float]] = []
    for line in log.read_text(errors="replace").replace("\r", "\n").splitlines():
        start = line.find("INFO 2")
        if start < 0:
            continue
        fields = line[start:].split(maxsplit=4)
        stamp = datetime.strptime(" ".join(fields[1:3]), "%Y-%m-%d %H:%M:%S").timestamp()
        # Every lerobot-train run opens its log with its configuration as a dict: `... train.py:272 {'batch_size'`.
        if not runs or (len(fields) > 4 and fields[4].startswith("{")):
            runs.append([stamp, stamp])
        runs[-1][1] = stamp
    if not runs:
        raise ValueError(f"No timestamp in {log}.")
    return [(first, last) for first, last in runs]


def training_seconds(runs: list[tuple[float, float]], until: float) -> float:
    """Seconds of training up to time `until`: the runs before it in full, the one it falls in up to it."""
    spent = 0.0
    for first, last in runs:
        if until <= last:
            return spent + max(0.0, until - first)
        spent += last - first
    return spent + until - runs[-1][1]  # written after the last log line


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--dataset_root", type=Path, required=True)
    p.add_argument("--repo_id", default="local/vib_arm_grasp_block_scripted")
    p.add_argument("--preset", type=Path, default=ROOT / "configs/policy/vib_arm_sim.json")
    p.add_argument("--variants", nargs="+", default=["vib", "act"], choices=["vib", "act"])
    p.add_argument("--seed", type=int, default=1000)
    p.add_argument("--eval_episodes", type=int, default=50)
    p.add_argument("--eval_batch_size", type=int, default=10)
    p.add_argument("--eval_seed", type=int, default=DEFAULT_EVAL_SEED)
    p.add_argument("--out", type=Path, default=Path("outputs/arm_learning"))
    p.add_argument("--note", default="", help="a remark on how this run went, printed in the report")
    p.add_argument("--eval_only", action="store_true", help="evaluate the checkpoints saved so far; train nothing")
    p.add_argument("--output", type=Path, default=None, help="write the Markdown report here")
    p.add_argument(
        "--inference",
        action="append",
        default=[],
        metavar="NAME=FLAGS",
        help="also evaluate every VIB checkpoint with these lerobot-eval policy flags (space-separated), e.g. "
        "'uncertainty=--policy.temporal_ensemble=uncertainty --policy.n_action_steps=1'; repeatable",
    )
    args = p.parse_args()
    inference = dict(parse_inference(spec) for spec in args.inference)
    preset = json.loads(args.preset.read_text())

    rows = []
    for variant in args.variants:
        train_dir = args.out / variant / "train" if args.eval_only else train(variant, args.preset, preset, args)
        runs = training_runs(args.out / variant / "train.log")
        checkpoints = sorted(
            (c for c in (train_dir / "checkpoints").iterdir() if c.name.isdigit()), key=lambda c: int(c.name)
        )
        for ckpt in checkpoints:
            model = ckpt / "pretrained_model"
            wall = training_seconds(runs, (model / "model.safetensors").stat().st_mtime)
            result = evaluate(model, args, eval_dir(args, variant, f"eval_{ckpt.name}"))
            rows.append(dict(variant=variant, step=int(ckpt.name), wall_s=wall, images="clean", **result))
            print(f"{variant} step {ckpt.name}: {result['success']}/{result['n']}", flush=True)
            for name, flags in inference.items() if variant == "vib" else ():
                result = evaluate(model, args, eval_dir(args, variant, f"eval_{ckpt.name}_{name}"), flags)
                rows.append(
                    dict(variant=variant, step=int(ckpt.name), wall_s=wall, images="clean", inference=name, **result)
                )
                print(f"{variant} step {ckpt.name} ({name}): {result['success']}/{result['n']}", flush=True)
        if variant == "vib":
            last = checkpoints[-1]
            black = ["--env.perturbation.black_images=true"]
            blind = evaluate(last / "pretrained_model", args, eval_dir(args, variant, f"eval_{last.name}_black"), black)
            rows.append(dict(variant=variant, step=int(last.name), wall_s=None, images="black", **blind))
    seeds = "" if args.eval_seed == DEFAULT_EVAL_SEED else f"_seed{args.eval_seed}"
    (args.out / f"results{seeds}.json").write_text(json.dumps(rows, indent=2))
    emit(render(args, preset, rows), args.output)
    plot(rows, args)


def parse_inference(spec: str) -> tuple[str, list[str]]:
    """'NAME=FLAG FLAG ...' -> (NAME, [FLAG, ...]); NAME names the evaluation folders and the report's rows."""
    name, sep, flags = spec.partition("=")
    if not sep or not name.isidentifier() or not flags.split() or not all(f.startswith("--") for f in flags.split()):
        raise SystemExit(f"--inference wants NAME=--flag [--flag ...] with NAME a plain word, got {spec!r}.")
    return name, flags.split()


def render(args, preset: dict, rows: list[dict]) -> str:
    inference = dict(parse_inference(spec) for spec in args.inference)
    described = "; ".join(f"{name}: `{' '.join(flags)}`" for name, flags in inference.items())
    lines = [
        "# The simulated arm: VIB and ACT learning to grasp with one CPU budget",
        "",
        f"Machine: {cpu_name()}, CPU only; torch {torch.__version__}, Python {platform.python_version()}.",
        f"Command: `python benchmarks/{Path(__file__).name} {' '.join(sys.argv[1:])}`",
        "",
        f"Data: {args.dataset_root} (scripted grasps recorded by `lerobot-vib-record-sim --task=grasp_block`). "
        f"Recipe: `{args.preset.name}` (batch {preset['batch_size']}, {preset['steps']} steps, seed {args.seed}); "
        f"ACT is LeRobot's with the same sizes, learning rates and budget. Evaluation: `lerobot-eval "
        f"--env.type=vib_arm`, {args.eval_episodes} episodes from seed {args.eval_seed}, the same for every row.",
        "",
        "| policy | step | wall time (min) | images | inference | success (95% Wilson) |",
        "| --- | ---: | ---: | --- | --- | ---: |",
    ]
    for r in rows:
        low, high = wilson_interval(r["success"], r["n"])
        wall = "-" if r["wall_s"] is None else f"{r['wall_s'] / 60:.0f}"
        lines.append(
            f"| {r['variant']} | {r['step']} | {wall} | {r['images']} | {r.get('inference', 'as trained')} | "
            f"{r['success']}/{r['n']} "
            f"({100 * r['success'] / r['n']:.0f}%, {100 * low:.0f}-{100 * high:.0f}%) |"
        )
    lines += [
        "",
        "Training commands:",
        "",
        *[
            f"- {v}: `{line}`"
            for v in args.variants
            for line in (args.out / v / "command.txt").read_text().splitlines()
            if (args.out / v / "command.txt").exists()
        ],
        "",
        *([f"Inference: {described}", ""] if described else []),
        "Wall time includes everything the training process did up to that checkpoint (data loading, saving), "
        "on a machine where other work may have shared the two cores; evaluation time is not included.",
        *(["", f"Note: {args.note}"] if args.note else []),
        "",
        f"![success over training]({Path(args.output).stem}.png)" if args.output else "",
    ]
    return "\n".join(lines) + "\n"


def plot(rows: list[dict], args) -> None:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return
    fig, ax = plt.subplots(figsize=(6, 4))
    clean_rows = [r for r in rows if r["images"] == "clean"]
    for variant, inference in dict.fromkeys((r["variant"], r.get("inference")) for r in clean_rows):
        clean = [r for r in clean_rows if (r["variant"], r.get("inference")) == (variant, inference)]
        label = variant if inference is None else f"{variant} ({inference})"
        ax.plot([r["step"] for r in clean], [100 * r["success"] / r["n"] for r in clean], marker="o", label=label)
    ax.set(xlabel="training step", ylabel="success (%)", ylim=(-2, 102), title="grasp_block, clean episodes")
    ax.legend()
    fig.tight_layout()
    fig.savefig(args.output.with_suffix(".png") if args.output else args.out / "success.png", dpi=100)


if __name__ == "__main__":
    main()
