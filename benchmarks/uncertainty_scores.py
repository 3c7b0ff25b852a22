"""Which uncertainty score sees what on the simulated arm: every score of one checkpoint on the same rollouts.

    python benchmarks/uncertainty_scores.py --policy outputs/train/vib_arm/checkpoints/last/pretrained_model \
        --dataset_root data/arm_near --out outputs/scores/vib_arm --splits calibration validation test

1. calibrate: `lerobot-vib-calibrate`'s own computation on the recording (every score's mean and std over
   the training frames, the RND fitted), into <out>/calibrated; plus the camera path's training mean, which
   the decomposition needs.
2. rollouts, with the stop off, one file per split and condition (<out>/<split>/<condition>.npz, skipped when
   present, so a stopped run resumes). Every step records every score (`VIBPolicy.trace_all_scores`) and the
   rate taken apart (mean and variance terms per token; the rate with each path held at its training mean).
   Conditions, each on the split's seeds (clean and perturbed rollouts share seeds, so frames pair by seed
   and step):
     tuned on:  gaussian (noise std 0.05 or 0.1: every episode perturbed), color (jitter 0.2, every episode),
                camera_shake (0.005), unseen_block, occlusion (a board from a step in [10, 40) for 15-40
                steps), black (black images)
     held out:  dim (every image x 0.45: an under-exposed camera) and frozen (the camera's image stops
                changing from step 20 on while the arm moves), which no choice looked at
   Splits: calibration (clean rollouts that set the thresholds), validation (the choice of score and
   threshold), test (the reported numbers; nothing is chosen on them).
3. `--report`: AUROC of each score, clean frames against perturbed frames at the same seed and step
   (occlusion: occluded steps only); the stop each threshold would make (the first crossing; with the stop off
   a rollout is the stopped one's up to its first stop); success; the rate's decomposition.

Seeds: the project's plan (`lerobot_vib.seeds`): calibration 200000.., validation 400000.., test 600000.., so
no test seed calibrates or chooses anything. The committed report was made before the plan, with calibration
600000.. and test 500000..; `--calibration_seed=600000 --test_seed=500000` reruns it as it was.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
import torch

os.environ.setdefault("MUJOCO_GL", "egl")

from lerobot.configs.policies import PreTrainedConfig
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot.envs.utils import preprocess_observation
from lerobot.policies.factory import make_pre_post_processors
from report import cpu_name

from lerobot_vib import seeds
from lerobot_vib.calibration import conformal_gamma, mean_plus_2std_gamma
from lerobot_vib.metrics import auroc, first_crossing, stop_metrics, time_indexed_band
from lerobot_vib.modeling_vib import VIBPolicy
from lerobot_vib.scores import SCORES as POLICY_SCORES
from lerobot_vib.scores import TOKEN_SCORES, rate_terms
from lerobot_vib.scripts.calibrate import _write, calibrate, record_frames
from lerobot_vib.sim.arm_env import EPISODE_LENGTH, ArmGraspEnv
from lerobot_vib.sim.env_config import ArmGraspEnvConfig
from lerobot_vib.sim.perturbations import PerturbationConfig, draw_scene_episode

TUNED = ("gaussian", "color", "camera_shake", "unseen_block", "occlusion", "black")
HELD_OUT = ("dim", "frozen")
CONDITIONS: dict[str, dict] = {
    "clean": {},
    "gaussian": {"noise_std": [0.05, 0.1]},
    "color": {"color_jitter": 0.2, "color_jitter_p": 1.0},
    "camera_shake": {"camera_shake": 0.005},
    "unseen_block": {"unseen_block": True},
    "occlusion": {"occlusion": True},
    "black": {"black_images": True},
    "dim": {},
    "frozen": {},
}
DIM_FACTOR, FROZEN_FROM = 0.45, 20
DEFAULT_SPLIT_SEEDS = {"calibration": seeds.CALIBRATION, "validation": seeds.VALIDATION, "test": seeds.TEST}
LENGTHS = "__lengths"  # beside a per-episode key in a cell file: each episode's number of steps
WIDTH = "__width"  # and the shape of one step's value (empty for a number)
ALPHA = 0.1
CATCH_WITHIN = 5


# The pooled network's scores: this script also takes that network's rate apart (its two input paths), which
# the token network does not have (its scores come from lerobot-vib-benchmark).
SCORES = tuple(s for s in POLICY_SCORES if s not in TOKEN_SCORES)


def load_policy(path: Path, overrides: list[str] | None = None) -> tuple[VIBPolicy, object]:
    config = PreTrainedConfig.from_pretrained(path, cli_overrides=overrides or [])
    config.device = "cpu"
    if getattr(config, "encoder", "pooled") != "pooled":
        raise SystemExit(
            f"{path} is a {config.encoder!r} network: this script reads the pooled network's two input paths; "
            "run lerobot-vib-benchmark --vib_tokens_checkpoint=... for a token network's scores."
        )
    policy = VIBPolicy.from_pretrained(path, config=config)
    preprocessor, _ = make_pre_post_processors(policy.config, pretrained_path=str(path))
    return policy.eval(), preprocessor


def calibrated(args) -> Path:
    """<out>/calibrated, made once: the checkpoint with every score's statistics and the fitted RND."""
    out = args.out / "calibrated"
    if (out / "model.safetensors").is_file() and (args.out / "dataset_frames.npz").is_file():
        return out
    policy, preprocessor = load_policy(args.policy, [f"--rnd_input={args.rnd_input}"])
    dataset = LeRobotDataset(args.repo_id, root=args.dataset_root)
    calibration = calibrate(
        policy, preprocessor, args.repo_id, root=args.dataset_root, batch_size=64, rnd_steps=args.rnd_steps
    )
    _write(policy, preprocessor, calibration, args.policy, out)
    # The same frames again for what the decomposition needs: the camera path's training mean, and the
    # training frames' rate terms.
    loader = torch.utils.data.DataLoader(dataset, batch_size=64, shuffle=False)
    records = record_frames(policy, preprocessor, loader)
    values = records.scores(policy)
    np.savez(
        args.out / "dataset_frames.npz",
        image_mean=records.image.mean(0).numpy(),
        **{name: v.numpy() for name, v in values.items()},
    )
    return out


