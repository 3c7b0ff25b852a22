"""What ends a stop under the occluder: the scene, or the clock? A time-indexed band read two ways.

A time band (`calibration.gamma_band`) is one threshold per episode step. While the arm holds, u stays where the
stop found it; read at the episode's step (`--policy.safety.band_index=episode_step`) the band keeps moving, and
where it rises above that u it releases the arm although nothing in the scene changed. Read at the env's
progress (`progress`, the default: steps run, stopped ones not counted) it stands still during a stop. This
rolls out the same occlusion episodes with the stop on under both readings (`lerobot-vib-eval`, LeRobot's eval
loop) and reads, for every stop that began while the board was in view, what ended it:

    scene cleared    it ended at or after the board left
    clock            it ended while the board was still in view
    never            it held to the end of the episode (or halted)

    python benchmarks/band_during_stop.py --policy <checkpoint calibrated with a band from rollouts> \
        --dataset_root data/arm_near --episodes 20 --seed 700000 --output_dir outputs/band_during_stop

Resumable: a reading whose `uncertainty_info.json` is there is not rolled out again.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import subprocess
import sys
from pathlib import Path

from report import cpu_name, emit

from lerobot_vib.sim.perturbations import PerturbationConfig, draw_scene_episode

READINGS = ("episode_step", "progress")


def stops(stopped: list[bool]) -> list[tuple[int, int | None]]:
    """(first stopped step, first step running again or None) of every stop in an episode."""
    out, start = [], None
    for t, s in enumerate(stopped):
        if s and start is None:
            start = t
        elif not s and start is not None:
            out.append((start, t))
            start = None
    if start is not None:
        out.append((start, None))
    return out


def classify(stop: tuple[int, int | None], occluded: range) -> str | None:
    """What ended a stop that began while the board was in view; None for a stop that began elsewhere."""
    start, end = stop
    if start not in occluded:
        return None
    if end is None:
        return "never"
    return "scene cleared" if end >= occluded.stop else "clock"


def read(run_dir: Path) -> list[dict]:
    info = json.loads((run_dir / "uncertainty_info.json").read_text())
    steps: dict[int, list[bool]] = {}
    with (run_dir / "uncertainty_trace.csv").open() as f:
        for row in csv.DictReader(f):
            steps.setdefault(int(row["episode"]), []).append(row["stopped"] in ("1", "True"))
    episodes = []
    for ep in info["per_episode"]:
        occluded = draw_scene_episode(PerturbationConfig(occlusion=True), int(ep["seed"])).occluded_steps
        kinds = [classify(s, occluded) for s in stops(steps[ep["episode_ix"]])]
        episodes.append(
            {"seed": ep["seed"], "success": ep["success"], "occluded": [occluded.start, occluded.stop],
             "stops": [k for k in kinds if k is not None], "other_stops": sum(k is None for k in kinds)}
        )  # fmt: skip
    return episodes


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--policy", type=Path, required=True)
    parser.add_argument("--dataset_root", type=Path, required=True)
    parser.add_argument("--episodes", type=int, default=20)
    parser.add_argument("--seed", type=int, default=700000)
    parser.add_argument("--output_dir", type=Path, default=Path("outputs/band_during_stop"))
    parser.add_argument("--output", type=Path, default=None, help="also write the report here")
    args = parser.parse_args()
    calibration = json.loads((args.policy / "config.json").read_text())["calibration"]
    if not calibration.get("gamma_band"):
        raise SystemExit(f"{args.policy} has no time band: calibrate it with `lerobot-vib-calibrate --rollouts=...`.")
    results = {}
    for reading in READINGS:
        out = args.output_dir / reading
        if not (out / "uncertainty_info.json").is_file():
            cmd = [
                str(Path(sys.executable).parent / "lerobot-vib-eval"),
                f"--policy.path={args.policy}",
                "--policy.safety.enabled=true",
                f"--policy.safety.band_index={reading}",
                "--env.type=vib_arm",
                f"--env.dataset_root={args.dataset_root}",
                "--env.perturbation.occlusion=true",
                f"--eval.n_episodes={args.episodes}",
                "--eval.batch_size=10",
                "--eval.use_async_envs=false",
                f"--seed={args.seed}",
                f"--output_dir={out}",
            ]
            subprocess.run(cmd, check=True, env={**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")})
        results[reading] = read(out)
    lines = [
        f"Machine: {cpu_name()}. Policy: {args.policy} (band of {len(calibration['gamma_band'])} steps, "
        f"{calibration.get('gamma_method')}, alpha {calibration.get('conformal_alpha')}). {args.episodes} occlusion "
        f"episodes from seed {args.seed}, the stop on, the same episodes for both readings.",
        f"Command: python benchmarks/band_during_stop.py {' '.join(sys.argv[1:])}",
        "",
        "| band read at | stops begun under the board | ended when the scene cleared | ended by the clock (board still "
        "there) | never ended | other stops | successes |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for reading, episodes in results.items():
        kinds = [k for e in episodes for k in e["stops"]]
        lines.append(
            f"| {reading} | {len(kinds)} | {kinds.count('scene cleared')} | {kinds.count('clock')} | "
            f"{kinds.count('never')} | {sum(e['other_stops'] for e in episodes)} | "
            f"{sum(e['success'] for e in episodes)}/{len(episodes)} |"
        )
    (args.output_dir / "results.json").write_text(json.dumps(results, indent=1))
    emit("\n".join(lines) + "\n", args.output)


if __name__ == "__main__":
    main()
