"""Which trunk normalization lets a policy learn from scratch: learning curves and success, VIB and ACT.

Every variant trains on the same dataset with the same seed, batch, step budget and recipe (a train preset
from `configs/policy/`, which also sets the architecture of both policies), then is evaluated with LeRobot's
eval loop (`eval_policy_all`) on the same episode seeds of `aloha_fast` at the dataset's image size and
shadow setting. ACT is LeRobot's, built with `pretrained_backbone_weights=None` (its frozen batch norm is then
the identity); `act+<norm>` swaps its trunk's norm layers (`backbone.swap_norm_layers`) to compare like with
like. Curves (training L1 and rate every `--log_every` steps) and results are saved as they come, and a
stopped run resumes: finished variants are skipped, a variant in training continues from its last state.
Each trained variant is also saved as a LeRobot checkpoint, `<out>/<variant>/pretrained_model`.

    python benchmarks/backbone_norm.py --dataset_root data/tc_120x160 --steps 1500 \
        --variants vib+frozen_bn vib+batch_norm vib+group_norm act+frozen_bn act+group_norm \
        --out outputs/backbone_norm --output benchmarks/results/backbone_norm_cpu_2core.md
"""

from __future__ import annotations

import argparse
import csv
import itertools
import json
import math
import platform
import shutil
import sys
import time
from pathlib import Path

import numpy as np
import torch
from lerobot.datasets.factory import resolve_delta_timestamps
from lerobot.datasets.lerobot_dataset import LeRobotDataset, LeRobotDatasetMetadata
from lerobot.envs.factory import make_env, make_env_pre_post_processors
from lerobot.envs.utils import close_envs
from lerobot.policies.act.configuration_act import ACTConfig
from lerobot.policies.factory import make_policy, make_pre_post_processors
from lerobot.scripts.lerobot_eval import eval_policy_all
from lerobot.utils.random_utils import set_seed
from report import cpu_name, emit

from lerobot_vib.backbone import swap_norm_layers
from lerobot_vib.configuration_vib import VIBConfig
from lerobot_vib.metrics import wilson_interval
from lerobot_vib.scripts.benchmark import ACT_FROM_VIB
from lerobot_vib.sim.env_config import AlohaFastEnv
from lerobot_vib.sim.recorder import SIDECAR

ROOT = Path(__file__).resolve().parents[1]
# VIB fields that ACT shares under another name (the preset sets VIB's; ACT gets the same sizes).


def policy_config(kind: str, norm: str, preset: dict) -> VIBConfig | ACTConfig:
    fields = {k: v for k, v in preset["policy"].items() if k not in ("type", "normalization_mapping")}
    fields.update(device="cpu", push_to_hub=False, pretrained_backbone_weights=None)
    if kind == "vib":
        return VIBConfig(**{**fields, "backbone_norm": norm})
    act = {ACT_FROM_VIB[k]: v for k, v in fields.items() if k in ACT_FROM_VIB}
    return ACTConfig(device="cpu", push_to_hub=False, pretrained_backbone_weights=None, **act)


def build(kind: str, norm: str, preset: dict, meta: LeRobotDatasetMetadata):
    cfg = policy_config(kind, norm, preset)
    policy = make_policy(cfg, ds_meta=meta)
    if kind == "act" and norm != "frozen_bn":
        swap_norm_layers(policy.model.backbone, norm)
    return cfg, policy