def perturb_pixels(condition: str, pixels: dict, step: int, frozen: dict) -> dict:
    if condition == "dim":
        return {k: (v.astype(np.float32) * DIM_FACTOR).astype(np.uint8) for k, v in pixels.items()}
    if condition == "frozen":
        if step == FROZEN_FROM:
            frozen.update({k: v.copy() for k, v in pixels.items()})
        return dict(frozen) if step >= FROZEN_FROM else pixels
    return pixels


@torch.no_grad()
def rollout(policy: VIBPolicy, processors: tuple, env: ArmGraspEnv, seed: int, condition: str, image_mean) -> dict:
    """One episode with the stop off; every score and the rate's parts at every step."""
    preprocessor, postprocessor = processors
    obs, _ = env.reset(seed=seed)
    policy.reset()
    network = policy.network
    rows: dict[str, list] = {k: [] for k in (*SCORES, "mean_term", "var_term", "rate_state_path")}
    success, frozen = False, {}
    for t in range(EPISODE_LENGTH):
        obs = {**obs, "pixels": perturb_pixels(condition, obs["pixels"], t, frozen)}
        batch = preprocessor(preprocess_observation(obs))
        action = policy.select_action(batch)
        scores = policy.last_step.scores
        for name in SCORES:
            rows[name].append(float(scores[name][0]))
        parts = network.encoder.parts(batch)
        posterior = network.posterior_of(parts.fused)
        mean_term, var_term = rate_terms(
            posterior, network.bottleneck.marginal_mean, network.bottleneck.marginal_logvar
        )
        rows["mean_term"].append(mean_term[0].numpy())
        rows["var_term"].append(var_term[0].numpy())
        held = image_mean.to(parts.state) + parts.state
        rows["rate_state_path"].append(float(network.bottleneck.rate(network.posterior_of(held))[0]))
        obs, _, terminated, _, info = env.step(postprocessor(action)[0].numpy())
        success = success or bool(info.get("is_success", False))
        if terminated:
            break
    return {k: np.asarray(v, dtype=np.float64) for k, v in rows.items()} | {"success": success}


