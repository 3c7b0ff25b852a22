"""Where the token network's rate map points under the occluder, and what the map looks like.

For a token-network checkpoint (`--policy.encoder=tokens`) on the simulated arm:

1. **Pointing.** `--episodes` occlusion episodes (the benchmark's occluder: a board between the camera and the
   workspace, drawn per episode), the stop off. At every step the board is in view, the simulator's
   segmentation gives the board's pixels (`ArmGraspEnv.occluder_mask`) and `policy.last_step.rate_map` the
   cells' rates; the share of those frames whose hottest cell lies under the board, and the share whose
   coldest cell does, are set against the share a random cell would reach, beside the mean gap between the
   board's cells and the rest (`lerobot_vib.rate_map`), and the frame AUROC of the map's two scores against
   the clean episode of the same seed at the same step. A map whose hottest cells always sit where the board
   goes would point without seeing it, so the clean episode's map at the same step, read against the same
   board's cells, gives a second chance line. Both for the raw rates and, where the checkpoint is
   calibrated (`lerobot-vib-calibrate` stores every cell's training mean and std), for the cells' z-scores
   that the map score reads.
2. **Pictures.** One episode per condition (clean, the board in view, an unseen block, a black image) at the
   same seed and step: the camera image with the map over it, on one diverging colour scale (red above the
   cell's training mean, blue below), so the conditions compare; the scale is set by the first three, and a
   black image's cells beyond it are drawn at its ends.

    python benchmarks/rate_map_pointing.py \
        --policy_path=outputs/train/vib_tokens/checkpoints/last/pretrained_model --episodes 20 \
        --out outputs/rate_map --output benchmarks/results/rate_map_tokens/report.md
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
import torch

os.environ.setdefault("MUJOCO_GL", "egl")

from lerobot.configs.policies import PreTrainedConfig
from lerobot.envs.utils import preprocess_observation
from lerobot.policies.factory import make_pre_post_processors
from report import cpu_name

from lerobot_vib.metrics import auroc
from lerobot_vib.modeling_vib import VIBPolicy
from lerobot_vib.provenance import training_recording
from lerobot_vib.rate_map import ENDS, pointing
from lerobot_vib.scores import token_scores
from lerobot_vib.sim.arm_env import DEFAULT_WORKSPACE, EPISODE_LENGTH, ArmGraspEnv
from lerobot_vib.sim.perturbations import CONDITIONS, PerturbationConfig

PICTURE_STEP = 25
PICTURES = {  # the board is in view over steps 10-39, so at PICTURE_STEP in its picture
    "clean": CONDITIONS["normal"],
    "board in view": PerturbationConfig(occlusion=True, occlusion_start=10, occlusion_duration=30),
    "unseen block": CONDITIONS["unseen_block"],
    "black image": CONDITIONS["black"],
}


def load(path: Path, device: str):
    config = PreTrainedConfig.from_pretrained(path)
    config.device = device
    policy = VIBPolicy.from_pretrained(path, config=config)
    if policy.config.encoder != "tokens":
        raise SystemExit(f"{path} is a `{policy.config.encoder}` network; only the token network has a rate map.")
    pre, post = make_pre_post_processors(policy.config, pretrained_path=str(path))
    policy.eval()
    return policy, pre, post


def make_env(policy, perturbation: PerturbationConfig, recording: dict) -> ArmGraspEnv:
    cameras = [key.removeprefix("observation.images.") for key in policy.config.image_features]
    _, height, width = next(iter(policy.config.image_features.values())).shape
    return ArmGraspEnv(
        observation_height=height, observation_width=width, cameras=cameras, perturbation=perturbation,
        shadows=recording.get("shadows", True), workspace=recording.get("workspace", DEFAULT_WORKSPACE),
    )  # fmt: skip


def z_map(policy, rate_map: np.ndarray) -> np.ndarray | None:
    """Each cell's rate as a z-score against its training statistics; None on an uncalibrated checkpoint."""
    mean, std = policy.map_cell_mean.cpu().numpy(), policy.map_cell_std.cpu().numpy()
    if not (np.isfinite(mean).all() and np.isfinite(std).all()):
        return None
    return (rate_map - mean[: rate_map.size].reshape(rate_map.shape)) / np.maximum(
        std[: rate_map.size].reshape(rate_map.shape), 1e-6
    )


