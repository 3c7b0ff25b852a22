"""How much of the token network's training input is noise, and what its decoder does without it.

    python benchmarks/latent_noise.py --policy seed_2000=<token-network checkpoint> --dataset_root data/arm_near \
        --heldout_root outputs/diag/heldout --output benchmarks/results/.../latent_noise.md

In training the decoder reads z = mu + sigma * eps; at evaluation it reads the posterior mean mu unless
`sample_latent_at_inference` is set. Per token type (the robot state, the image cells), on recorded frames
(every `--stride`-th) of the training recording and of a recording the network never saw:
  - the rate per token (KL against the marginal, summed over latent dims);
  - the signal-to-noise ratio of z: the variance of mu across frames (and cells) over the mean posterior
    variance sigma^2, averaged over latent dims. Below 1, a training input is mostly noise;
  - the decoded first action's L1 error against the recorded action (normalized units), decoding mu and
    decoding a posterior sample (the mean over `--draws` draws of the per-draw error);
  - the same with each frame's camera image swapped for another frame's (half the frames away, so another
    episode), the state kept: how much the decoded action depends on the camera at all;
  - the first action is close to the current state whatever the camera shows, so the whole chunk says more: the
    mean absolute change of the decoded chunk (posterior mean, normalized units, every step and action dim) when
    the camera is swapped, and for scale when the state is swapped instead.
"""

from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path

import torch
from lerobot.configs.policies import PreTrainedConfig
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot.policies.factory import make_pre_post_processors
from lerobot.utils.constants import ACTION
from report import cpu_name

from lerobot_vib.modeling_vib import VIBPolicy


def frames_batch(root: Path, repo_id: str, stride: int, keys: list[str]) -> dict[str, torch.Tensor]:
    dataset = LeRobotDataset(repo_id, root=root)
    frames = [dataset[i] for i in range(0, len(dataset), stride)]
    return {k: torch.stack([f[k] for f in frames]) for k in keys}


def snr(mean: torch.Tensor, logvar: torch.Tensor) -> float:
    """mean, logvar: (frames, tokens, D) -> mean over D of Var(mu) / E[sigma^2], pooled over frames and tokens."""
    mu = mean.flatten(0, 1)
    return float((mu.var(0) / logvar.flatten(0, 1).exp().mean(0)).mean())


@torch.no_grad()
def measure(policy: VIBPolicy, pre, batch: dict, draws: int) -> dict[str, float]:
    net = policy.network
    obs = pre(dict(batch))
    posterior = net.encode(obs)
    rates = net.token_rates(posterior)
    n1 = net.n_1d_tokens
    out = {
        "state rate": float(rates[:, :n1].mean()),
        "image rate": float(rates[:, n1:].mean()),
        "state SNR": snr(posterior.mean[:, :n1], posterior.logvar[:, :n1]),
        "image SNR": snr(posterior.mean[:, n1:], posterior.logvar[:, n1:]),
    }
    target = obs[ACTION]

    def l1(z: torch.Tensor) -> float:
        return float((net.decode(z)[:, 0] - target).abs().mean())

    out["L1, mean z"] = l1(posterior.mean)
    torch.manual_seed(0)
    out["L1, sampled z"] = sum(l1(posterior.sample()) for _ in range(draws)) / draws
    # Each frame's camera swapped for another episode's (half the frames away), the state kept: a network that
    # reads the camera gets worse; one that acts from the state alone does not.
    swapped = dict(obs)
    for key in policy.config.image_features:
        swapped[key] = obs[key].roll(len(target) // 2, dims=0)
    other = net.encode(swapped)
    torch.manual_seed(0)
    out["L1, sampled z, camera swapped"] = sum(l1(other.sample()) for _ in range(draws)) / draws
    own = net.decode(posterior.mean)
    out["chunk change, camera swapped"] = float((net.decode(other.mean) - own).abs().mean())
    state_swapped = dict(obs)
    state_swapped["observation.state"] = obs["observation.state"].roll(len(target) // 2, dims=0)
    out["chunk change, state swapped"] = float((net.decode(net.encode(state_swapped).mean) - own).abs().mean())
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--policy", action="append", required=True, help="LABEL=token-network checkpoint")
    parser.add_argument("--dataset_root", type=Path, required=True, help="the training recording")
    parser.add_argument("--heldout_root", type=Path, help="a recording of other episode seeds")
    parser.add_argument("--repo_id", default="local/vib_arm_grasp_block_scripted")
    parser.add_argument("--stride", type=int, default=10)
    parser.add_argument("--draws", type=int, default=4)
    parser.add_argument("--output", type=Path, required=True)
    args = parser.parse_args()
    torch.set_num_threads(1)
    columns = [
        "state rate",
        "image rate",
        "state SNR",
        "image SNR",
        "L1, mean z",
        "L1, sampled z",
        "L1, sampled z, camera swapped",
        "chunk change, camera swapped",
        "chunk change, state swapped",
    ]
    lines = [
        "# How much of the token network's training input is noise",
        "",
        f"Machine: {cpu_name()}. Command: `python benchmarks/{Path(__file__).name} " + shlex.join(sys.argv[1:]) + "`.",
        "",
        "SNR: the variance of the posterior mean across frames (and cells) over the mean posterior variance, "
        "averaged over latent dims. L1: the decoded first action against the recorded one, normalized units. "
        "Chunk change: the mean absolute change of the decoded chunk (posterior mean) when each frame's camera, "
        "or its state, is swapped for another episode's.",
        "",
        "| checkpoint | frames | " + " | ".join(columns) + " |",
        "| --- | --- |" + " --- |" * len(columns),
    ]
    roots = {"training recording": args.dataset_root}
    if args.heldout_root is not None:
        roots["held-out recording"] = args.heldout_root
    for spec in args.policy:
        label, path = spec.split("=", 1)
        config = PreTrainedConfig.from_pretrained(path)
        config.device = "cpu"
        if config.encoder != "tokens":
            raise SystemExit(f"{path} is not a token network (encoder={config.encoder!r}).")
        policy = VIBPolicy.from_pretrained(path, config=config).eval()
        pre, _ = make_pre_post_processors(policy.config, pretrained_path=path)
        inputs = [*policy.config.image_features, "observation.state", ACTION]
        for name, root in roots.items():
            batch = frames_batch(root, args.repo_id, args.stride, inputs)
            row = measure(policy, pre, batch, args.draws)
            n = len(batch[ACTION])
            lines.append(f"| {label} | {name}, {n} | " + " | ".join(f"{row[c]:.3f}" for c in columns) + " |")
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