def run_split(args, path: Path, split: str, conditions: list[str], n_episodes: dict[str, int]) -> None:
    policy, _ = load_policy(path)
    policy.trace_all_scores = True
    processors = make_pre_post_processors(policy.config, pretrained_path=str(path))
    image_mean = torch.as_tensor(np.load(args.out / "dataset_frames.npz")["image_mean"])
    env_kwargs = ArmGraspEnvConfig(dataset_root=str(args.dataset_root)).gym_kwargs
    env_kwargs = {k: v for k, v in env_kwargs.items() if k not in ("render_mode", "perturbation", "max_episode_steps")}
    for condition in conditions:
        target = args.out / split / f"{condition}.npz"
        if target.is_file():
            continue
        env = ArmGraspEnv(**env_kwargs, perturbation=PerturbationConfig(**CONDITIONS[condition]))
        episode_seeds = seeds.seed_range(split, n_episodes[condition], args.split_seeds[split])
        start = time.time()
        episodes = [rollout(policy, processors, env, s, condition, image_mean) for s in episode_seeds]
        env.close()
        target.parent.mkdir(parents=True, exist_ok=True)
        flat = {"seeds": np.asarray(episode_seeds), "success": np.asarray([e["success"] for e in episodes])}
        for key in (*SCORES, "mean_term", "var_term", "rate_state_path"):
            flat.update(_ragged_to_arrays(key, [e[key] for e in episodes]))
        flat["wall_s"] = np.asarray(time.time() - start)
        tmp = target.with_suffix(".tmp.npz")
        np.savez(tmp, **flat)
        tmp.replace(target)  # whole files only: a stopped run redoes the condition it was in
        print(f"{split}/{condition}: {len(episode_seeds)} episodes, {sum(e['success'] for e in episodes)} successes, "
              f"{time.time() - start:.0f} s", flush=True)  # fmt: skip


# ------------------------------------------------------------------------------------------------- report


# Scores derived from the recorded ones (computed here, not by the policy), each a function of a trace and
# the training frames' means: two-sided forms, which also flag a score far *below* its training range.
def _two_sided(name: str):
    def derive(cell: dict, means: dict) -> list[np.ndarray]:
        m = means[name]
        return [
            np.maximum(np.asarray(t, dtype=np.float64) / m, m / np.asarray(t, dtype=np.float64)) for t in cell[name]
        ]

    return derive


DERIVED = {"rate_two_sided": _two_sided("rate"), "image_rate_two_sided": _two_sided("image_rate")}
ALL_SCORES = (*SCORES, *DERIVED)


def load_dataset_frames(out: Path) -> dict:
    dataset = dict(np.load(out / "dataset_frames.npz"))
    dataset.setdefault("low_image_rate", 1.0 / dataset["image_rate"])
    return dataset


def dataset_means(dataset: dict) -> dict[str, float]:
    return {name: float(np.mean(dataset[name])) for name in SCORES}


def derived_dataset(dataset: dict) -> dict:
    means = dataset_means(dataset)
    out = dict(dataset)
    for name, derive in DERIVED.items():
        out[name] = np.concatenate(derive({k: [dataset[k]] for k in SCORES}, means))
    return out


def _ragged_to_arrays(key: str, per_episode: list) -> dict[str, np.ndarray]:
    """Episodes of different lengths as plain arrays (values end to end, and each episode's length), so that
    reading them back never needs pickle: a pickled array in a file can run code when it is loaded."""
    values = [np.asarray(v, dtype=np.float64) for v in per_episode]
    width = values[0].shape[1:] if values else ()  # a per-step vector (the rate's terms per token) keeps its size
    return {
        key: np.concatenate([v.reshape(-1) for v in values]) if values else np.zeros(0),
        f"{key}{LENGTHS}": np.asarray([len(v) for v in values], dtype=np.int64),
        f"{key}{WIDTH}": np.asarray(width, dtype=np.int64),
    }


def _read_cell(path: Path) -> dict:
    try:
        data = np.load(path, allow_pickle=False)
        raw = {k: data[k] for k in data.files}
    except ValueError as e:  # an object array: written by an earlier version of this script
        raise SystemExit(
            f"{path} stores arrays that only pickle can read, which this script no longer loads (a crafted file "
            f"could run code). Delete it and rerun: the condition is evaluated again. ({e})"
        ) from None
    cell = {}
    for key, value in raw.items():
        if key.endswith((LENGTHS, WIDTH)):
            continue
        if f"{key}{LENGTHS}" in raw:
            lengths = raw[f"{key}{LENGTHS}"]
            # files written without the width hold one number per step, or stored a vector's numbers flat
            width = tuple(int(w) for w in raw.get(f"{key}{WIDTH}", np.zeros(0, dtype=np.int64)))
            size = int(np.prod(width)) if width else 1
            pieces = np.split(value, np.cumsum(lengths * size)[:-1]) if len(lengths) else []
            cell[key] = [piece.reshape(-1, *width) for piece in pieces]
        else:
            cell[key] = value
    return cell


def load_split(out: Path, split: str, dataset: dict | None = None) -> dict[str, dict]:
    cells = {}
    for f in sorted((out / split).glob("*.npz")):
        if f.name.endswith(".tmp.npz"):
            continue
        cell = cells[f.stem] = _read_cell(f)
        if "low_image_rate" not in cell:  # recorded before the score had a name: the same value
            cell["low_image_rate"] = [1.0 / np.asarray(t, dtype=np.float64) for t in cell["image_rate"]]
        if dataset is not None:
            means = dataset_means(dataset)
            for name, derive in DERIVED.items():
                cells[f.stem][name] = derive(cells[f.stem], means)
    return cells