def train_variant(name: str, preset: dict, args, meta: LeRobotDatasetMetadata, out: Path):
    """Train with LeRobot's dataset, processors and optimizer preset; returns (cfg, policy, pre, post)."""
    kind, norm = name.split("+")
    set_seed(args.seed)
    cfg, policy = build(kind, norm, preset, meta)
    pre, post = make_pre_post_processors(cfg, dataset_stats=meta.stats)
    optimizer = cfg.get_optimizer_preset().build(policy.get_optim_params())
    state_path, curve_path = out / "train_state.pt", out / "curve.csv"
    step, rows = 0, []
    if state_path.exists():  # resume an interrupted variant
        state = torch.load(state_path, weights_only=True)  # tensors and numbers only: no code runs
        policy.load_state_dict(state["policy"])
        optimizer.load_state_dict(state["optimizer"])
        torch.set_rng_state(state["rng"])
        step, rows = state["step"], state["rows"]
    if step >= args.steps:
        return cfg, policy, pre, post

    dataset = LeRobotDataset(meta.repo_id, root=args.dataset_root, delta_timestamps=resolve_delta_timestamps(cfg, meta))
    loader = torch.utils.data.DataLoader(
        dataset, batch_size=preset["batch_size"], shuffle=True, num_workers=args.num_workers, drop_last=True
    )
    batches = iter(())
    l1s, rates, t0 = [], [], time.perf_counter()
    policy.train()
    while step < args.steps:
        try:
            batch = next(batches)
        except StopIteration:
            batches = iter(loader)
            batch = next(batches)
        loss, info = policy.forward(pre(batch))
        loss.backward()
        torch.nn.utils.clip_grad_norm_(policy.parameters(), preset.get("optimizer", {}).get("grad_clip_norm", 10.0))
        optimizer.step()
        optimizer.zero_grad()
        step += 1
        l1s.append(info["l1_loss"])
        rates.append(info.get("rate", float("nan")))  # ACT has no rate
        if step % args.log_every == 0 or step == args.steps:
            elapsed = time.perf_counter() - t0
            rows.append(dict(step=step, l1=float(np.mean(l1s)), rate=float(np.mean(rates)), seconds=elapsed))
            print(f"  {name} step {step}: l1 {rows[-1]['l1']:.4f} rate {rows[-1]['rate']:.2f}", flush=True)
            l1s, rates = [], []
            if step % args.save_every == 0 or step == args.steps:
                tmp = state_path.with_suffix(".tmp")
                torch.save(
                    dict(
                        policy=policy.state_dict(),
                        optimizer=optimizer.state_dict(),
                        rng=torch.get_rng_state(),
                        step=step,
                        rows=rows,
                    ),
                    tmp,
                )
                tmp.replace(state_path)
    # Seconds are per resumed segment; the curve keeps the sum as wall time.
    offset = 0.0
    for prev, row in zip([None, *rows[:-1]], rows, strict=True):
        if prev is not None and row["seconds"] < prev["seconds"]:
            offset = prev["seconds"] + offset
        row["wall_s"] = row["seconds"] + offset
    with curve_path.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=["step", "l1", "rate", "seconds", "wall_s"])
        writer.writeheader()
        writer.writerows(rows)
    return cfg, policy, pre, post


def exportable(name: str) -> bool:
    """ACT's config cannot say that its trunk's norms were swapped, so only such a variant is not saved."""
    kind, norm = name.split("+")
    return kind == "vib" or norm == "frozen_bn"