def map_scores(policy, rate_map: np.ndarray) -> dict[str, float]:
    """The policy's own `map_score` and `low_map_score` (scores.py, unnormalized) of one camera's map."""
    cells = torch.from_numpy(rate_map).reshape(1, -1)
    n = cells.shape[1]
    scores = token_scores(
        cells, 0, policy.map_cell_mean[:n].cpu(), policy.map_cell_std[:n].cpu(), policy.config.map_top_k
    )
    return {name: float(scores[name]) for name in ("map_score", "low_map_score")}


def episode(policy, pre, post, env: ArmGraspEnv, seed: int, record_at=None):
    """Roll one episode; returns the (step, rate map, mask) of every step the board is in view, the rate map
    of every step, the frame and map at `record_at`, and whether it succeeded."""
    obs, _ = env.reset(seed=seed)
    policy.reset()
    occluded, every, shown, success = [], [], None, False
    for t in range(EPISODE_LENGTH):
        in_view = env.scene.occluded(env.step_count)
        mask = env.occluder_mask() if in_view else None
        with torch.inference_mode():
            action = post(policy.select_action(pre(preprocess_observation(obs))))
        rate_map = policy.last_step.rate_map[0, 0].float().cpu().numpy()  # the first camera
        every.append(rate_map)
        if in_view:
            occluded.append((t, rate_map, mask))
        if t == record_at:
            shown = (obs["pixels"][env.cameras[0]], rate_map)
        obs, _, terminated, _, info = env.step(action[0].numpy())
        success = success or bool(info.get("is_success"))
        if terminated:
            break
    return occluded, every, shown, success


