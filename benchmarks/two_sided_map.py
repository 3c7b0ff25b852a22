"""The rate map read both ways: `abs_map_score` (the cell that moved furthest from its training statistics,
either way) beside `map_score` and `low_map_score`, on finished `lerobot-vib-benchmark` runs.

Which way a board in front of the camera moves the token network's cell rates is not fixed: on VIB's trunk it
lowers them (`low_map_score` stops it), on ACT's trunk cut after layer3 it raises them (`map_score` sees it),
and on ACT's trunk cut after layer2 it lowered them on one training seed and raised them on another. A stop
that has to be told the direction is a stop chosen on the answer; |z| does not need it.

At `--policy.map_top_k=1` (every benchmark row) the score is exactly recoverable from what the benchmark
traced: max_c |z_c| = max(max_c z_c, max_c -z_c), the raw `map_score` and `low_map_score`, each of which the
cells hold as u = s / s_bar with s_bar from the calibrated checkpoint's `calibration.score_means`. Its
thresholds are set as the report sets every score's (`benchmark_report.score_stops`: conformal, the time band
and FAIL-Detect's band on the chosen run time's clean validation rollouts, judged on the test cells), so it is
left in raw units: a constant scale moves no stop. Cells that already trace `abs_map_score` (runs after the
score was added) are read as they are. Also: each score's frame AUROC against every perturbation
(`benchmark_report.score_aurocs`), and the default score's rule on validation rollouts alone
(`choose_score_on_validation`) with the score offered, where the run has occluded validation rollouts.

Each argument is `output_dir:variant:seed` of a benchmark run that kept its calibrated checkpoint
(`<output_dir>/calibrated/<variant>/seed_<seed>/config.json`):

    python benchmarks/two_sided_map.py \\
        outputs/bn_l2_s1000:vib_tokens_narrow_act_trunk_l2:1000 \\
        outputs/bn_l2_s2000:vib_tokens_narrow_act_trunk_l2:2000 \\
        --output benchmarks/results/two_sided_map_cpu_2core/report.md
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from report import cpu_name

from lerobot_vib.scripts.benchmark import VALIDATION
from lerobot_vib.scripts.benchmark_report import (
    STOP_WITHIN,
    choose_score_on_validation,
    runtime_of,
    score_aurocs,
    score_stops,
)

SCORES = ("map_score", "low_map_score", "abs_map_score")
KEPT = ("false_stops", "clean_episodes", "in_time", "occlusion_episodes")


def with_abs_map_score(cell: dict, means: dict[str, float]) -> dict:
    """The cell with an `abs_map_score` trace (raw |z| units) derived from its `map_score` and `low_map_score`
    traces, unless it already has one."""
    scores = cell.get("scores", {})
    if "abs_map_score" in scores or "map_score" not in scores:
        return cell
    high, low = means["map_score"], means["low_map_score"]
    derived = [
        [max(a * high, b * low) for a, b in zip(up, down, strict=True)]
        for up, down in zip(scores["map_score"], scores["low_map_score"], strict=True)
    ]
    return {**cell, "scores": {**scores, "abs_map_score": derived}}


def load_run(spec: str) -> dict:
    """One `output_dir:variant:seed`: its calibration cell, test cells and occluded validation cell."""
    folder, variant, seed = spec.rsplit(":", 2)
    out = Path(folder)
    config_path = out / "calibrated" / variant / f"seed_{seed}" / "config.json"
    if not config_path.exists():
        raise SystemExit(f"{spec}: no calibrated checkpoint at {config_path}; the derivation needs its score means.")
    config = json.loads(config_path.read_text())
    if config.get("map_top_k", 1) != 1:
        raise SystemExit(f"{spec}: map_top_k={config['map_top_k']}; |z| is recoverable from the traces at k = 1 only.")
    means = config["calibration"]["score_means"]
    if not {"map_score", "low_map_score"} <= set(means):
        raise SystemExit(f"{spec}: the checkpoint has no map statistics (score means {sorted(means)}).")
    choices = json.loads((out / "choices.json").read_text())
    runtime = runtime_of(choices, variant, int(seed))
    if runtime is None:
        raise SystemExit(f"{spec}: choices.json has no run time for this variant and seed.")
    read = lambda p: with_abs_map_score(json.loads(p.read_text()), means)  # noqa: E731
    cells = {p.parent.parent.name: read(p) for p in sorted(out.glob(f"cells/*/{variant}/seed_{seed}.json"))}
    if "normal" not in cells or "occlusion" not in cells:
        raise SystemExit(f"{spec}: the clean and occluded test cells are needed, found {sorted(cells)}.")
    occluded = out / "validation_perturbed" / "occlusion" / variant / f"seed_{seed}.json"
    return {
        "folder": folder, "variant": variant, "seed": int(seed), "runtime": runtime, "means": means,
        "calibration": read(out / VALIDATION / variant / f"seed_{seed}" / f"{runtime.replace(':', '_', 1)}.json"),
        "cells": cells,
        "occluded_validation": read(occluded) if occluded.exists() else None,
    }  # fmt: skip


def measure(run: dict, alpha: float) -> dict:
    stops = score_stops(run["cells"], run["calibration"], alpha)
    aurocs = score_aurocs(run["cells"])
    choice = choose_score_on_validation(run["calibration"], run["occluded_validation"], alpha)
    on_test = stops.get(choice["score"], {}).get(choice["threshold"]) if choice and choice["score"] else None
    return {
        "folder": run["folder"], "variant": run["variant"], "seed": run["seed"], "runtime": run["runtime"],
        "score_means": {k: run["means"][k] for k in ("map_score", "low_map_score")},
        "stops": {s: {t: {k: r[k] for k in ("gamma", "false_stops", "clean_episodes", "in_time",
                                            "occlusion_episodes", "early_stops")} for t, r in stops[s].items()}
                  for s in SCORES if s in stops},
        "aurocs": {s: aurocs.get(s, {}) for s in SCORES},
        "choice": None if not choice or not choice["score"] else {
            "score": choice["score"], "threshold": choice["threshold"],
            "validation": {k: choice["row"][k] for k in KEPT},
            "test": None if on_test is None else {k: on_test[k] for k in KEPT},
        },
    }  # fmt: skip


def _frac(k: int, n: int) -> str:
    return f"{k}/{n}"


def stop_cell(row: dict) -> str:
    """ "occlusions in time / occluded, clean stopped / clean" of one stop row."""
    return f"{_frac(row['in_time'], row['occlusion_episodes'])}, {_frac(row['false_stops'], row['clean_episodes'])}"


def markdown(rows: list[dict], alpha: float, command: str, wall_s: float) -> str:
    lines = [
        "# The rate map read both ways: `abs_map_score`",
        "",
        f"- Command: `{command}`",
        f"- Machine: {cpu_name()}; {wall_s / 60:.1f} min",
        f"- alpha = {alpha}; thresholds set on each run's clean validation rollouts at its chosen run time; every "
        "number below on its test seeds. `abs_map_score` derived from the traced `map_score` and "
        "`low_map_score` (k = 1; the script's docstring says how).",
        "",
        f"## The stop: occlusions stopped within {STOP_WITHIN} steps, clean rollouts stopped",
        "",
        "| variant, training seed | score | conformal | band | std band |",
        "| --- | --- | --- | --- | --- |",
    ]
    for r in rows:
        for s in SCORES:
            by = r["stops"].get(s, {})
            cols = [stop_cell(by[t]) if t in by else "-" for t in ("conformal", "band", "std_band")]
            lines.append(f"| {r['variant']}, {r['seed']} | `{s}` | " + " | ".join(cols) + " |")
    lines += [
        "",
        "Target: at least 90% of occlusions in time, at most 5% of clean rollouts stopped.",
        "",
        "## Frame AUROC, clean against each perturbation (paired frames)",
        "",
    ]
    conditions = sorted({c for r in rows for s in SCORES for c in r["aurocs"].get(s, {})})
    lines += ["| variant, training seed | score | " + " | ".join(conditions) + " |"]
    lines += ["| --- | --- | " + " | ".join("---" for _ in conditions) + " |"]
    for r in rows:
        for s in SCORES:
            a = r["aurocs"].get(s, {})
            lines.append(
                f"| {r['variant']}, {r['seed']} | `{s}` | "
                + " | ".join(f"{a[c]:.2f}" if c in a else "-" for c in conditions)
                + " |"
            )
    lines += [
        "",
        "## The default score's rule on validation rollouts, `abs_map_score` offered",
        "",
        "Each (score, threshold) pair set on half of the clean validation rollouts and judged on the other half and "
        "the occluded validation rollouts; the most occlusions in time among the pairs that stop at most 10% of "
        "those clean rollouts. Then what that pair does on the test seeds.",
        "",
        "| variant, training seed | pick | validation: in time, clean stopped | test: in time, clean stopped |",
        "| --- | --- | --- | --- |",
    ]
    for r in rows:
        c = r["choice"]
        if c is None:
            lines.append(f"| {r['variant']}, {r['seed']} | no occluded validation rollouts | - | - |")
            continue
        v, t = c["validation"], c["test"]
        test = (
            "-"
            if t is None
            else f"{_frac(t['in_time'], t['occlusion_episodes'])}, {_frac(t['false_stops'], t['clean_episodes'])}"
        )
        lines.append(
            f"| {r['variant']}, {r['seed']} | `{c['score']}`, {c['threshold']} | "
            f"{_frac(v['in_time'], v['occlusion_episodes'])}, {_frac(v['false_stops'], v['clean_episodes'])} | {test} |"
        )
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", help="output_dir:variant:seed of finished benchmark runs")
    parser.add_argument("--alpha", type=float, default=0.1)
    parser.add_argument("--output", type=Path, required=True, help="the report (.md); its .json beside it")
    args = parser.parse_args()
    start = time.time()
    rows = [measure(load_run(spec), args.alpha) for spec in args.runs]
    command = "python benchmarks/two_sided_map.py " + " ".join(args.runs) + f" --output {args.output}"
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.with_suffix(".json").write_text(json.dumps({"alpha": args.alpha, "rows": rows}, indent=1))
    args.output.write_text(markdown(rows, args.alpha, command, time.time() - start))
    print(args.output.read_text())


if __name__ == "__main__":
    main()
