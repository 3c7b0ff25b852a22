"""VIB vs ACT compute cost, measured in one run on one machine.

For each image size: training throughput (samples/s of forward + backward + AdamW step on a synthetic batch,
both policies with their default architectures, same chunk size, same batch), the latency of a
`select_action` call that runs the network (batch 1, `n_action_steps=1` as with temporal ensembling), and
the mean `select_action` time per step with ACT's action queue (`n_action_steps=chunk_size`): ACT runs the
network once per chunk, VIB also encodes every step's observation for its uncertainty.
Prints a Markdown table with VIB/ACT ratios and, with --output, writes it to a file.

    python benchmarks/bench_policy.py --sizes 120x160 480x640 --output benchmarks/results/cpu.md
"""

from __future__ import annotations

import argparse
import platform
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import torch
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.policies.act.configuration_act import ACTConfig
from lerobot.policies.act.modeling_act import ACTPolicy

from lerobot_vib.configuration_vib import VIBConfig
from lerobot_vib.modeling_vib import VIBPolicy


def features(h: int, w: int) -> dict:
    return dict(
        input_features={
            "observation.images.top": PolicyFeature(FeatureType.VISUAL, (3, h, w)),
            "observation.state": PolicyFeature(FeatureType.STATE, (14,)),
        },
        output_features={"action": PolicyFeature(FeatureType.ACTION, (14,))},
    )


KINDS = ("act", "vib", "vib_u_at_plans")


def make_policy(kind: str, h: int, w: int, chunk_size: int, device: str) -> torch.nn.Module:
    common = dict(device=device, pretrained_backbone_weights=None, chunk_size=chunk_size, n_action_steps=1)
    if kind == "vib":
        return VIBPolicy(VIBConfig(**common, **features(h, w))).to(device)
    if kind == "vib_u_at_plans":  # uncertainty only when a chunk is planned: ACT's cost with the queue
        return VIBPolicy(VIBConfig(**common, **features(h, w), uncertainty_every_step=False)).to(device)
    return ACTPolicy(ACTConfig(**common, **features(h, w))).to(device)


def batch(h: int, w: int, b: int, chunk_size: int, device: str, with_action: bool = True) -> dict:
    out = {
        "observation.images.top": torch.rand(b, 3, h, w, device=device),
        "observation.state": torch.randn(b, 14, device=device),
    }
    if with_action:
        out["action"] = torch.randn(b, chunk_size, 14, device=device)
        out["action_is_pad"] = torch.zeros(b, chunk_size, dtype=torch.bool, device=device)
    return out


def timed(fn: Callable[[], object], warmup: int, repeats: int, device: str) -> float:
    """Median seconds per call."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        fn()
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def measure(kind: str, h: int, w: int, args: argparse.Namespace) -> dict:
    torch.manual_seed(0)
    policy = make_policy(kind, h, w, args.chunk_size, args.device)
    n_params = sum(p.numel() for p in policy.parameters())
    optimizer = torch.optim.AdamW(policy.get_optim_params(), lr=1e-5)
    train_batch = batch(h, w, args.batch_size, args.chunk_size, args.device)

    def train_step():
        policy.train()
        loss, _ = policy.forward(train_batch)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()

    step_s = timed(train_step, args.warmup, args.train_repeats, args.device)

    obs = batch(h, w, 1, args.chunk_size, args.device, with_action=False)
    policy.eval()
    policy.reset()
    # n_action_steps=1: every select_action call runs the network, as with temporal ensembling.
    latency_s = timed(lambda: policy.select_action(obs), args.warmup, args.latency_repeats, args.device)

    policy.config.n_action_steps = args.chunk_size  # ACT's action queue over a whole chunk
    policy.reset()
    policy.select_action(obs)
    chunk_s = timed(
        lambda: [policy.select_action(obs) for _ in range(args.chunk_size)], 1, args.queue_repeats, args.device
    )
    return {
        "params_m": n_params / 1e6,
        "samples_per_s": args.batch_size / step_s,
        "latency_ms": 1e3 * latency_s,
        "queue_ms": 1e3 * chunk_s / args.chunk_size,
    }


def machine(device: str) -> str:
    if device.startswith("cuda"):
        return torch.cuda.get_device_name()
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{cpu}, {torch.get_num_threads()} threads"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", nargs="+", default=["120x160", "480x640"], help="image sizes HxW")
    parser.add_argument("--chunk_size", type=int, default=100)
    parser.add_argument("--batch_size", type=int, default=8)
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument("--train_repeats", type=int, default=5)
    parser.add_argument("--latency_repeats", type=int, default=10)
    parser.add_argument("--queue_repeats", type=int, default=3, help="chunks timed in queue mode")
    parser.add_argument("--output", type=Path, default=None, help="also write the table to this file")
    args = parser.parse_args()

    rows = []
    for size in args.sizes:
        h, w = (int(x) for x in size.split("x"))
        res = {kind: measure(kind, h, w, args) for kind in KINDS}
        rows.append((size, res))
        print(f"{size}: {res}", file=sys.stderr)

    lines = [
        "| image | policy | params (M) | train samples/s | select_action ms, network every step | "
        "select_action ms/step, queue of a chunk |",
        "| --- | --- | ---: | ---: | ---: | ---: |",
    ]
    for size, res in rows:
        for kind in KINDS:
            r = res[kind]
            lines.append(
                f"| {size} | {kind} | {r['params_m']:.1f} | {r['samples_per_s']:.2f} | {r['latency_ms']:.1f} "
                f"| {r['queue_ms']:.1f} |"
            )
        a, v, p = res["act"], res["vib"], res["vib_u_at_plans"]
        lines.append(
            f"| {size} | **VIB / ACT** | {v['params_m'] / a['params_m']:.2f} | "
            f"**{v['samples_per_s'] / a['samples_per_s']:.2f}x** | "
            f"**{v['latency_ms'] / a['latency_ms']:.2f}x** | **{v['queue_ms'] / a['queue_ms']:.2f}x** "
            f"(u at plans only: **{p['queue_ms'] / a['queue_ms']:.2f}x**) |"
        )
    header = (
        f"Machine: {machine(args.device)}; torch {torch.__version__}; device {args.device}; "
        f"chunk_size {args.chunk_size}; "
        f"train batch {args.batch_size}; median of {args.train_repeats} train steps and "
        f"{args.latency_repeats} select_action calls after {args.warmup} warm-up calls.\n"
        f"Command: python benchmarks/bench_policy.py {' '.join(sys.argv[1:])}\n"
        "Ratios: samples/s VIB/ACT (above 1: VIB trains faster); times VIB/ACT (below 1: VIB acts faster).\n"
    )
    table = header + "\n" + "\n".join(lines) + "\n"
    print(table)
    if args.output:
        args.output.parent.mkdir(parents=True, exist_ok=True)
        args.output.write_text(table)


if __name__ == "__main__":
    main()