def draw(shown: dict[str, tuple[np.ndarray, np.ndarray]], path: Path, label: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    # A black image's cells sit hundreds of standard deviations out; scaled to them, the other maps vanish.
    scaled = [m for name, (_, m) in shown.items() if name != "black image"] or [m for _, m in shown.values()]
    centre = 0.0 if "z-score" in label else float(np.median(np.concatenate([m.ravel() for m in scaled])))
    reach = max(float(np.abs(m - centre).max()) for m in scaled) or 1.0
    low, high = centre - reach, centre + reach
    fig, axes = plt.subplots(1, len(shown), figsize=(3.2 * len(shown), 2.9))
    for ax, (name, (image, rate_map)) in zip(axes, shown.items(), strict=True):
        h, w = image.shape[:2]
        ax.imshow(image)
        over = ax.imshow(rate_map, cmap="RdBu_r", alpha=0.6, vmin=low, vmax=high, extent=(0, w, h, 0))
        ax.set(title=f"{name} (step {PICTURE_STEP})", xticks=[], yticks=[])
    fig.colorbar(over, ax=list(axes), fraction=0.02, label=label)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--policy_path", type=Path, required=True)
    p.add_argument("--episodes", type=int, default=20)
    p.add_argument("--seed", type=int, default=600000, help="first episode seed (the benchmark's test seeds)")
    p.add_argument("--device", default="cpu")
    p.add_argument("--out", type=Path, default=Path("outputs/rate_map"))
    p.add_argument("--output", type=Path, default=None, help="write the Markdown report (and the picture) here")
    args = p.parse_args()
    start = time.time()
    policy, pre, post = load(args.policy_path, args.device)
    recording = (training_recording(args.policy_path) or (None, {}))[1]
    args.out.mkdir(parents=True, exist_ok=True)

    env = make_env(policy, CONDITIONS["occlusion"], recording)
    clean_env = make_env(policy, CONDITIONS["normal"], recording)
    maps, z_maps, masks, successes = [], [], [], 0
    clean_same, clean_z, clean_masks = [], [], []  # the clean episode at the occluded frames' steps
    paired: dict[str, tuple[list[float], list[float]]] = {"map_score": ([], []), "low_map_score": ([], [])}
    for i in range(args.episodes):
        frames, _, _, success = episode(policy, pre, post, env, args.seed + i)
        _, clean_maps, _, _ = episode(policy, pre, post, clean_env, args.seed + i)
        successes += success
        for t, rate_map, mask in frames:
            maps.append(rate_map)
            masks.append(mask)
            if t < len(clean_maps):
                clean_same.append(clean_maps[t])
                clean_masks.append(mask)
                clean_z.append(z_map(policy, clean_maps[t]))
            z = z_map(policy, rate_map)
            if z is None:
                continue
            z_maps.append(z)
            if t < len(clean_maps):  # the clean episode of the same seed at the same step
                clean_scores, scores = map_scores(policy, clean_maps[t]), map_scores(policy, rate_map)
                for name, (neg, pos) in paired.items():
                    neg.append(clean_scores[name])
                    pos.append(scores[name])
    env.close()
    clean_env.close()
    separation = {name: auroc(neg, pos) for name, (neg, pos) in paired.items() if neg and pos}
    measured = {"raw cell rates": maps}
    if len(z_maps) == len(maps) and maps:
        measured["cell z-scores (the map score's)"] = z_maps
    found = {name: {end: pointing(values, masks, end=end) for end in ENDS} for name, values in measured.items()}
    clean_measured = {"raw cell rates": clean_same, "cell z-scores (the map score's)": clean_z}
    for name in found:
        found[name]["clean hottest"] = pointing(clean_measured[name], clean_masks, end="hottest")

    shown = {}
    for name, perturbation in PICTURES.items():
        env = make_env(policy, perturbation, recording)
        _, _, frame, _ = episode(policy, pre, post, env, args.seed, record_at=PICTURE_STEP)
        env.close()
        if frame is None:
            raise SystemExit(f"The {name} episode of seed {args.seed} ended before step {PICTURE_STEP}.")
        image, rate_map = frame
        zm = z_map(policy, rate_map)
        shown[name] = (image, rate_map if zm is None else zm)
    picture_dir = args.output.parent if args.output else args.out
    picture_dir.mkdir(parents=True, exist_ok=True)
    picture = picture_dir / "rate_maps.png"
    draw(shown, picture, "cell rate" if zm is None else "cell rate, z-score against training")

    result = {"pointing": found, "frame_auroc": separation, "episodes": args.episodes, "successes": successes}
    (args.out / "pointing.json").write_text(json.dumps(result, indent=2))
    rows = [
        f"| {name} | {r['hottest']['frames']} | {100 * r['hottest']['share']:.0f}% | "
        f"{100 * r['coldest']['share']:.0f}% | {100 * r['hottest']['chance']:.0f}% | "
        f"{100 * r['clean hottest']['share']:.0f}% | {r['hottest']['contrast']:+.3g} | "
        f"{r['clean hottest']['contrast']:+.3g} |"
        for name, r in found.items()
    ]
    report = "\n".join(
        [
            "# Where the token network's rate map points under the occluder",
            "",
            f"Machine: {cpu_name()}, {os.cpu_count()} CPUs, {platform.platform()}; torch {torch.__version__}.",
            f"Command: `python benchmarks/rate_map_pointing.py {' '.join(sys.argv[1:])}`",
            f"Checkpoint: `{args.policy_path}`. {args.episodes} occlusion episodes from seed {args.seed} (the "
            f"benchmark's occluder, drawn per episode; the stop off): {successes} solved. A frame points at the "
            "board when its hottest cell lies under it (the board covers at least half of the cell's image "
            "block, from MuJoCo's segmentation); chance is the share of cells under the board, what a map of "
            "random values would score. The clean columns read the clean episode of the same seed at the same "
            "steps against the same board's cells: where the map's hottest cells sit without a board.",
            "",
            "| map | occluded frames | hottest cell under the board | coldest cell under the board | chance | "
            "clean: hottest cell there | board's cells minus the rest | clean: those cells minus the rest |",
            "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
            *rows,
            "",
            *(
                [
                    "The map's two scores (top-1) on the occluded frames against the clean episode of the same "
                    "seed at the same step, frame AUROC (0.5 is chance): "
                    + ", ".join(f"`{name}` {value:.2f}" for name, value in separation.items())
                    + ".",
                    "",
                ]
                if separation
                else []
            ),
            f"![the map over the camera image, four conditions]({picture.name}): seed {args.seed}, step "
            f"{PICTURE_STEP}, one diverging colour scale set by the first three panels (red above the cell's "
            "training mean, blue below; a black image's cells beyond it are drawn at its ends).",
            "",
            f"This run: {(time.time() - start) / 60:.1f} min.",
            "",
        ]
    )
    print(report)
    if args.output:
        args.output.write_text(report)


if __name__ == "__main__":
    main()
