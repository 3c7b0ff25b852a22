"""The benchmark's report: success with Wilson intervals, the uncertainty metrics (metrics.py), and the plots.

Every number comes from the saved cells (`<output_dir>/cells/<condition>/<variant>.json`) and the scores'
training statistics (`scores.json`), so the report can be rebuilt at any time from what is on disk.
"""

from __future__ import annotations

import json
import logging
import platform
import re
from pathlib import Path
from typing import Any

import numpy as np

from ..calibration import conformal_gamma, conformal_min_scores
from ..metrics import auroc, roc_curve, stop_metrics, time_indexed_band, wilson_interval
from ..sim.perturbations import CONDITIONS, draw_scene_episode
from ..variants import VARIANTS

logger = logging.getLogger(__name__)

THRESHOLDS = ("mean_2std", "conformal", "band")


def success_cell(cell: dict) -> dict:
    k, n = sum(cell["success"]), len(cell["success"])
    low, high = wilson_interval(k, n)
    return {"k": k, "n": n, "pc": 100 * k / n, "low": 100 * low, "high": 100 * high}


def thresholds(calibration: dict, train_gamma: float | None, alpha: float) -> dict[str, Any]:
    """gamma of each kind from the clean calibration rollouts of one row (metrics.py)."""
    traces = calibration["u"]
    out: dict[str, Any] = {"mean_2std": train_gamma, "conformal": None, "band": None, "notes": []}
    needed = conformal_min_scores(alpha)
    if len(traces) >= needed:
        out["conformal"] = conformal_gamma(np.array([max(t) for t in traces]), alpha)
    else:
        out["notes"].append(f"conformal needs {needed} calibration episodes at alpha={alpha}, got {len(traces)}")
    half = len(traces) // 2
    if len(traces) - half >= needed and half >= 1:
        out["band"] = time_indexed_band(traces[:half], traces[half:], alpha).round(5).tolist()
    else:
        out["notes"].append(f"the band needs 1 + {needed} calibration episodes at alpha={alpha}, got {len(traces)}")
    return out


def occlusion_onsets(cell: dict) -> list[int | None]:
    return [draw_scene_episode(CONDITIONS["occlusion"], seed).occluded_steps.start for seed in cell["seeds"]]


def uncertainty(cells: dict, variant: str, conditions: list[str], train_gamma: float | None, alpha: float) -> dict:
    clean = cells.get((variant, "normal"))
    result: dict[str, Any] = {"score": VARIANTS[variant].score, "auroc": {}, "failure_auroc_clean": None, "stops": {}}
    result["thresholds"] = thresholds(cells[(variant, "calibration")], train_gamma, alpha)
    if clean is None:
        return result
    clean_frames = np.concatenate([np.asarray(t) for t in clean["u"]])
    clean_max = [max(t) for t in clean["u"]]
    for condition in conditions:
        if condition == "normal":
            continue
        cell = cells[(variant, condition)]
        frames = np.concatenate([np.asarray(t) for t in cell["u"]])
        result["auroc"][condition] = {
            "frames": auroc(clean_frames, frames),
            "episodes": auroc(clean_max, [max(t) for t in cell["u"]]),
        }
    failed = [m for m, s in zip(clean_max, clean["success"], strict=True) if not s]
    succeeded = [m for m, s in zip(clean_max, clean["success"], strict=True) if s]
    if failed and succeeded:
        result["failure_auroc_clean"] = auroc(succeeded, failed)
    occluded = cells.get((variant, "occlusion"))
    for name in THRESHOLDS:
        gamma = result["thresholds"][name]
        if gamma is None:
            continue
        false_stops = stop_metrics(clean["u"], gamma)
        row = {"clean_episodes": false_stops.n_episodes, "false_stops": false_stops.stopped}
        if occluded is not None:
            occ = stop_metrics(occluded["u"], gamma, occlusion_onsets(occluded))
            row.update(
                occlusion_episodes=occ.n_episodes, occlusion_stops=occ.stopped, early_stops=occ.early,
                mean_delay=occ.mean_delay, delays=occ.delays,
            )  # fmt: skip
        result["stops"][name] = row
    return result


