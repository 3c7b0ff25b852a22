"""The rate taken apart on the same frames: only the image changed, or only the state.

    python benchmarks/rate_decomposition.py --policy outputs/scores/vib_arm/calibrated --dataset_root data/arm_near \
        --image_mean outputs/scores/vib_arm/dataset_frames.npz --output benchmarks/results/.../rate_decomposition.md

The encoder sums a camera path and a state path, e = e_img + e_state, and the posterior head is affine in e
(scores.py). On recorded frames (every `--stride`-th frame of the recording), each change below is applied to
the observation alone, and the rate is split exactly:
  - the rate R(e); the image path R(e_img + mean e_state) and the state path R(mean e_img + e_state), each
    path with the other held at its training mean;
  - the KL's mean term and variance term, averaged over tokens;
  - the image path's pooled keypoints: how far they move from the frame's own.
Reported as the median over frames of changed / unchanged. `uncertainty_scores.py`'s report pairs rollouts
instead (the same seed and step), where the arm also moves differently.
"""

from __future__ import annotations

import argparse
import os
import shlex
import sys
from pathlib import Path

import numpy as np
import torch

os.environ.setdefault("MUJOCO_GL", "egl")

from lerobot.configs.policies import PreTrainedConfig
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot.policies.factory import make_pre_post_processors
from lerobot.utils.constants import OBS_STATE
from report import cpu_name

from lerobot_vib.modeling_vib import VIBPolicy
from lerobot_vib.scores import rate_terms


def image_change(name: str):
    def apply(img: torch.Tensor, g: torch.Generator) -> torch.Tensor:
        if name == "black":
            return torch.zeros_like(img)
        if name == "dim x0.45":
            return img * 0.45
        if name == "noise 0.1":
            return (img + 0.1 * torch.randn(img.shape, generator=g)).clamp(0, 1)
        if name == "grey":
            return torch.full_like(img, 0.5)
        raise ValueError(name)

    return apply


IMAGE_CHANGES = ("black", "dim x0.45", "grey", "noise 0.1")
STATE_CHANGES = ((3, 0.002), (3, 0.01), (3, 0.05), (0, 0.05))  # (joint, radians added)


@torch.no_grad()
def measure(policy: VIBPolicy, pre, frames: list[dict], image_mean: torch.Tensor) -> dict:
    net = policy.network
    bn = net.bottleneck

    def split(batch: dict) -> dict[str, np.ndarray]:
        parts = net.encoder.parts(pre(dict(batch)))
        post = net.posterior_of(parts.fused)
        mean_term, var_term = rate_terms(post, bn.marginal_mean, bn.marginal_logvar)
        state_mean = policy.state_embedding_mean
        return {
            "rate": bn.rate(post).numpy(),
            "image path": bn.rate(net.posterior_of(parts.image + state_mean)).numpy(),
            "state path": bn.rate(net.posterior_of(image_mean + parts.state)).numpy(),
            "mean term": mean_term.mean(-1).numpy(),
            "variance term": var_term.mean(-1).numpy(),
            "keypoints": parts.pooled.numpy(),
        }

    camera = next(iter(policy.config.image_features))
    batch = {k: torch.stack([f[k] for f in frames]) for k in (camera, OBS_STATE)}
    base = split(batch)
    g = torch.Generator().manual_seed(0)
    rows = {}
    for name in IMAGE_CHANGES:
        changed = split({**batch, camera: image_change(name)(batch[camera], g)})
        rows[f"image: {name}"] = ratios(base, changed)
    for joint, delta in STATE_CHANGES:
        state = batch[OBS_STATE].clone()
        state[:, joint] += delta
        rows[f"state: joint {joint} + {delta} rad"] = ratios(base, split({**batch, OBS_STATE: state}))
    return {
        "n_frames": len(frames),
        "base": {k: float(np.median(v)) for k, v in base.items() if k != "keypoints"},
        "rows": rows,
    }


def ratios(base: dict, changed: dict) -> dict[str, float]:
    out = {k: float(np.median(changed[k] / base[k])) for k in base if k != "keypoints"}
    out["keypoint shift"] = float(np.median(np.abs(changed["keypoints"] - base["keypoints"]).mean(1)))
    return out


def table(result: dict, label: str) -> list[str]:
    keys = ["rate", "image path", "state path", "mean term", "variance term"]
    lines = [
        f"### {label}: {result['n_frames']} recorded frames",
        "",
        "Unchanged frames (median): " + ", ".join(f"{k} {result['base'][k]:.1f}" for k in keys) + ".",
        "",
        "| change | " + " | ".join(keys) + " | mean pooled-feature shift |",
        "| --- |" + " --- |" * (len(keys) + 1),
    ]
    for name, row in result["rows"].items():
        lines.append(f"| {name} | " + " | ".join(f"{row[k]:.2f}x" for k in keys) + f" | {row['keypoint shift']:.3f} |")
    return [*lines, ""]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--policy", action="append", required=True, help="LABEL=calibrated checkpoint")
    parser.add_argument("--image_mean", action="append", required=True, help="dataset_frames.npz, one per policy")
    parser.add_argument("--dataset_root", type=Path, required=True)
    parser.add_argument("--repo_id", default="local/vib_arm_grasp_block_scripted")
    parser.add_argument("--stride", type=int, default=25)
    parser.add_argument("--output", type=Path, required=True)
    args = parser.parse_args()
    torch.set_num_threads(1)
    dataset = LeRobotDataset(args.repo_id, root=args.dataset_root)
    frames = [dataset[i] for i in range(0, len(dataset), args.stride)]
    lines = [
        "# The rate taken apart on the same frames",
        "",
        f"Machine: {cpu_name()}. Command: `python benchmarks/{Path(__file__).name} " + shlex.join(sys.argv[1:]) + "`.",
        "",
        "Each change is applied to the recorded observation alone; a cell is the median over frames of the "
        "changed value over the unchanged one. image path: the rate with the state path held at its training "
        "mean; state path: with the camera path held at its training mean; the mean and variance terms of the "
        "KL average over tokens (their sum is the rate).",
        "",
    ]
    for spec, npz in zip(args.policy, args.image_mean, strict=True):
        label, path = spec.split("=", 1)
        config = PreTrainedConfig.from_pretrained(path)
        config.device = "cpu"
        policy = VIBPolicy.from_pretrained(path, config=config).eval()
        pre, _ = make_pre_post_processors(policy.config, pretrained_path=path)
        image_mean = torch.as_tensor(np.load(npz)["image_mean"])
        lines += table(measure(policy, pre, frames, image_mean), label)
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