def occluded_steps(seed: int) -> range:
    return draw_scene_episode(PerturbationConfig(occlusion=True), int(seed)).occluded_steps


def paired(clean: dict, cell: dict, key: str, condition: str) -> tuple[np.ndarray, np.ndarray]:
    """Clean and perturbed values of `key` at the same seed and step, stacked over episodes (occlusion: the
    occluded steps only; frozen: from the freeze on). Per-step values may be scalars or vectors."""
    index = {int(s): i for i, s in enumerate(clean["seeds"])}
    neg, pos = [], []
    for j, seed in enumerate(cell["seeds"]):
        i = index.get(int(seed))
        if i is None:
            continue
        a = np.asarray(np.stack(clean[key][i]), dtype=np.float64)
        b = np.asarray(np.stack(cell[key][j]), dtype=np.float64)
        n = min(len(a), len(b))
        steps = list(range(n))
        if condition == "occlusion":
            steps = [t for t in occluded_steps(seed) if t < n]
        elif condition == "frozen":
            steps = list(range(FROZEN_FROM, n))
        if steps:
            neg.append(a[steps])
            pos.append(b[steps])
    if not neg:
        return np.zeros(0), np.zeros(0)
    return np.concatenate(neg), np.concatenate(pos)


def thresholds(score: str, calib: dict, dataset: dict) -> dict[str, float | np.ndarray]:
    """Each threshold on a raw score: mean + 2 std of the training frames, split conformal on the clean
    calibration rollouts' per-episode max, and the time-indexed band (shape and level from halves of them)."""
    traces = [np.asarray(t, dtype=np.float64) for t in calib[score]]
    mean = float(np.mean(dataset[score]))
    out: dict[str, float | np.ndarray] = {
        "mean_plus_2std": mean * mean_plus_2std_gamma(mean, float(np.std(dataset[score]))),
    }
    half = len(traces) // 2
    try:
        out["conformal"] = conformal_gamma(np.array([t.max() for t in traces]), ALPHA)
        out["time_band"] = time_indexed_band(traces[:half], traces[half:], ALPHA)
    except ValueError:
        pass  # too few calibration rollouts for alpha
    return out


def stop_table(score: str, gammas: dict, clean: dict, occl: dict) -> dict[str, dict]:
    rows = {}
    for name, gamma in gammas.items():
        clean_stops = stop_metrics([np.asarray(t, dtype=np.float64) for t in clean[score]], gamma)
        onsets = [occluded_steps(s).start for s in occl["seeds"]]
        traces = [np.asarray(t, dtype=np.float64) for t in occl[score]]
        caught = n = early = 0
        delays = []
        for trace, onset in zip(traces, onsets, strict=True):
            if onset >= len(trace):
                continue  # ended (success) before the occluder came
            n += 1
            t = first_crossing(trace, gamma)
            if t is not None and t < onset:
                early += 1
            elif t is not None:
                delays.append(t - onset)
                caught += t - onset <= CATCH_WITHIN
        rows[name] = {
            "clean_false_stops": clean_stops.stopped / max(clean_stops.n_episodes, 1),
            "occlusion_caught_5": caught / max(n, 1),
            "occlusion_stopped_before": early / max(n, 1),
            "occlusion_mean_delay": float(np.mean(delays)) if delays else None,
            "n_clean": clean_stops.n_episodes,
            "n_occlusion": n,
            "gamma": float(np.max(gamma)) if np.ndim(gamma) else float(gamma),
        }
    return rows


def score_results(out: Path, split: str, calib: dict, dataset: dict) -> dict:
    cells = load_split(out, split, dataset)
    dataset = derived_dataset(dataset)
    clean = cells.get("clean")
    if clean is None:
        return {}
    res: dict = {"success": {}, "auroc": {}, "stops": {}}
    for condition, cell in cells.items():
        k = int(np.sum(cell["success"]))
        res["success"][condition] = [k, len(cell["success"])]
    for score in ALL_SCORES:
        res["auroc"][score] = {}
        for condition, cell in cells.items():
            if condition == "clean":
                continue
            neg, pos = paired(clean, cell, score, condition)
            if len(neg) and len(pos):
                res["auroc"][score][condition] = auroc(neg, pos)
        if "occlusion" in cells and calib:
            res["stops"][score] = stop_table(score, thresholds(score, calib, dataset), clean, cells["occlusion"])
        r_bar = float(np.mean(dataset[score]))
        res.setdefault("max_u_clean", {})[score] = max(float(np.max(t)) for t in clean[score]) / r_bar
    return res