# LeRobot's training log: its progress bar (exact step) then the loss line, whose `step:` is rounded ("1K").
_LOSS_LINE = re.compile(
    r"(\d+)/\d+ \[[^\]\n]*\]\s*INFO[^\n]*? step:(\S+) [^\n]*?\bl1_loss:([-+.\de]+)(?:[^\n]*?\brate:([-+.\de]+))?"
)


def training_curve(log_text: str) -> list[dict]:
    """(step, L1, rate) of every loss line in a `lerobot-train` log, sorted by step.

    A resumed training appends to the log and repeats the steps after its checkpoint: the later value wins. A
    progress-bar count that disagrees with the line's own rounded step (the bar not yet redrawn) is dropped
    rather than guessed.
    """
    from lerobot.utils.utils import format_big_number

    points: dict[int, dict] = {}
    for m in _LOSS_LINE.finditer(log_text):
        step = int(m.group(1))
        if format_big_number(step) != m.group(2):
            continue
        points[step] = {
            "step": step,
            "l1": float(m.group(3)),
            "rate": None if m.group(4) is None else float(m.group(4)),
        }
    return [points[k] for k in sorted(points)]


def training_curves(out: Path) -> dict[str, list[dict]]:
    """The loss curves of the networks this benchmark trained (none for given checkpoints)."""
    logs = {net: out / "train" / f"{net}.log" for net in ("vib", "act")}
    curves = {net: training_curve(log.read_text(errors="replace")) for net, log in logs.items() if log.exists()}
    return {net: curve for net, curve in curves.items() if curve}


def _pct(k: int, n: int) -> str:
    return f"{k}/{n} ({100 * k / n:.0f}%)" if n else "-"


def _num(x: float | None, fmt: str = ".2f") -> str:
    return "-" if x is None else format(x, fmt)


def write_report(cfg, cells: dict, wall_s: float) -> dict:
    import lerobot
    import torch

    out = Path(cfg.output_dir)
    scores = json.loads((out / "scores.json").read_text()) if (out / "scores.json").exists() else {}
    results: dict[str, Any] = {
        "config": json.loads((out / "config.json").read_text()),
        "wall_s": wall_s,
        "versions": {"python": platform.python_version(), "torch": torch.__version__, "lerobot": lerobot.__version__},
        "scores": scores,
        "success": {v: {c: success_cell(cells[(v, c)]) for c in cfg.conditions} for v in cfg.variants},
        "uncertainty": {},
        "training": training_curves(out),
    }
    for v in cfg.variants:
        score = VARIANTS[v].score
        if score is not None:
            gamma = scores.get(score, {}).get("mean_2std")
            results["uncertainty"][v] = uncertainty(cells, v, cfg.conditions, gamma, cfg.alpha)
    (out / "results.json").write_text(json.dumps(results, indent=1))
    plots = _plots(cfg, cells, results, out)
    (out / "report.md").write_text(_markdown(cfg, results, plots))
    logger.info("Report: %s", out / "report.md")
    return results


