"""Which reduction of the rate map stops the occluder: the map's cell z-scores reduced by the mean of their k
largest (high) or k smallest (low), for a calibrated token-network checkpoint.

The policy's map scores reduce the cells' z-scores (each cell's rate against its training statistics) by the
mean of the `--policy.map_top_k` largest, `map_score`, or of the negated z-scores, `low_map_score`; k = 1, the
extreme cell, is the default. On a trunk cut after layer2 a board in front of the camera lowers its cells'
rates and `low_map_score` stops it; on a trunk cut after layer3 each of the 48 cells sees more of the image,
and no extreme cell stops the board without stopping clean rollouts too. A board covers several cells at
once, where a clean peak may be one cell: a mean over k cells may tell them apart.

The checkpoint is rolled out with the stop off on the benchmark's seed plan (`lerobot_vib.seeds`): clean and
occluded validation episodes (400000..) choose, clean and occluded test episodes (600000..) report. Every
step's z-map is saved per episode, so an interrupted run resumes and a new reduction needs no new rollout.
Each (reduction, threshold) pair is judged by the rule that chose the policy's default score
(`benchmark_report.choose_score_on_validation`: set on the first half of the clean validation rollouts,
judged on the other half and the occluded validation rollouts; the most occlusions stopped within 5 steps
among pairs stopping at most 10% of those clean rollouts), and the chosen pair's stop on the test episodes
is reported beside every pair's, which chose nothing.

    python benchmarks/map_reductions.py \
        --policy_path=outputs/tokens_l3_s1000/calibrated/vib_tokens_narrow_act_trunk_l3/seed_1000 --sample \
        --out outputs/map_reductions/act_trunk_l3_s1000 \
        --output benchmarks/results/map_reductions_cpu_2core/act_trunk_l3_s1000.md
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import numpy as np
import torch

os.environ.setdefault("MUJOCO_GL", "egl")

from rate_map_pointing import episode, load, make_env, z_map
from report import cpu_name

from lerobot_vib.failure import windowed
from lerobot_vib.provenance import training_recording
from lerobot_vib.scripts.benchmark_report import (
    STOP_THRESHOLDS,
    _episodes,
    choose_score_on_validation,
    score_stops,
)
from lerobot_vib.seeds import seed_range
from lerobot_vib.sim.perturbations import CONDITIONS

KS = (1, 2, 4, 8, 16, 0)  # 0: every cell (the mean z-score)
WINDOWS = (1, 3, 5)  # steps; an occlusion counts as stopped in time within 5 steps of its entry
EPISODES = {  # (condition, split): episodes, as the benchmark runs them
    ("normal", "validation"): 40,
    ("occlusion", "validation"): 20,
    ("normal", "test"): 50,
    ("occlusion", "test"): 20,
}


def reductions(z: np.ndarray) -> dict[str, np.ndarray]:
    """Every candidate score per step from a (T, cells) z-map: the mean of the k largest z-scores ("high") and
    of the k largest negated ones ("low"), as `lerobot_vib.scores.map_score` reduces them, each also as its mean
    over the last w steps (`lerobot_vib.failure.windowed`, as the stop's `calibration.window` smooths u): a
    board stays in view for tens of steps, a clean peak may last one."""
    out = {}
    ordered = np.sort(z, axis=1)
    n = z.shape[1]
    for k in KS:
        k_ = n if k == 0 or k > n else k
        name = "all" if k == 0 else f"k={k}"
        for score, per_step in (("map_score", ordered[:, n - k_ :]), ("low_map_score", -ordered[:, :k_])):
            for w in WINDOWS:
                out[f"{score} {name}" + (f", w={w}" if w > 1 else "")] = windowed(per_step.mean(axis=1), w)
    return out


def roll(policy, pre, post, condition: str, seeds: list[int], recording: dict, out: Path, sample: bool) -> dict:
    """The z-maps (T, cells) and success of each seed's episode, read from `out` where already saved."""
    env = make_env(policy, CONDITIONS[condition], recording)
    episodes = {}
    for seed in seeds:
        path = out / condition / f"{seed}.npz"
        if not path.exists():
            if sample:
                torch.manual_seed(seed)
            _, maps, _, success = episode(policy, pre, post, env, seed)
            z = np.stack([z_map(policy, m).ravel() for m in maps])
            path.parent.mkdir(parents=True, exist_ok=True)
            np.savez(path.with_suffix(".tmp.npz"), z=z, success=success)
            path.with_suffix(".tmp.npz").replace(path)
        saved = np.load(path)
        episodes[seed] = (saved["z"], bool(saved["success"]))
    env.close()
    return episodes


def cell(episodes: dict) -> dict:
    seeds = sorted(episodes)
    traces: dict[str, list] = {}
    for seed in seeds:
        for name, trace in reductions(episodes[seed][0]).items():
            traces.setdefault(name, []).append(trace.tolist())
    return {"seeds": seeds, "success": [episodes[s][1] for s in seeds], "scores": traces}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--policy_path", type=Path, required=True, help="a calibrated token-network checkpoint")
    p.add_argument("--sample", action="store_true", help="decode a posterior sample (a '+sample' run time)")
    p.add_argument("--alpha", type=float, default=0.1)
    p.add_argument("--out", type=Path, required=True, help="the saved z-maps (resumable)")
    p.add_argument("--output", type=Path, required=True, help="the Markdown report (its JSON beside it)")
    args = p.parse_args()
    start = time.time()
    policy, pre, post = load(args.policy_path, "cpu")
    if not np.isfinite(policy.map_cell_mean.cpu().numpy()).all():
        raise SystemExit(f"{args.policy_path} has no per-cell statistics: run lerobot-vib-calibrate on it first.")
    policy.config.sample_latent_at_inference = args.sample
    recording = (training_recording(args.policy_path) or (None, {}))[1]
    cells = {
        key: cell(roll(policy, pre, post, key[0], seed_range(key[1], n), recording, args.out / key[1], args.sample))
        for key, n in EPISODES.items()
    }
    validation, occluded = cells[("normal", "validation")], cells[("occlusion", "validation")]
    choice = choose_score_on_validation(validation, occluded, args.alpha)
    test = score_stops({"normal": cells[("normal", "test")], "occlusion": cells[("occlusion", "test")]},
                       validation, args.alpha)  # fmt: skip
    half = len(validation["seeds"]) // 2
    judged = score_stops(  # the validation rule's own split (choose_score_on_validation), every pair shown
        {"normal": _episodes(validation, slice(half, None)), "occlusion": occluded},
        _episodes(validation, slice(None, half)),
        args.alpha,
    )

    def frac(row: dict, key: str, n: str) -> str:
        return f"{row[key]}/{row[n]}"

    lines = [
        f"# Map reductions: {args.policy_path}",
        "",
        f"`python benchmarks/map_reductions.py --policy_path={args.policy_path}{' --sample' if args.sample else ''}` "
        f"({(time.time() - start) / 60:.1f} min on {cpu_name()}, {os.cpu_count()} CPUs, Python "
        f"{platform.python_version()}; the rollouts saved before this run are read back, not timed).",
        "",
        f"Clean success: validation {sum(validation['success'])}/{len(validation['success'])}, test "
        f"{sum(cells[('normal', 'test')]['success'])}/{len(cells[('normal', 'test')]['success'])}. "
        f"Thresholds at alpha = {args.alpha}. Validation: set on {half} clean rollouts, judged on "
        f"{len(validation['seeds']) - half} clean and {len(occluded['seeds'])} occluded; test: set on all "
        f"{len(validation['seeds'])} clean validation rollouts, judged on the test episodes. In time: stopped at "
        "most 5 steps after the board entered.",
        "",
        "| reduction | threshold | validation: clean stopped | occlusions in time | test: clean stopped | "
        "occlusions in time |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for name, by_threshold in test.items():
        for threshold in STOP_THRESHOLDS:
            row, val = by_threshold.get(threshold), judged.get(name, {}).get(threshold)
            if row is None or val is None:
                continue
            mark = "**" if choice and (choice["score"], choice["threshold"]) == (name, threshold) else ""
            lines.append(
                f"| {mark}{name}{mark} | {threshold} | {frac(val, 'false_stops', 'clean_episodes')} | "
                f"{frac(val, 'in_time', 'occlusion_episodes')} | {frac(row, 'false_stops', 'clean_episodes')} | "
                f"{frac(row, 'in_time', 'occlusion_episodes')} |"
            )
    if choice and choice["score"]:
        row = test[choice["score"]][choice["threshold"]]
        caught = row["in_time"] / max(row["occlusion_episodes"], 1)
        false = row["false_stops"] / max(row["clean_episodes"], 1)
        verdict = "met" if caught >= 0.9 and false <= 0.05 else "not met"
        lines += [
            "",
            f"Chosen on validation (bold): `{choice['score']}` with its {choice['threshold']}; on test "
            f"{frac(row, 'in_time', 'occlusion_episodes')} occlusions in time at "
            f"{frac(row, 'false_stops', 'clean_episodes')} clean stops. Target (at least 90% in time, at most 5% "
            f"clean stopped): {verdict}.",
        ]
    else:
        lines += ["", "No pair stops at most 10% of the judged clean validation rollouts."]
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text("\n".join(lines) + "\n")
    args.output.with_suffix(".json").write_text(
        json.dumps({"choice": choice, "validation": judged, "test": test}, indent=1, default=str)
    )
    print("\n".join(lines))


if __name__ == "__main__":
    main()