def export(cfg, policy, pre, post, path: Path) -> None:
    """A LeRobot checkpoint of the trained variant, for `lerobot-eval`, `lerobot-vib-calibrate`, ..."""
    tmp = path.with_name(path.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    policy.save_pretrained(tmp)
    pre.save_pretrained(tmp)
    post.save_pretrained(tmp)
    tmp.replace(path)


def evaluate(cfg, policy, pre, post, env_cfg: AlohaFastEnv, args) -> dict:
    policy.eval()
    if isinstance(cfg, VIBConfig):
        cfg.uncertainty_every_step = False  # no stop in this benchmark: actions are the same, the cost is not
    envs = make_env(env_cfg, n_envs=args.eval_batch_size)
    env_pre, env_post = make_env_pre_post_processors(env_cfg, cfg)
    try:
        with torch.no_grad():
            info = eval_policy_all(
                envs=envs,
                policy=policy,
                env_preprocessor=env_pre,
                env_postprocessor=env_post,
                preprocessor=pre,
                postprocessor=post,
                n_episodes=args.eval_episodes,
                start_seed=args.eval_seed,
            )
    finally:
        close_envs(envs)
    overall = info["overall"]
    return dict(pc_success=overall["pc_success"], avg_max_reward=overall["avg_max_reward"], n=args.eval_episodes)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--dataset_root", type=Path, required=True)
    p.add_argument("--preset", type=Path, default=ROOT / "configs/policy/vib_cpu.json")
    p.add_argument("--variants", nargs="+", default=["vib+frozen_bn", "vib+batch_norm", "vib+group_norm"])
    p.add_argument("--steps", type=int, default=None, help="training steps (default: the preset's)")
    p.add_argument("--log_every", type=int, default=50)
    p.add_argument("--save_every", type=int, default=250)
    p.add_argument("--num_workers", type=int, default=1)
    p.add_argument("--seed", type=int, default=1000)
    p.add_argument("--eval_episodes", type=int, default=20)
    p.add_argument("--eval_batch_size", type=int, default=10)
    p.add_argument("--eval_seed", type=int, default=100000)
    p.add_argument("--out", type=Path, default=Path("outputs/backbone_norm"))
    p.add_argument("--output", type=Path, default=None, help="write the Markdown report here")
    args = p.parse_args()
    preset = json.loads(args.preset.read_text())
    args.steps = args.steps or preset["steps"]

    recording = json.loads((args.dataset_root / SIDECAR).read_text())["settings"]
    meta = LeRobotDatasetMetadata("local/dataset", root=args.dataset_root)
    env_cfg = AlohaFastEnv(dataset_root=str(args.dataset_root))
    results = {}
    for name in args.variants:
        out = args.out / name
        out.mkdir(parents=True, exist_ok=True)
        result_path = out / "result.json"
        if result_path.exists():
            results[name] = json.loads(result_path.read_text())
            print(f"{name}: done before, {results[name]['pc_success']:.0f}% success")
            if exportable(name) and not (out / "pretrained_model").exists():
                export(*train_variant(name, preset, args, meta, out), out / "pretrained_model")
            continue
        print(f"{name}: training {args.steps} steps", flush=True)
        cfg, policy, pre, post = train_variant(name, preset, args, meta, out)
        if exportable(name):
            export(cfg, policy, pre, post, out / "pretrained_model")
        t0 = time.perf_counter()
        result = evaluate(cfg, policy, pre, post, env_cfg, args)
        curve = list(csv.DictReader((out / "curve.csv").open()))
        result.update(
            eval_s=time.perf_counter() - t0,
            train_s=float(curve[-1]["wall_s"]),
            final_l1=float(curve[-1]["l1"]),
            final_rate=float(curve[-1]["rate"]),
            params=sum(p.numel() for p in policy.parameters()),
        )
        result_path.write_text(json.dumps(result, indent=2))
        results[name] = result
        print(f"{name}: {result['pc_success']:.0f}% success over {result['n']} episodes", flush=True)

    report = render(args, preset, recording, results)
    plot(args, results)
    emit(report, args.output)


def render(args, preset: dict, recording: dict, results: dict) -> str:
    lines = [
        "# Backbone normalization from scratch: learning curves and success",
        "",
        f"Machine: {cpu_name()}, CPU only; torch {torch.__version__}, Python {platform.python_version()}.",
        f"Command: `python benchmarks/{Path(__file__).name} {' '.join(sys.argv[1:])}`",
        "",
        f"Data: {args.dataset_root} ({recording['task']}, {recording['image_height']}x{recording['image_width']}, "
        f"cameras {recording['cameras']}, shadows {recording['shadows']}). Recipe: `{args.preset.name}` "
        f"(batch {preset['batch_size']}), {args.steps} steps, seed {args.seed}. Evaluation: LeRobot's eval loop, "
        f"`aloha_fast` at the same size, seeds from {args.eval_seed}.",
        "",
        "| variant | params | s/step (median) | final L1 | final rate | success (95% Wilson) | max reward (of 4) |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for name, r in results.items():
        curve = list(csv.DictReader((args.out / name / "curve.csv").open()))
        windows = [float(b["wall_s"]) - float(a["wall_s"]) for a, b in itertools.pairwise(curve)]
        per_step = [w / args.log_every for w in windows if w > 0]
        k = round(r["pc_success"] * r["n"] / 100)
        low, high = wilson_interval(k, r["n"])
        rate = "-" if math.isnan(r["final_rate"]) else f"{r['final_rate']:.2f}"  # ACT has no rate
        lines.append(
            f"| {name} | {r['params'] / 1e6:.1f}M | {np.median(per_step):.2f} | {r['final_l1']:.4f} | "
            f"{rate} | {k}/{r['n']} ({100 * low:.0f}-{100 * high:.0f}%) | {r['avg_max_reward']:.2f} |"
        )
    lines += [
        "",
        "Final L1 and rate: means over the last logging window (training mode, normalized actions; ACT's L1 is "
        "its reconstruction term, without its KL). s/step: the median over logging windows, so that periods "
        "when other work shared the CPU do not count; total wall time per variant is in `result.json`.",
    ]
    lines += ["", f"![curves]({Path(args.output).stem}.png)" if args.output else ""]
    return "\n".join(lines) + "\n"


def plot(args, results: dict) -> None:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return
    fig, (ax_l1, ax_rate) = plt.subplots(1, 2, figsize=(11, 4))
    for name in results:
        curve = list(csv.DictReader((args.out / name / "curve.csv").open()))
        steps = [int(r["step"]) for r in curve]
        ax_l1.plot(steps, [float(r["l1"]) for r in curve], label=name)
        if name.startswith("vib"):
            ax_rate.plot(steps, [float(r["rate"]) for r in curve], label=name)
    ax_l1.set(xlabel="step", ylabel="training L1 (normalized actions)", yscale="log", title="L1")
    ax_rate.set(xlabel="step", ylabel="rate R (nats)", title="VIB rate")
    ax_l1.legend()
    ax_rate.legend()
    fig.tight_layout()
    target = args.output.with_suffix(".png") if args.output else args.out / "curves.png"
    fig.savefig(target, dpi=100)


if __name__ == "__main__":
    main()
