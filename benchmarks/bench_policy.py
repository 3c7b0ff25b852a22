"""VIB vs ACT compute cost, measured in one run on one machine.

For each image size: training throughput (samples/s of forward + backward + AdamW step on a synthetic batch,
both policies with their default architectures, same chunk size, same batch), the latency of a
`select_action` call that runs the network (batch 1, `n_action_steps=1` as with temporal ensembling), and
the mean `select_action` time per step with ACT's action queue (`n_action_steps=chunk_size`): ACT runs the
network once per chunk, VIB also encodes every step's observation for its uncertainty. `vib_tokens` is VIB
with `encoder=tokens` (the bottleneck on ACT's token memory, one token per trunk feature-map cell, so its cost
grows with the image).
Prints a Markdown table with VIB/ACT ratios and, with --output, writes it to a file.

    python benchmarks/bench_policy.py --sizes 120x160 480x640 --output benchmarks/results/cpu.md

`--vib KEY=VALUE` and `--act KEY=VALUE` (repeatable, VALUE read as JSON where it parses) change a field of
VIB's or ACT's config from its default, e.g. `--vib backbone_layer=layer3 --vib n_layers=2`.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import torch
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.policies.act.configuration_act import ACTConfig
from lerobot.policies.act.modeling_act import ACTPolicy
from report import cpu_name, emit

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


KINDS = ("act", "vib", "vib_u_at_plans", "vib_tokens")


def make_policy(
    kind: str, h: int, w: int, chunk_size: int, device: str, vib: dict | None = None, act: dict | None = None
) -> torch.nn.Module:
    common = dict(device=device, pretrained_backbone_weights=None, chunk_size=chunk_size, n_action_steps=1)
    if kind == "vib":
        return VIBPolicy(VIBConfig(**common, **features(h, w), **(vib or {}))).to(device)
    if kind == "vib_u_at_plans":  # uncertainty only when a chunk is planned: ACT's cost with the queue
        return VIBPolicy(VIBConfig(**common, **features(h, w), **(vib or {}), uncertainty_every_step=False)).to(device)
    if kind == "vib_tokens":  # the bottleneck on ACT's token memory: one token per feature-map cell
        return VIBPolicy(VIBConfig(**common, **features(h, w), **{**(vib or {}), "encoder": "tokens"})).to(device)
    return ACTPolicy(ACTConfig(**common, **features(h, w), **(act or {}))).to(device)


def overrides(pairs: list[str]) -> dict:
    """['n_layers=2', 'backbone_layer=layer3'] -> {'n_layers': 2, 'backbone_layer': 'layer3'}."""
    out = {}
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep or not key:
            raise SystemExit(f"Expected KEY=VALUE, got {pair!r}.")
        try:
            out[key] = json.loads(value)
        except json.JSONDecodeError:
            out[key] = value
    return out


def batch(h: int, w: int, b: int, chunk_size: int, device: str, with_action: bool = True) -> dict:
    out = {
        "observation.images.top": torch.rand(b, 3, h, w, device=device),
        "observation.state": torch.randn(b, 14, device=device),
    }
    if with_action:
        out["action"] = torch.randn(b, chunk_size, 14, device=device)
        out["action_is_pad"] = torch.zeros(b, chunk_size, dtype=torch.bool, device=device)
    return out


def timed_interleaved(fns: dict[str, Callable[[], object]], warmup: int, repeats: int, device: str) -> dict:
    """Median seconds per call of each function, the functions taking turns in every round so that a slow
    spell of a shared machine hits all of them alike."""
    for fn in fns.values():
        for _ in range(warmup):
            fn()
    times: dict[str, list[float]] = {name: [] for name in fns}
    for _ in range(repeats):
        for name, fn in fns.items():
            if device.startswith("cuda"):
                torch.cuda.synchronize()
            t0 = time.perf_counter()
            fn()
            if device.startswith("cuda"):
                torch.cuda.synchronize()
            times[name].append(time.perf_counter() - t0)
    return {name: statistics.median(t) for name, t in times.items()}


def measure(h: int, w: int, args: argparse.Namespace) -> dict[str, dict]:
    policies, train_steps, act_steps, queue_chunks = {}, {}, {}, {}
    train_batch = batch(h, w, args.batch_size, args.chunk_size, args.device)
    obs = batch(h, w, 1, args.chunk_size, args.device, with_action=False)
    for kind in KINDS:
        torch.manual_seed(0)
        policy = policies[kind] = make_policy(
            kind, h, w, args.chunk_size, args.device, overrides(args.vib), overrides(args.act)
        )
        optimizer = torch.optim.AdamW(policy.get_optim_params(), lr=1e-5)

        def train_step(policy=policy, optimizer=optimizer):
            policy.train()
            loss, _ = policy.forward(train_batch)
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()

        train_steps[kind] = train_step
    train_s = timed_interleaved(train_steps, args.warmup, args.train_repeats, args.device)

    for kind, policy in policies.items():
        policy.eval()
        policy.reset()
        # n_action_steps=1: every select_action call runs the network, as with temporal ensembling.
        act_steps[kind] = lambda policy=policy: policy.select_action(obs)
    latency_s = timed_interleaved(act_steps, args.warmup, args.latency_repeats, args.device)

    for kind, policy in policies.items():
        policy.config.n_action_steps = args.chunk_size  # ACT's action queue over a whole chunk
        policy.reset()
        policy.select_action(obs)  # each timed call below then holds exactly one network pass
        queue_chunks[kind] = lambda policy=policy: [policy.select_action(obs) for _ in range(args.chunk_size)]
    chunk_s = timed_interleaved(queue_chunks, 1, args.queue_repeats, args.device)

    # Where a VIB pass spends its time: the encoder (ResNet, MLPs, posterior) and the action transformer.
    vib = policies["vib"].model
    with torch.no_grad():
        z = vib.encode(obs).mean
        parts = timed_interleaved(
            {"encoder": lambda: vib.encode(obs), "decoder": lambda: vib.decoder(z)},
            args.warmup,
            args.latency_repeats,
            args.device,
        )
    return {
        kind: {
            "params_m": sum(p.numel() for p in policies[kind].parameters()) / 1e6,
            "samples_per_s": args.batch_size / train_s[kind],
            "latency_ms": 1e3 * latency_s[kind],
            "queue_ms": 1e3 * chunk_s[kind] / args.chunk_size,
            **({"encoder_ms": 1e3 * parts["encoder"], "decoder_ms": 1e3 * parts["decoder"]} if kind == "vib" else {}),
        }
        for kind in KINDS
    }


def machine(device: str) -> str:
    if device.startswith("cuda"):
        return torch.cuda.get_device_name()
    return f"{cpu_name()}, {torch.get_num_threads()} torch threads"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", nargs="+", default=["120x160", "480x640"], help="image sizes HxW")
    parser.add_argument("--chunk_size", type=int, default=100)
    parser.add_argument("--batch_size", type=int, default=8)
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument("--train_repeats", type=int, default=10)
    parser.add_argument("--latency_repeats", type=int, default=20)
    parser.add_argument("--queue_repeats", type=int, default=3, help="chunks timed in queue mode")
    parser.add_argument("--output", type=Path, default=None, help="also write the table to this file")
    parser.add_argument("--vib", action="append", default=[], metavar="KEY=VALUE", help="a VIBConfig field")
    parser.add_argument("--act", action="append", default=[], metavar="KEY=VALUE", help="an ACTConfig field")
    args = parser.parse_args()

    rows = []
    for size in args.sizes:
        h, w = (int(x) for x in size.split("x"))
        res = measure(h, w, args)
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
        a, v, p, t = res["act"], res["vib"], res["vib_u_at_plans"], res["vib_tokens"]
        lines.append(
            f"| {size} | **VIB / ACT** | {v['params_m'] / a['params_m']:.2f} | "
            f"**{v['samples_per_s'] / a['samples_per_s']:.2f}x** | "
            f"**{v['latency_ms'] / a['latency_ms']:.2f}x** | **{v['queue_ms'] / a['queue_ms']:.2f}x** "
            f"(u at plans only: **{p['queue_ms'] / a['queue_ms']:.2f}x**) |"
        )
        lines.append(
            f"| {size} | **VIB tokens / ACT** | {t['params_m'] / a['params_m']:.2f} | "
            f"**{t['samples_per_s'] / a['samples_per_s']:.2f}x** | "
            f"**{t['latency_ms'] / a['latency_ms']:.2f}x** | **{t['queue_ms'] / a['queue_ms']:.2f}x** |"
        )
    header = (
        f"Machine: {machine(args.device)}; torch {torch.__version__}; device {args.device}; "
        f"chunk_size {args.chunk_size}; "
        f"train batch {args.batch_size}; medians of {args.train_repeats} train steps, "
        f"{args.latency_repeats} select_action calls and {args.queue_repeats} chunks in queue mode, after "
        f"{args.warmup} warm-up calls; the policies take turns in every round.\n"
        f"Command: python benchmarks/bench_policy.py {' '.join(sys.argv[1:])}\n"
        "Ratios: samples/s VIB/ACT (above 1: VIB trains faster); times VIB/ACT (below 1: VIB acts faster).\n"
    )
    lines += ["", "VIB network pass at batch 1:", "", "| image | encoder ms | action transformer ms |"]
    lines += ["| --- | ---: | ---: |"]
    lines += [f"| {size} | {res['vib']['encoder_ms']:.1f} | {res['vib']['decoder_ms']:.1f} |" for size, res in rows]
    emit(header + "\n" + "\n".join(lines) + "\n", args.output)


if __name__ == "__main__":
    main()