def decomposition(out: Path, split: str, dataset: dict) -> dict:
    """The rate taken apart on paired frames: which path moves it, mean against variance term, which tokens."""
    cells = load_split(out, split)
    clean = cells.get("clean")
    if clean is None:
        return {}

    res = {}
    for condition, cell in cells.items():
        if condition == "clean":
            continue
        row = {}
        for key in ("rate", "image_rate", "rate_state_path"):
            neg, pos = paired(clean, cell, key, condition)
            row[key] = [float(np.median(neg)), float(np.median(pos))]
        for key in ("mean_term", "var_term"):
            neg, pos = paired(clean, cell, key, condition)
            row[key] = [float(np.median(neg.mean(1))), float(np.median(pos.mean(1)))]
            row[key + "_tokens"] = (np.median(pos, 0) - np.median(neg, 0)).tolist()
        res[condition] = row
    # Clean frames: how much of the rate's spread each path carries.
    rate = np.concatenate([np.asarray(t, dtype=np.float64) for t in clean["rate"]])
    img = np.concatenate([np.asarray(t, dtype=np.float64) for t in clean["image_rate"]])
    st = np.concatenate([np.asarray(t, dtype=np.float64) for t in clean["rate_state_path"]])
    res["clean_spread"] = {
        "std_rate": float(rate.std()),
        "std_image_path": float(img.std()),
        "std_state_path": float(st.std()),
        "corr_rate_image_path": float(np.corrcoef(rate, img)[0, 1]),
        "corr_rate_state_path": float(np.corrcoef(rate, st)[0, 1]),
    }
    return res


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--policy", type=Path, required=True, help="the trained checkpoint (pretrained_model)")
    parser.add_argument("--dataset_root", type=Path, required=True)
    parser.add_argument("--repo_id", default="local/vib_arm_grasp_block_scripted")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--splits", nargs="*", default=[], choices=list(DEFAULT_SPLIT_SEEDS))
    for split, first in DEFAULT_SPLIT_SEEDS.items():
        parser.add_argument(f"--{split}_seed", type=int, default=first, help=f"first {split} episode seed")
    parser.add_argument("--conditions", nargs="*", default=None, help="default: all (calibration: clean only)")
    parser.add_argument("--episodes", type=int, default=25, help="episodes per perturbed condition")
    parser.add_argument("--episodes_clean", type=int, default=50, help="clean episodes (test, calibration)")
    parser.add_argument("--episodes_validation", type=int, default=15)
    parser.add_argument("--rnd_input", default="fused", help="the embedding the RND score reads (VIBConfig)")
    parser.add_argument("--rnd_steps", type=int, default=3000, help="training steps of the RND predictor")
    parser.add_argument("--results", type=Path, default=None, help="write results.json of every split here")
    args = parser.parse_args()
    args.split_seeds = {split: getattr(args, f"{split}_seed") for split in DEFAULT_SPLIT_SEEDS}
    torch.set_num_threads(1)
    path = calibrated(args)
    for split in args.splits:
        conditions = ["clean"] if split == "calibration" else args.conditions or list(CONDITIONS)
        if split == "validation":
            conditions = [c for c in conditions if c not in HELD_OUT]  # never looked at while choosing
        n = {c: args.episodes_clean if c == "clean" else args.episodes for c in conditions}
        if split == "validation":
            n = dict.fromkeys(conditions, args.episodes_validation)
        run_split(args, path, split, conditions, n)
    if args.results:
        dataset = load_dataset_frames(args.out)
        calib = load_split(args.out, "calibration", dataset).get("clean", {})
        results = {
            "machine": f"{cpu_name()}, {platform.system()}, torch {torch.__version__}, Python {sys.version.split()[0]}",
            "policy": str(args.policy),
            "split_seeds": args.split_seeds,
            "calibration": json.loads((path / "config.json").read_text())["calibration"],
            "splits": {s: score_results(args.out, s, calib, dataset) for s in ("validation", "test")},
            "calibration_success": [int(np.sum(calib["success"])), len(calib["success"])] if calib else None,
            "decomposition": {s: decomposition(args.out, s, dataset) for s in ("test",)},
        }
        args.results.parent.mkdir(parents=True, exist_ok=True)
        args.results.write_text(json.dumps(results, indent=1, default=_json_default))
        print(f"wrote {args.results}")


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, float) and math.isnan(o):
        return None
    raise TypeError(type(o))


if __name__ == "__main__":
    main()
