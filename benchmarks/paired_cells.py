"""Paired comparison of a benchmark's perturbed cells with its clean ones.

`lerobot-vib-benchmark` evaluates every condition on the same episode seeds, so a perturbed episode has a clean
twin: same block or cube, same policy, only the images differ. This prints, per row and perturbation, how many
twins end differently (success, max reward) and how far the perturbation moves u, which tells a perturbation
that changes nothing apart from one the policy shrugs off. An AUROC alone cannot: it ranks, so a systematic
shift of 0.1% reads as well separated.

    python benchmarks/paired_cells.py outputs/bench_tc_cpu_small/cells
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def compare(clean: dict, perturbed: dict) -> dict:
    if clean["seeds"] != perturbed["seeds"]:
        raise ValueError(f"{perturbed['condition']}/{perturbed['variant']}: its seeds differ from the clean cell's.")
    out = {
        "pairs": len(clean["seeds"]),
        "success_differs": sum(a != b for a, b in zip(clean["success"], perturbed["success"], strict=True)),
        "max_reward_differs": sum(a != b for a, b in zip(clean["max_reward"], perturbed["max_reward"], strict=True)),
    }
    if clean["u"] is not None:
        clean_max = np.array([max(u) for u in clean["u"]])
        change = np.array([max(u) for u in perturbed["u"]]) / clean_max - 1
        # Twins may end at different steps (a success ends early): compare the steps both ran.
        pairs = zip(perturbed["u"], clean["u"], strict=True)
        frames = [np.abs(np.subtract(a[: len(b)], b[: len(a)])).max() for a, b in pairs]
        out |= {
            "max_u_change_pct": (round(100 * change.min(), 3), round(100 * change.max(), 3)),
            "frame_u_abs_diff_max": round(float(max(frames)), 4),
            "clean_max_u_mean": round(float(clean_max.mean()), 3),
        }
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("cells", type=Path, help="A benchmark's cells/ folder")
    args = parser.parse_args()
    print("| variant | condition | pairs | success differs | max reward differs | max u change % | max abs u diff |")
    print("| --- | --- | ---: | ---: | ---: | --- | ---: |")
    for clean_path in sorted((args.cells / "normal").glob("*.json")):
        clean = json.loads(clean_path.read_text())
        for condition in sorted(p.name for p in args.cells.iterdir() if p.name not in ("normal", "calibration")):
            path = args.cells / condition / clean_path.name
            if not path.exists():
                continue
            r = compare(clean, json.loads(path.read_text()))
            lo_hi = "{}..{}".format(*r["max_u_change_pct"]) if "max_u_change_pct" in r else "-"
            print(
                f"| {clean['variant']} | {condition} | {r['pairs']} | {r['success_differs']} | "
                f"{r['max_reward_differs']} | {lo_hi} | {r.get('frame_u_abs_diff_max', '-')} |"
            )


if __name__ == "__main__":
    main()