def _markdown(cfg, results: dict, plots: list[str]) -> str:
    c = results["config"]
    lines = [
        "# lerobot-vib-benchmark",
        "",
        f"- Command: `{c['command']}`",
        f"- Env: `{c['env_type']}`, dataset `{c['dataset']['repo_id']}`; profile `{cfg.profile}`, "
        f"{cfg.steps} training steps, device `{cfg.device}`",
        f"- Machine: {c['machine']['processor'] or c['machine']['platform']}, {c['machine']['cpus']} CPUs; "
        + ", ".join(f"{k} {v}" for k, v in results["versions"].items()),
        f"- Wall time: {results['wall_s'] / 60:.1f} min (every invocation; a killed one to its last beat, <= 30 s)",
        f"- Episode seeds: {cfg.eval_seed}.. per condition for every row; calibration {cfg.calibration_seed}..",
        "",
        "## Success (episodes succeeded / evaluated, 95% Wilson interval)",
        "",
        "| variant | " + " | ".join(cfg.conditions) + " |",
        "| --- |" + " --- |" * len(cfg.conditions),
    ]
    for v in cfg.variants:
        cells = [results["success"][v][cond] for cond in cfg.conditions]
        row = [f"{s['k']}/{s['n']} = {s['pc']:.0f}% [{s['low']:.0f}-{s['high']:.0f}]" for s in cells]
        lines.append(f"| {VARIANTS[v].label} | " + " | ".join(row) + " |")
    if results["training"]:
        lines += [
            "",
            "## Training (L1 of the normalized action chunk, training mode, from the `lerobot-train` logs)",
            "",
            "| network | logged steps | L1 first | L1 at half | L1 last | rate last |",
            "| --- | --- | --- | --- | --- | --- |",
        ]
        for net, curve in results["training"].items():
            first, half, last = curve[0], curve[len(curve) // 2], curve[-1]
            lines.append(
                f"| {net.upper()} | {first['step']}-{last['step']} | {first['l1']:.3f} (step {first['step']}) | "
                f"{half['l1']:.3f} (step {half['step']}) | {last['l1']:.3f} | {_num(last['rate'])} |"
            )
    if results["uncertainty"]:
        perturbed = [cond for cond in cfg.conditions if cond != "normal"]
        lines += [
            "",
            "## Uncertainty: AUROC of u separating clean (normal) from perturbed rollouts",
            "",
            "Frames: every step's u; episodes: each episode's max u. 0.5 is chance. The last column: an "
            "episode's max u predicting failure among the clean episodes.",
            "",
            "| variant (score) | " + " | ".join(f"{p} frames / episodes" for p in perturbed) + " | clean failure |",
            "| --- |" + " --- |" * (len(perturbed) + 1),
        ]
        for v, u in results["uncertainty"].items():
            row = [f"{_num(u['auroc'][p]['frames'])} / {_num(u['auroc'][p]['episodes'])}" for p in perturbed]
            lines.append(
                f"| {VARIANTS[v].label} ({u['score']}) | " + " | ".join(row) + f" | {_num(u['failure_auroc_clean'])} |"
            )
        lines += [
            "",
            f"## The safety stop, judged offline on the recorded u (alpha = {cfg.alpha})",
            "",
            "A rollout stops at its first step with u above the threshold. False stops: clean (normal) episodes "
            "that stop. On occlusion: stops at or after the occluder's entry, stops before it (early, also "
            "false), and the mean delay in steps from entry to stop. Thresholds: the paper's mean + 2 std of "
            "the training frames; split-conformal on the calibration rollouts' max u; the time-indexed band.",
            "",
            "| variant | threshold | gamma | false stops (clean) | occlusion stops | early | mean delay |",
            "| --- | --- | --- | --- | --- | --- | --- |",
        ]
        for v, u in results["uncertainty"].items():
            for name in THRESHOLDS:
                gamma, row = u["thresholds"][name], u["stops"].get(name)
                if row is None:
                    lines.append(f"| {VARIANTS[v].label} | {name} | - | - | - | - | - |")
                    continue
                shown = f"{min(gamma):.2f}-{max(gamma):.2f}" if isinstance(gamma, list) else f"{gamma:.2f}"
                occ = ["-", "-", "-"]
                if "occlusion_episodes" in row:
                    occ = [
                        _pct(row["occlusion_stops"], row["occlusion_episodes"]),
                        str(row["early_stops"]),
                        _num(row["mean_delay"], ".1f"),
                    ]
                lines.append(
                    f"| {VARIANTS[v].label} | {name} | {shown} | {_pct(row['false_stops'], row['clean_episodes'])} | "
                    + " | ".join(occ)
                    + " |"
                )
            for note in u["thresholds"]["notes"]:
                lines.append(f"\n_{VARIANTS[v].label}: {note}._")
    if plots:
        lines += ["", "## Plots", ""] + [f"![{p}]({p})" for p in plots]
    return "\n".join(lines) + "\n"


def _plots(cfg, cells: dict, results: dict, out: Path) -> list[str]:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        logger.warning("matplotlib is not installed: no plots.")
        return []
    written = []
    fig, ax = plt.subplots(figsize=(max(6, 1.6 * len(cfg.conditions)), 4))
    width = 0.8 / len(cfg.variants)
    for i, v in enumerate(cfg.variants):
        s = [results["success"][v][c] for c in cfg.conditions]
        x = np.arange(len(cfg.conditions)) + (i - (len(cfg.variants) - 1) / 2) * width
        pc = np.array([c["pc"] for c in s])
        err = np.array([[c["pc"] - c["low"] for c in s], [c["high"] - c["pc"] for c in s]])
        ax.bar(x, pc, width, yerr=err, capsize=2, label=VARIANTS[v].label)
    ax.set_xticks(np.arange(len(cfg.conditions)), cfg.conditions)
    ax.set_ylabel("success % (95% Wilson)")
    ax.set_ylim(0, 100)
    ax.legend(fontsize=7, ncol=2, loc="upper right")
    fig.tight_layout()
    fig.savefig(out / "success.png", dpi=120)
    plt.close(fig)
    written.append("success.png")

    if results["training"]:
        fig, ax = plt.subplots(figsize=(6, 3.5))
        for net, curve in results["training"].items():
            ax.plot([p["step"] for p in curve], [p["l1"] for p in curve], label=net.upper())
        ax.set_xlabel("training step")
        ax.set_ylabel("L1 (normalized actions, log scale)")
        ax.set_yscale("log")
        ax.set_title("Learning curves", fontsize=9)
        ax.legend(fontsize=8)
        fig.tight_layout()
        fig.savefig(out / "learning_curve.png", dpi=120)
        plt.close(fig)
        written.append("learning_curve.png")

    scored = [v for v in results["uncertainty"] if (v, "normal") in cells]
    perturbed = [c for c in cfg.conditions if c != "normal"]
    if scored and perturbed:
        ncols = min(3, len(scored))
        nrows = -(-len(scored) // ncols)
        fig, axes = plt.subplots(nrows, ncols, figsize=(4 * ncols, 4 * nrows), squeeze=False)
        for ax in axes.flat[len(scored) :]:
            ax.set_visible(False)
        for ax, v in zip(axes.flat, scored, strict=False):  # the grid may have spare axes
            clean_max = [max(t) for t in cells[(v, "normal")]["u"]]
            for c in perturbed:
                fpr, tpr = roc_curve(clean_max, [max(t) for t in cells[(v, c)]["u"]])
                ax.plot(fpr, tpr, label=f"{c} ({results['uncertainty'][v]['auroc'][c]['episodes']:.2f})")
            ax.plot([0, 1], [0, 1], "k:", lw=0.8)
            ax.set_title(f"{VARIANTS[v].label}: episode max u", fontsize=9)
            ax.set_xlabel("false-positive rate (clean)")
            ax.set_ylabel("true-positive rate (perturbed)")
            ax.legend(fontsize=7, loc="lower right")
        fig.tight_layout()
        fig.savefig(out / "roc.png", dpi=120)
        plt.close(fig)
        written.append("roc.png")

    if scored:
        v = "vib" if "vib" in scored else scored[0]
        cell = cells[(v, "normal")]
        picks = [
            (label, next((i for i, s in enumerate(cell["success"]) if s == want), None))
            for label, want in (("success", True), ("failure", False))
        ]
        fig, ax = plt.subplots(figsize=(8, 3.5))
        for label, i in picks:
            if i is not None:
                ax.plot(cell["u"][i], label=f"{label} (seed {cell['seeds'][i]})")
        th = results["uncertainty"][v]["thresholds"]
        if th["mean_2std"] is not None:
            ax.axhline(th["mean_2std"], color="k", ls=":", lw=1, label="mean + 2 std")
        if th["conformal"] is not None:
            ax.axhline(th["conformal"], color="r", ls="--", lw=1, label="conformal")
        if th["band"] is not None:
            ax.plot(th["band"], color="r", lw=1, label="time-indexed band")
        ax.set_xlabel("step")
        ax.set_ylabel("u (log scale)")
        ax.set_yscale("log")
        ax.set_title(f"{VARIANTS[v].label}, clean episodes (Fig. 3a/b)", fontsize=9)
        ax.legend(fontsize=7, loc="upper right", bbox_to_anchor=(1.0, 1.0))
        fig.tight_layout()
        fig.savefig(out / "traces.png", dpi=120)
        plt.close(fig)
        written.append("traces.png")
    return written
