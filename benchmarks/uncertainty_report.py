"""The report of `uncertainty_scores.py` over several checkpoints (training seeds), grouped by recipe.

    python benchmarks/uncertainty_report.py \
        --group "keypoints=outputs/scores/a/results.json,outputs/scores/b/results.json" \
        --output benchmarks/results/uncertainty_scores_cpu_2core/report.md

Every number is the mean over a group's checkpoints, with the range in brackets when there are several.
The default score and threshold are chosen on the validation split (`choose`): the test split is reported.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

TUNED = ("gaussian", "color", "camera_shake", "unseen_block", "occlusion", "black")
HELD_OUT = ("dim", "frozen")
TARGETS = {
    "occlusion": 0.90,
    "unseen_block": 0.90,
    "black": 0.90,
    "gaussian": 0.75,
    "color": 0.75,
    "camera_shake": 0.75,
}
THRESHOLD_NAMES = {"mean_plus_2std": "mean + 2 std", "conformal": "conformal", "time_band": "time band"}


def agg(values: list[float | None], fmt: str = "{:.2f}") -> str:
    values = [v for v in values if v is not None]
    if not values:
        return "-"
    if len(values) == 1:
        return fmt.format(values[0])
    return f"{fmt.format(np.mean(values))} ({fmt.format(min(values))}-{fmt.format(max(values))})"


def mean_of(values: list[float | None]) -> float | None:
    values = [v for v in values if v is not None]
    return float(np.mean(values)) if values else None


def choose(results: list[dict]) -> tuple[str, str]:
    """On validation, the (score, threshold) pair for the safety stop: the most occlusions caught within 5
    steps among the pairs with at most 10% clean false stops; ties go to the higher mean frame AUROC over the
    tuned perturbations. (The project's bar is a stop that fires when the robot is out of its depth and not
    otherwise; AUROC alone says nothing about a threshold.)"""
    val = [r["splits"]["validation"] for r in results if r["splits"].get("validation")]

    def key(pair):
        score, name = pair
        rows = [v["stops"][score][name] for v in val]
        false = mean_of([r["clean_false_stops"] for r in rows])
        caught = mean_of([r["occlusion_caught_5"] for r in rows])
        auroc = mean_of([mean_of([v["auroc"][score].get(c) for c in TUNED]) for v in val])
        return (false <= 0.10, caught if false <= 0.10 else -false, auroc)

    pairs = [(score, name) for score, stops in val[0]["stops"].items() for name in stops]
    return max(pairs, key=key)


# Results written before the project's seed plan (lerobot_vib.seeds) record no seeds; these are the ones used.
SEEDS_BEFORE_PLAN = {"calibration": 600000, "validation": 400000, "test": 500000}


def report(groups: dict[str, list[dict]], commands: list[str]) -> str:
    first = next(iter(groups.values()))[0]
    seeds = first.get("split_seeds", SEEDS_BEFORE_PLAN)
    lines = [
        "# Uncertainty scores on the simulated arm",
        "",
        f"Machine (rollouts and scores): {first['machine']}. Checkpoints: the arm preset "
        "(`configs/policy/vib_arm_sim.json`), trained where each group's name says (H200: `benchmarks/gpu_train.sh`), "
        "with the normalization floor unless the name says otherwise. Commands:",
        "",
        "```bash",
        *commands,
        "```",
        "",
        "Every score is read from the same rollouts, with the stop off: clean and perturbed rollouts share "
        "episode seeds, and frames pair by seed and step (occlusion: the occluded steps only; frozen: from the "
        "freeze on). A number is the mean over a group's training seeds with the range in brackets. Seeds: "
        f"calibration rollouts {seeds['calibration']}.. (they set the conformal thresholds), validation "
        f"{seeds['validation']}.. (every choice), test {seeds['test']}.. (reported; nothing chosen on them). "
        "The held-out perturbations (dim, frozen) were "
        "never looked at while choosing. The stop columns are the first crossing of each threshold: with the "
        "stop off, a rollout is the stopped one's up to its first stop.",
        "",
    ]
    chosen = None
    for label, results in groups.items():
        n_seeds = len(results)
        if any(r["splits"].get("validation") for r in results):
            best, threshold = choose(results)
            chosen = chosen or (best, threshold)
        elif chosen is None:
            raise ValueError(f"{label}: no validation split, and no group before it made the choice.")
        else:
            best, threshold = chosen  # a group measured on test seeds only is judged by the earlier choice
        test = [r["splits"]["test"] for r in results]
        lines += [f"## {label} ({n_seeds} training seed{'s' if n_seeds > 1 else ''})", ""]
        for r, t in zip(results, test, strict=True):
            counts = ", ".join(f"{c} {n}" for c, (_, n) in t["success"].items())
            has_val = "validation and test" if r["splits"].get("validation") else "test only"
            lines.append(f"- `{r['policy']}`: {has_val}; test episodes per condition: {counts}.")
        lines += [
            "",
            "The choice rule, set on validation before any test result was read (a one-episode dry run of the "
            "script had used the first test seed): the (score, threshold) pair "
            "with the most occlusions caught within 5 steps among the pairs with at most 10% clean false stops; "
            "ties to the higher mean frame AUROC over the tuned perturbations.",
            "",
        ]
        success = [t["success"].get("clean") for t in test]
        calibration = [r.get("calibration_success") for r in results]
        lines.append(
            "Clean success with the stop off, test: "
            + ", ".join(f"{k}/{n}" for k, n in success if n)
            + "; calibration rollouts: "
            + ", ".join(f"{k}/{n}" for k, n in (c for c in calibration if c))
            + (
                f". Chosen on this group's validation: **{best}** with the "
                f"**{THRESHOLD_NAMES.get(threshold, threshold)}** threshold."
                if any(r["splits"].get("validation") for r in results)
                else f". No validation here: judged with the first group's choice, **{best}** with the "
                f"**{THRESHOLD_NAMES.get(threshold, threshold)}** threshold."
            )
        )
        lines += ["", "### Frame AUROC, test (clean vs perturbed, paired by seed and step)", ""]
        conditions = [*TUNED, *HELD_OUT]
        lines.append("| score | " + " | ".join(c + (" (held out)" if c in HELD_OUT else "") for c in conditions) + " |")
        lines.append("| --- |" + " --- |" * len(conditions))
        for score in test[0]["auroc"]:
            cells = [agg([t["auroc"][score].get(c) for t in test]) for c in conditions]
            name = f"**{score}**" if score == best else score
            lines.append(f"| {name} | " + " | ".join(cells) + " |")
        lines += ["", "Validation (what the choice saw):", ""]
        lines.append("| score | " + " | ".join(TUNED) + " |")
        lines.append("| --- |" + " --- |" * len(TUNED))
        for score in test[0]["auroc"]:
            val = [r["splits"]["validation"]["auroc"][score] for r in results if r["splits"].get("validation")]
            lines.append(f"| {score} | " + " | ".join(agg([v.get(c) for v in val]) for c in TUNED) + " |")
        lines += [
            "",
            "### The safety stop, test: alpha = 0.1 where conformal",
            "",
            "| score | threshold | clean false stops | occlusions caught within 5 steps | stopped before the "
            "occluder | mean delay (steps) |",
            "| --- | --- | --- | --- | --- | --- |",
        ]
        for score in test[0]["stops"] if all(t["stops"] for t in test) else []:
            for name in test[0]["stops"][score]:
                rows = [t["stops"][score][name] for t in test]
                lines.append(
                    f"| {score} | {THRESHOLD_NAMES.get(name, name)} | "
                    f"{agg([r['clean_false_stops'] for r in rows], '{:.0%}')} | "
                    f"{agg([r['occlusion_caught_5'] for r in rows], '{:.0%}')} | "
                    f"{agg([r['occlusion_stopped_before'] for r in rows], '{:.0%}')} | "
                    f"{agg([r['occlusion_mean_delay'] for r in rows], '{:.1f}')} |"
                )
        lines += ["", "### Success with the stop off, test", ""]
        lines.append("| " + " | ".join(["clean", *conditions]) + " |")
        lines.append("|" + " --- |" * (len(conditions) + 1))
        lines.append(
            "| "
            + " | ".join(
                agg([t["success"][c][0] / t["success"][c][1] for t in test if c in t["success"]], "{:.0%}")
                for c in ["clean", *conditions]
            )
            + " |"
        )
        lines += [
            "",
            "### Largest clean u (test), per score: max over clean frames of s / mean over training frames",
            "",
        ]
        lines.append("| " + " | ".join(test[0]["max_u_clean"]) + " |")
        lines.append("|" + " --- |" * len(test[0]["max_u_clean"]))
        lines.append(
            "| " + " | ".join(agg([t["max_u_clean"][s] for t in test], "{:.1f}") for s in test[0]["max_u_clean"]) + " |"
        )
        lines += ["", *decomposition_section(results), ""]
        if all(t["stops"] for t in test):
            lines += targets_section(test, best, threshold)
        else:
            lines += ["No occlusion rollouts on the test seeds here: no stop and no targets.", ""]
    return "\n".join(lines) + "\n"


def decomposition_section(results: list[dict]) -> list[str]:
    dec = [r["decomposition"]["test"] for r in results]
    lines = [
        "### The rate taken apart, test (median over paired frames, clean -> perturbed)",
        "",
        "image path: the rate with the state path held at its training mean; state path: with the camera path "
        "held at its training mean; mean and variance terms: the KL's two parts, averaged over tokens.",
        "",
        "| condition | rate | image path | state path | mean term | variance term | tokens whose mean term rose most |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for condition in [*TUNED, *HELD_OUT]:
        rows = [d[condition] for d in dec if condition in d]
        if not rows:
            continue

        def pair(key, rows=rows):
            return f"{agg([r[key][0] for r in rows], '{:.1f}')} -> {agg([r[key][1] for r in rows], '{:.1f}')}"

        tokens = np.mean([r["mean_term_tokens"] for r in rows], axis=0)
        top = ", ".join(f"{i} (+{tokens[i]:.0f})" for i in np.argsort(tokens)[::-1][:3])
        lines.append(
            f"| {condition} | {pair('rate')} | {pair('image_rate')} | {pair('rate_state_path')} | "
            f"{pair('mean_term')} | {pair('var_term')} | {top} |"
        )
    spread = [d["clean_spread"] for d in dec]
    lines += [
        "",
        "Clean frames: std of the rate "
        + agg([s["std_rate"] for s in spread], "{:.1f}")
        + ", of the image path "
        + agg([s["std_image_path"] for s in spread], "{:.1f}")
        + ", of the state path "
        + agg([s["std_state_path"] for s in spread], "{:.1f}")
        + "; correlation of the rate with the image path "
        + agg([s["corr_rate_image_path"] for s in spread])
        + ", with the state path "
        + agg([s["corr_rate_state_path"] for s in spread])
        + ".",
    ]
    return lines


def targets_section(test: list[dict], best: str, threshold: str) -> list[str]:
    lines = [f"### Against the targets ({best}, {THRESHOLD_NAMES.get(threshold, threshold)} threshold; test)", ""]
    lines += ["| target | measured | met |", "| --- | --- | --- |"]

    def row(name: str, values: list, fmt: str, met: bool) -> None:
        lines.append(f"| {name} | {agg(values, fmt)} | {'yes' if met else 'no'} |")

    for condition, target in TARGETS.items():
        values = [t["auroc"][best].get(condition) for t in test]
        value = mean_of(values)
        row(f"frame AUROC {condition} >= {target}", values, "{:.2f}", value is not None and value >= target)
    stops = [t["stops"][best][threshold] for t in test]
    caught = [r["occlusion_caught_5"] for r in stops]
    false = [r["clean_false_stops"] for r in stops]
    row("occlusions caught within 5 steps >= 90%", caught, "{:.0%}", mean_of(caught) >= 0.9)
    row("clean false stops <= 10%", false, "{:.0%}", mean_of(false) <= 0.1)
    max_u = [t["max_u_clean"]["rate"] for t in test]
    row("no clean rollout with the rate's u > 5", max_u, "{:.1f}", max(max_u) <= 5)
    return [*lines, ""]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--group", action="append", required=True, help="LABEL=results.json[,results.json...]")
    parser.add_argument("--command", action="append", default=[], help="a command to list in the report")
    parser.add_argument("--output", type=Path, required=True)
    args = parser.parse_args()
    groups = {}
    for spec in args.group:
        label, paths = spec.split("=", 1)
        groups[label] = [json.loads(Path(p).read_text()) for p in paths.split(",")]
    text = report(groups, args.command)
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(text)
    print(text)


if __name__ == "__main__":
    main()
