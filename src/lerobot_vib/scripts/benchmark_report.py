"""The benchmark's report: success with Wilson intervals, the uncertainty metrics (metrics.py), and the plots.

Every number comes from the saved cells (`<output_dir>/cells/<condition>/<variant>/seed_<s>.json`, the validation
cells under `validation/`), the choices made on validation (`choices.json`) and the scores' training statistics
(`scores/seed_<s>.json`), so the report can be rebuilt at any time from what is on disk, also from a run that
has not finished (it says which cells it lacks).

Success is given pooled over the training seeds (k/n with a 95% Wilson interval, which counts episodes and so
understates the spread from training) and as the mean and range of the per-seed rates (the spread from
training, over few seeds).
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
from ..configuration_vib import DEFAULT_SCORE
from ..metrics import auroc, roc_curve, std_band, stop_metrics, time_indexed_band, wilson_interval
from ..sim.perturbations import CONDITIONS, draw_scene_episode
from ..variants import CHOSEN, VARIANTS
from . import failure_report

logger = logging.getLogger(__name__)

THRESHOLDS = ("mean_2std", "conformal", "band", "std_band")
# The thresholds a score's offline stop may read, all set on clean validation rollouts.
STOP_THRESHOLDS = ("conformal", "band", "std_band")
# An occlusion stopped this many steps after the occluder's entry or sooner counts as caught in time.
STOP_WITHIN = 5


VALIDATION = "validation"


def success_cell(cell: dict) -> dict:
    return _wilson(sum(cell["success"]), len(cell["success"]))


def _wilson(k: int, n: int) -> dict:
    low, high = wilson_interval(k, n)
    return {"k": k, "n": n, "pc": 100 * k / n, "low": 100 * low, "high": 100 * high}


def success_over_seeds(per_seed: dict[int, dict]) -> dict:
    """Pooled k/n with its Wilson interval, and the mean and range of the per-seed success rates."""
    pooled = _wilson(sum(c["k"] for c in per_seed.values()), sum(c["n"] for c in per_seed.values()))
    rates = [c["pc"] for c in per_seed.values()]
    return {
        **pooled,
        "per_seed": {str(s): c for s, c in per_seed.items()},
        "n_seeds": len(rates),
        "mean_pc": float(np.mean(rates)),
        "min_pc": min(rates),
        "max_pc": max(rates),
    }


def thresholds(calibration: dict, train_gamma: float | None, alpha: float, score: str | None = None) -> dict[str, Any]:
    """gamma of each kind from the clean calibration rollouts of one row (metrics.py), on the u the row recorded
    or, with `score`, on that traced score's u."""
    traces = calibration["u"] if score is None else calibration["scores"][score]
    out: dict[str, Any] = {"mean_2std": train_gamma, "conformal": None, "band": None, "std_band": None, "notes": []}
    needed = conformal_min_scores(alpha)
    if len(traces) >= needed:
        out["conformal"] = conformal_gamma(np.array([max(t) for t in traces]), alpha)
    else:
        out["notes"].append(f"conformal needs {needed} calibration episodes at alpha={alpha}, got {len(traces)}")
    half = len(traces) // 2
    if len(traces) - half >= needed and half >= 1:
        try:
            out["band"] = time_indexed_band(traces[:half], traces[half:], alpha).round(5).tolist()
        except ValueError as e:  # a score that is 0 at some step (chunk disagreement at the first) has no band
            out["notes"].append(f"no band: {e}")
        try:  # FAIL-Detect's band: the same split, its shape from the first half and q from the second
            out["std_band"] = std_band(traces[:half], traces[half:], alpha).round(5).tolist()
        except ValueError as e:
            out["notes"].append(f"no std band: {e}")
    else:
        out["notes"].append(f"the band needs 1 + {needed} calibration episodes at alpha={alpha}, got {len(traces)}")
    return out


def occlusion_onsets(cell: dict) -> list[int | None]:
    return [draw_scene_episode(CONDITIONS["occlusion"], seed).occluded_steps.start for seed in cell["seeds"]]


def score_aurocs(cells: dict[str, dict]) -> dict[str, dict[str, float]]:
    """Every traced score's frame AUROC, clean against each perturbation, on paired frames: the clean and the
    perturbed episode of one seed, at the same steps (both still running; under the occluder only the steps
    it is in view, so that an occluder's frames are not diluted by the clean frames around it). A non-finite
    u counts as higher than every finite one: unknown means stop."""
    clean = cells.get("normal")
    if clean is None or not clean.get("scores"):
        return {}
    by_seed = {seed: i for i, seed in enumerate(clean["seeds"])}
    out: dict[str, dict[str, float]] = {}
    for condition, cell in cells.items():
        if condition == "normal" or not cell.get("scores"):
            continue
        for name, traces in cell["scores"].items():
            if name not in clean["scores"]:
                continue
            neg, pos = [], []
            for j, seed in enumerate(cell["seeds"]):
                if seed not in by_seed:
                    continue
                a, b = clean["scores"][name][by_seed[seed]], traces[j]
                steps = range(min(len(a), len(b)))
                if condition == "occlusion":
                    window = draw_scene_episode(CONDITIONS["occlusion"], seed).occluded_steps
                    steps = [t for t in steps if t in window]
                neg += [a[t] for t in steps]
                pos += [b[t] for t in steps]
            if neg and pos:
                values = np.asarray(neg + pos, dtype=float)
                finite = values[np.isfinite(values)]
                values[~np.isfinite(values)] = (finite.max() + 1.0) if finite.size else 0.0
                out.setdefault(name, {})[condition] = auroc(values[: len(neg)], values[len(neg) :])
    return out


def uncertainty(
    cells: dict[str, dict],
    calibration: dict,
    variant: str,
    conditions: list[str],
    train_gamma: float | None,
    alpha: float,
) -> dict:
    """The metrics of one scored row at one training seed: `cells` its test cells by condition, `calibration`
    its validation cell (clean, at the run time it was tested with), where the thresholds are set."""
    clean = cells.get("normal")
    result: dict[str, Any] = {"score": VARIANTS[variant].score, "auroc": {}, "failure_auroc_clean": None, "stops": {}}
    result["thresholds"] = thresholds(calibration, train_gamma, alpha)
    if clean is None:
        return result
    clean_frames = np.concatenate([np.asarray(t) for t in clean["u"]])
    clean_max = [max(t) for t in clean["u"]]
    for condition in conditions:
        if condition == "normal" or condition not in cells:
            continue
        cell = cells[condition]
        frames = np.concatenate([np.asarray(t) for t in cell["u"]])
        result["auroc"][condition] = {
            "frames": auroc(clean_frames, frames),
            "episodes": auroc(clean_max, [max(t) for t in cell["u"]]),
        }
    failed = [m for m, s in zip(clean_max, clean["success"], strict=True) if not s]
    succeeded = [m for m, s in zip(clean_max, clean["success"], strict=True) if s]
    if failed and succeeded:
        result["failure_auroc_clean"] = auroc(succeeded, failed)
    occluded = cells.get("occlusion")
    for name in THRESHOLDS:
        gamma = result["thresholds"][name]
        if gamma is None:
            continue
        result["stops"][name] = _stop_row(clean, occluded, gamma, None)
    result["score_stops"] = score_stops(cells, calibration, alpha)
    return result


def _stop_row(clean: dict, occluded: dict | None, gamma: float | list[float], score: str | None) -> dict:
    def u(cell: dict) -> list:
        return cell["u"] if score is None else cell["scores"][score]

    false_stops = stop_metrics(u(clean), gamma)
    row: dict[str, Any] = {"clean_episodes": false_stops.n_episodes, "false_stops": false_stops.stopped}
    if occluded is not None:
        occ = stop_metrics(u(occluded), gamma, occlusion_onsets(occluded))
        row.update(
            occlusion_episodes=occ.n_episodes, occlusion_stops=occ.stopped, early_stops=occ.early,
            mean_delay=occ.mean_delay, delays=occ.delays,
            in_time=sum(d <= STOP_WITHIN for d in occ.delays),
        )  # fmt: skip
    return row


def score_stops(cells: dict[str, dict], calibration: dict, alpha: float) -> dict[str, dict]:
    """The stop as each traced score would run it, offline: its conformal threshold and its band set on the
    calibration cell's clean rollouts, judged on the clean and occluded test cells. The policy's stop reads one
    score (its `uncertainty_score`); this says what each would have done in its place."""
    clean, occluded = cells.get("normal"), cells.get("occlusion")
    if clean is None or not calibration.get("scores") or not clean.get("scores"):
        return {}
    out: dict[str, dict] = {}
    for score in calibration["scores"]:
        if score not in clean["scores"] or (occluded is not None and score not in occluded.get("scores", {})):
            continue
        gammas = thresholds(calibration, None, alpha, score)
        out[score] = {
            name: {"gamma": gammas[name], **_stop_row(clean, occluded, gammas[name], score)}
            for name in STOP_THRESHOLDS
            if gammas[name] is not None
        }
    return out


# LeRobot's training log: its progress bar (steps done / steps to do) then the loss line, whose `step:` is
# rounded ("1K").
_LOSS_LINE = re.compile(
    r"(\d+)/(\d+) \[[^\]\n]*\]\s*INFO[^\n]*? step:(\S+) [^\n]*?\bl1_loss:([-+.\de]+)(?:[^\n]*?\brate:([-+.\de]+))?"
)


def training_curve(log_text: str, steps: int | None = None) -> list[dict]:
    """(step, L1, rate) of every loss line in a `lerobot-train` log, sorted by step.

    A resumed training appends to the log and repeats the steps after its checkpoint: the later value wins. Its
    progress bar counts from the checkpoint to the end, so with the training's `steps` a bar of N steps to do
    starts at step `steps - N`. A bar count that disagrees with the line's own rounded step (the bar not yet
    redrawn) is dropped rather than guessed.
    """
    from lerobot.utils.utils import format_big_number

    points: dict[int, dict] = {}
    for m in _LOSS_LINE.finditer(log_text):
        step = int(m.group(1)) + (steps - int(m.group(2)) if steps else 0)
        if format_big_number(step) != m.group(3):
            continue
        points[step] = {
            "step": step,
            "l1": float(m.group(4)),
            "rate": None if m.group(5) is None else float(m.group(5)),
        }
    return [points[k] for k in sorted(points)]


def training_curves(out: Path, steps: int | None = None) -> dict[str, list[dict]]:
    """The loss curves of the networks this benchmark trained (none for given checkpoints), keyed
    "<network> seed <s>"."""
    curves = {}
    for log in sorted((out / "train").glob("*/seed_*.log")):
        curve = training_curve(log.read_text(errors="replace"), steps)
        if curve:
            curves[f"{log.parent.name} seed {log.stem.removeprefix('seed_')}"] = curve
    return curves


def _pct(k: int, n: int) -> str:
    return f"{k}/{n} ({100 * k / n:.0f}%)" if n else "-"


def _num(x: float | None, fmt: str = ".2f") -> str:
    return "-" if x is None else format(x, fmt)


def runtime_of(choices: dict, variant: str, seed: int) -> str | None:
    """The run time a row was tested with at a training seed: chosen on validation, or its own."""
    if VARIANTS[variant].ensemble != CHOSEN:
        return VARIANTS[variant].runtime()
    return choices.get(variant, {}).get(str(seed), {}).get("runtime")


def protocol_flags(cfg, cells: dict, choices: dict, planned: int) -> list[str]:
    """What keeps this report from carrying a claim, each said in one line; empty when nothing does."""
    flags = []
    test = set(cfg.test_seeds())
    for variant, by_seed in choices.items():
        for seed, choice in by_seed.items():
            if shared := test & set(choice.get("validation_seeds") or []):
                flags.append(
                    f"VIOLATION: {VARIANTS[variant].label}'s run time at training seed {seed} was chosen on "
                    f"{len(shared)} test episodes"
                )
    for name in ("vib_checkpoint", "vib_tokens_checkpoint", "act_checkpoint"):
        if getattr(cfg, name, None) is not None:
            flags.append(
                f"--{name} was given: how that checkpoint (and its recipe) was chosen is outside this run and "
                "not checked, beyond its recorded stop threshold"
            )
    if len(cfg.train_seeds) < 3:
        flags.append(f"{len(cfg.train_seeds)} training seed(s): the spread over training is not measured (use 3+)")
    if len(cells) < planned:
        flags.append(f"incomplete: {len(cells)} of {planned} cells evaluated; rerun the command to finish")
    return flags


def write_report(cfg, cells: dict, wall_s: float, planned: int) -> dict:
    """`cells`: (variant, condition, training seed, run time of a validation cell) -> saved cell; `planned`: how
    many cells the run plans (the report flags a run with fewer)."""
    import lerobot
    import torch

    out = Path(cfg.output_dir)
    choices = json.loads((out / "choices.json").read_text()) if (out / "choices.json").exists() else {}
    scores = {
        seed: json.loads(f.read_text())
        for seed in cfg.train_seeds
        if (f := out / "scores" / f"seed_{seed}.json").exists()
    }
    results: dict[str, Any] = {
        "config": json.loads((out / "config.json").read_text()),
        "wall_s": wall_s,
        "invocations": json.loads(wall.read_text()).get("invocations", [])
        if (wall := out / "wall_time.json").exists()
        else [],
        "versions": {"python": platform.python_version(), "torch": torch.__version__, "lerobot": lerobot.__version__},
        "protocol": {
            "train_seeds": list(cfg.train_seeds),
            "validation_seeds": [cfg.validation_seeds()[0], cfg.validation_seeds()[-1]],
            "test_seeds": [cfg.test_seeds()[0], cfg.test_seeds()[-1]],
            "runtimes": list(cfg.runtimes),
            "flags": protocol_flags(cfg, cells, choices, planned),
        },
        "choices": choices,
        "scores": {str(k): v for k, v in scores.items()},
        "success": {},
        "validation": {},
        "uncertainty": {},
        "training": training_curves(out, cfg.steps),
    }
    for v in cfg.variants:
        for c in cfg.conditions:
            per_seed = {s: success_cell(cells[(v, c, s, None)]) for s in cfg.train_seeds if (v, c, s, None) in cells}
            if per_seed:
                results["success"].setdefault(v, {})[c] = success_over_seeds(per_seed)
        for (cv, cc, seed, rt), cell in cells.items():
            if cv == v and cc == VALIDATION:
                results["validation"].setdefault(v, {}).setdefault(str(seed), {})[rt] = success_cell(cell)
        score = VARIANTS[v].score
        if score is None:
            continue
        for seed in cfg.train_seeds:
            calibration = cells.get((v, VALIDATION, seed, runtime_of(choices, v, seed)))
            by_condition = {c: cells[(v, c, seed, None)] for c in cfg.conditions if (v, c, seed, None) in cells}
            if calibration is None or not by_condition:
                continue
            gamma = scores.get(seed, {}).get(score, {}).get("mean_2std")
            u = results["uncertainty"].setdefault(v, {})[str(seed)] = uncertainty(
                by_condition, calibration, v, cfg.conditions, gamma, cfg.alpha
            )
            occluded = cells.get((v, failure_report.PERTURBED + "occlusion", seed, None))
            u["score_choice"] = choose_score_on_validation(calibration, occluded, cfg.alpha)
            if every := score_aurocs(by_condition):
                results.setdefault("score_aurocs", {}).setdefault(v, {})[str(seed)] = every
    results["failure_prediction"] = failure_report.failure_prediction(
        cfg, cells, lambda v, seed: runtime_of(choices, v, seed)
    )
    (out / "results.json").write_text(json.dumps(results, indent=1))
    plots = _plots(cfg, cells, results, out)
    labels = {v: VARIANTS[v].label for v in cfg.variants}
    if results["failure_prediction"]:
        try:
            plots += failure_report.plot(results["failure_prediction"], out, labels)
        except ImportError:
            logger.warning("matplotlib is not installed: no failure prediction plot.")
    (out / "report.md").write_text(_markdown(cfg, results, plots))
    logger.info("Report: %s", out / "report.md")
    return results


def _success_text(s: dict | None) -> str:
    if s is None:
        return "-"
    text = f"{s['k']}/{s['n']} = {s['pc']:.0f}% [{s['low']:.0f}-{s['high']:.0f}]"
    if s["n_seeds"] > 1:
        text += f"; {s['mean_pc']:.0f} ({s['min_pc']:.0f}-{s['max_pc']:.0f})"
    return text


def _wall_time_line(results: dict) -> str:
    line = (
        f"- Wall time: {results['wall_s'] / 60:.1f} min, summed over every invocation (a killed one to its last "
        "beat, <= 30 s)"
    )
    runs = results.get("invocations") or []
    if len(runs) > 1:
        elapsed = max(r["end"] for r in runs) - min(r["start"] for r in runs)
        line += (
            f"; {len(runs)} invocations, side by side at times, so {elapsed / 60:.1f} min from the first start to the "
            "last end"
        )
    return line


def score_auroc_table(every: dict, perturbed: list[str]) -> list[str]:
    """The table of every score's paired frame AUROC: the mean over training seeds, (lowest-highest) with more."""
    if not every:
        return []
    lines = [
        "",
        "## Every score: frame AUROC, clean against perturbed",
        "",
        "Each score the policy traces, on paired frames (the clean and the perturbed episode of one seed at the "
        "same steps; under the occluder only the steps it is in view). Mean over training seeds, "
        "(lowest-highest) with more than one; 0.5 is chance, below 0.5 the score falls.",
        "",
        "| variant, score | " + " | ".join(perturbed) + " |",
        "| --- |" + " --- |" * len(perturbed),
    ]
    for v, by_seed in every.items():
        names = sorted({name for per_score in by_seed.values() for name in per_score})
        for name in names:
            row = []
            for p in perturbed:
                values = [per_score[name][p] for per_score in by_seed.values() if p in per_score.get(name, {})]
                values = [x for x in values if x is not None and np.isfinite(x)]
                if not values:
                    row.append("-")
                elif len(values) == 1:
                    row.append(f"{values[0]:.2f}")
                else:
                    row.append(f"{np.mean(values):.2f} ({min(values):.2f}-{max(values):.2f})")
            lines.append(f"| {VARIANTS[v].label}, `{name}` | " + " | ".join(row) + " |")
    return lines


def _markdown(cfg, results: dict, plots: list[str]) -> str:
    c, p = results["config"], results["protocol"]
    seeds = ", ".join(str(s) for s in p["train_seeds"])
    lines = [
        "# lerobot-vib-benchmark",
        "",
        *[f"- Command: `{command}`" for command in c.get("commands") or [c["command"]]],
        f"- Env: `{c['env_type']}`, dataset `{c['dataset']['repo_id']}`; profile `{cfg.profile}`, "
        f"{cfg.steps} training steps, device `{cfg.device}`",
        f"- Machine: {c['machine']['processor'] or c['machine']['platform']}, {c['machine']['cpus']} CPUs; "
        + ", ".join(f"{k} {v}" for k, v in results["versions"].items()),
        _wall_time_line(results),
        f"- Training seeds: {seeds}: every network is trained once per seed and every cell evaluated per seed.",
        f"- Protocol: every choice (the run time of each row marked *chosen*, among {', '.join(p['runtimes'])}; "
        f"the thresholds) was made on clean validation episodes, seeds {p['validation_seeds'][0]}-"
        f"{p['validation_seeds'][1]}. Every number below is on test seeds {p['test_seeds'][0]}-"
        f"{p['test_seeds'][1]} (the same seeds per condition for every row), which no choice saw.",
    ]
    if p["flags"]:
        lines += ["", "**Limits of this run:**", ""] + [f"- {f}" for f in p["flags"]]
    lines += [
        "",
        "## Success",
        "",
        "Episodes succeeded / evaluated, pooled over the training seeds [95% Wilson interval]; then, with more than "
        "one training seed, the mean success % over the seeds (lowest-highest).",
        "",
        "| variant | " + " | ".join(cfg.conditions) + " |",
        "| --- |" + " --- |" * len(cfg.conditions),
    ]
    for v in cfg.variants:
        row = [_success_text(results["success"].get(v, {}).get(cond)) for cond in cfg.conditions]
        lines.append(f"| {VARIANTS[v].label} | " + " | ".join(row) + " |")
    if "normal" in cfg.conditions and len(cfg.train_seeds) > 1:
        lines += [
            "",
            "Per training seed, normal condition:",
            "",
            "| variant | " + " | ".join(f"seed {s}" for s in cfg.train_seeds) + " |",
            "| --- |" + " --- |" * len(cfg.train_seeds),
        ]
        for v in cfg.variants:
            per_seed = results["success"].get(v, {}).get("normal", {}).get("per_seed", {})
            row = [_pct(x["k"], x["n"]) if (x := per_seed.get(str(s))) else "-" for s in cfg.train_seeds]
            lines.append(f"| {VARIANTS[v].label} | " + " | ".join(row) + " |")
    chosen = [v for v in cfg.variants if VARIANTS[v].ensemble == CHOSEN]
    if chosen:
        lines += [
            "",
            "## Run times chosen on validation",
            "",
            "Successes on the clean validation episodes per candidate; the most wins, a tie goes to the one listed "
            "first.",
            "",
            "| variant | training seed | chosen | " + " | ".join(cfg.runtimes) + " |",
            "| --- | --- | --- |" + " --- |" * len(cfg.runtimes),
        ]
        for v in chosen:
            for seed in cfg.train_seeds:
                val = results["validation"].get(v, {}).get(str(seed), {})
                if not val:
                    continue
                choice = results["choices"].get(v, {}).get(str(seed), {}).get("runtime", "-")
                row = [_pct(x["k"], x["n"]) if (x := val.get(rt)) else "-" for rt in cfg.runtimes]
                lines.append(f"| {VARIANTS[v].label} | {seed} | {choice} | " + " | ".join(row) + " |")
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
                f"| {net} | {first['step']}-{last['step']} | {first['l1']:.3f} (step {first['step']}) | "
                f"{half['l1']:.3f} (step {half['step']}) | {last['l1']:.3f} | {_num(last['rate'])} |"
            )
    if results["uncertainty"]:
        perturbed = [cond for cond in cfg.conditions if cond != "normal"]
        lines += [
            "",
            "## Uncertainty: AUROC of u separating clean (normal) from perturbed rollouts",
            "",
            "u is the paper's rate over its training mean. Frames: every step's u; episodes: each episode's max u. "
            "0.5 is chance. The last column: an episode's max u predicting failure among the clean episodes.",
            "",
            "| variant (score), training seed | "
            + " | ".join(f"{p} frames / episodes" for p in perturbed)
            + " | clean failure |",
            "| --- |" + " --- |" * (len(perturbed) + 1),
        ]
        for v, by_seed in results["uncertainty"].items():
            for seed, u in by_seed.items():
                row = [
                    f"{_num(u['auroc'][p]['frames'])} / {_num(u['auroc'][p]['episodes'])}" if p in u["auroc"] else "-"
                    for p in perturbed
                ]
                lines.append(
                    f"| {VARIANTS[v].label} ({u['score']}), {seed} | "
                    + " | ".join(row)
                    + f" | {_num(u['failure_auroc_clean'])} |"
                )
        lines += score_auroc_table(results.get("score_aurocs", {}), perturbed)
        lines += [
            "",
            f"## The safety stop, judged offline on the recorded u (alpha = {cfg.alpha})",
            "",
            "A rollout stops at its first step with u above the threshold. False stops: clean (normal) episodes "
            "that stop. On occlusion: stops at or after the occluder's entry, stops before it (early, also "
            "false), and the mean delay in steps from entry to stop. Thresholds: the paper's mean + 2 std of "
            "the training frames; split-conformal on the validation rollouts' max u; the time-indexed band; "
            "FAIL-Detect's band (mean + q standard deviations per step).",
            "",
            "| variant, training seed | threshold | gamma | false stops (clean) | occlusion stops | early | "
            "mean delay |",
            "| --- | --- | --- | --- | --- | --- | --- |",
        ]
        for v, by_seed in results["uncertainty"].items():
            for seed, u in by_seed.items():
                label = f"{VARIANTS[v].label}, {seed}"
                for name in THRESHOLDS:
                    gamma, row = u["thresholds"][name], u["stops"].get(name)
                    if row is None:
                        lines.append(f"| {label} | {name} | - | - | - | - | - |")
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
                        f"| {label} | {name} | {shown} | {_pct(row['false_stops'], row['clean_episodes'])} | "
                        + " | ".join(occ)
                        + " |"
                    )
                for note in u["thresholds"]["notes"]:
                    lines.append(f"\n_{label}: {note}._")
        lines += score_stop_table(results["uncertainty"], cfg.alpha)
    if results.get("failure_prediction"):
        labels = {v: VARIANTS[v].label for v in cfg.variants}
        lines += failure_report.markdown(cfg, results["failure_prediction"], labels)
    if plots:
        lines += ["", "## Plots", ""] + [f"![{p}]({p})" for p in plots]
    return "\n".join(lines) + "\n"


def _episodes(cell: dict, part: slice) -> dict:
    """The episodes `part` of a saved cell (its per-episode lists cut alike)."""
    n = len(cell["seeds"])
    out = {k: v[part] if isinstance(v, list) and len(v) == n else v for k, v in cell.items()}
    out["scores"] = {name: traces[part] for name, traces in cell.get("scores", {}).items()}
    return out


def choose_score_on_validation(
    calibration: dict, occluded: dict | None, alpha: float, max_false: float = 0.1
) -> dict | None:
    """The rule that chose the policy's default score (docs/uncertainty.md), on validation rollouts alone: each
    (score, threshold) pair set on the first half of the clean validation rollouts and judged on the other half
    and on the occluded validation rollouts; among the pairs that stop at most `max_false` of those clean
    rollouts, the one that stops the most occlusions in time (ties: fewer clean stops, then the order traced).
    None without occluded validation rollouts."""
    if occluded is None or not calibration.get("scores"):
        return None
    half = len(calibration["seeds"]) // 2
    judged = {"normal": _episodes(calibration, slice(half, None)), "occlusion": occluded}
    candidates = score_stops(judged, _episodes(calibration, slice(None, half)), alpha)
    best = None
    for order, (score, by_threshold) in enumerate(candidates.items()):
        for name, row in by_threshold.items():
            false = row["false_stops"] / max(row["clean_episodes"], 1)
            if false > max_false or "occlusion_episodes" not in row:
                continue
            key = (row["in_time"], -row["false_stops"], -order)
            if best is None or key > best[0]:
                best = (key, score, name, row)
    return {
        "score": best[1] if best else None,
        "threshold": best[2] if best else None,
        "row": best[3] if best else None,
        "n_set": half,
        "n_judged": len(calibration["seeds"]) - half,
        "n_occluded": len(occluded["seeds"]),
    }


def score_stop_table(uncertainty: dict, alpha: float) -> list[str]:
    """The offline stop of every traced score (`score_stops`), and the default score's band against the
    targets: at least 90% of occlusions stopped within STOP_WITHIN steps, at most 5% of clean rollouts."""
    rows = [(v, seed, u["score_stops"]) for v, by_seed in uncertainty.items() for seed, u in by_seed.items()
            if u.get("score_stops")]  # fmt: skip
    if not rows:
        return []
    lines = [
        "",
        f"## The stop with each traced score, judged offline (alpha = {alpha})",
        "",
        "Each score's conformal threshold on the max u, its time-indexed band and FAIL-Detect's standard-deviation "
        "band (std_band), set on the same clean validation rollouts as above. In time: stopped at most "
        f"{STOP_WITHIN} steps after the occluder entered. "
        f"`{DEFAULT_SCORE}` (bold) is the policy's default score; the band is `lerobot-vib-calibrate --rollouts`' "
        "default threshold.",
        "",
        "| variant, training seed | score | threshold | false stops (clean) | occlusion stops | in time | early | "
        "mean delay |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    verdicts = []
    for v, seed, by_score in rows:
        for score, by_threshold in by_score.items():
            shown = f"**{score}**" if score == DEFAULT_SCORE else score
            for name, row in by_threshold.items():
                occ = ["-"] * 4
                if "occlusion_episodes" in row:
                    occ = [
                        _pct(row["occlusion_stops"], row["occlusion_episodes"]),
                        _pct(row["in_time"], row["occlusion_episodes"]),
                        str(row["early_stops"]),
                        _num(row["mean_delay"], ".1f"),
                    ]
                lines.append(
                    f"| {VARIANTS[v].label}, {seed} | {shown} | {name} | "
                    f"{_pct(row['false_stops'], row['clean_episodes'])} | " + " | ".join(occ) + " |"
                )
                if score == DEFAULT_SCORE and name == "band" and "occlusion_episodes" in row:
                    caught = row["in_time"] / max(row["occlusion_episodes"], 1)
                    false = row["false_stops"] / max(row["clean_episodes"], 1)
                    met = caught >= 0.9 and false <= 0.05
                    verdicts.append(
                        f"{VARIANTS[v].label}, seed {seed}: {caught:.0%} of occlusions stopped in time, {false:.0%} "
                        f"of clean rollouts stopped: {'met' if met else 'not met'}"
                    )
    if verdicts:
        lines += ["", f"Target (`{DEFAULT_SCORE}`, band): at least 90% of occlusions in time, at most 5% of clean "
                  "rollouts stopped. " + "; ".join(verdicts) + "."]  # fmt: skip
    chosen = [(v, seed, u["score_choice"]) for v, by_seed in uncertainty.items() for seed, u in by_seed.items()
              if u.get("score_choice")]  # fmt: skip
    if chosen:
        lines += [
            "",
            "The default score's rule on validation rollouts alone (each pair set on half of the clean validation "
            "rollouts, judged on the other half and the occluded validation rollouts; the most occlusions in time "
            "among the pairs that stop at most 10% of those clean rollouts), and what that pair does on the test "
            "seeds above:",
            "",
        ]
        for v, seed, c in chosen:
            if c["score"] is None:
                lines.append(f"- {VARIANTS[v].label}, {seed}: no pair stops at most 10% of the clean rollouts.")
                continue
            row = c["row"]
            test = uncertainty[v][seed]["score_stops"].get(c["score"], {}).get(c["threshold"])
            on_test = (
                f"on test {_pct(test['in_time'], test['occlusion_episodes'])} of occlusions in time, "
                f"{_pct(test['false_stops'], test['clean_episodes'])} clean stopped"
                if test and "occlusion_episodes" in test
                else "not on test"
            )
            lines.append(
                f"- {VARIANTS[v].label}, {seed}: `{c['score']}` with its {c['threshold']} (set on {c['n_set']}, "
                f"judged on {c['n_judged']} clean: {_pct(row['false_stops'], row['clean_episodes'])} stopped, "
                f"{_pct(row['in_time'], row['occlusion_episodes'])} of occlusions in time); {on_test}."
            )
    return lines


def _plots(cfg, cells: dict, results: dict, out: Path) -> list[str]:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        logger.warning("matplotlib is not installed: no plots.")
        return []
    written = []
    rows = [v for v in cfg.variants if v in results["success"]]
    if rows:
        fig, ax = plt.subplots(figsize=(max(6, 1.6 * len(cfg.conditions)), 4))
        width = 0.8 / len(rows)
        for i, v in enumerate(rows):
            x0 = np.arange(len(cfg.conditions)) + (i - (len(rows) - 1) / 2) * width
            present = [(x, results["success"][v][c]) for x, c in zip(x0, cfg.conditions, strict=True)
                       if c in results["success"][v]]  # fmt: skip
            x = np.array([p[0] for p in present])
            s = [p[1] for p in present]
            pc = np.array([c["pc"] for c in s])
            err = np.array([[c["pc"] - c["low"] for c in s], [c["high"] - c["pc"] for c in s]])
            ax.bar(x, pc, width, yerr=err, capsize=2, label=VARIANTS[v].label)
            for xi, c in zip(x, s, strict=True):  # one dot per training seed
                if c["n_seeds"] > 1:
                    rates = [r["pc"] for r in c["per_seed"].values()]
                    ax.plot([xi] * len(rates), rates, ".", ms=4, color="k")
        ax.set_xticks(np.arange(len(cfg.conditions)), cfg.conditions)
        ax.set_ylabel("success % (pooled, 95% Wilson; dots: seeds)")
        ax.set_ylim(0, 100)
        ax.legend(fontsize=7, ncol=2, loc="upper right")
        fig.tight_layout()
        fig.savefig(out / "success.png", dpi=120)
        plt.close(fig)
        written.append("success.png")

    if results["training"]:
        fig, ax = plt.subplots(figsize=(6, 3.5))
        for net, curve in results["training"].items():
            ax.plot([p["step"] for p in curve], [p["l1"] for p in curve], label=net, lw=1)
        ax.set_xlabel("training step")
        ax.set_ylabel("L1 (normalized actions, log scale)")
        ax.set_yscale("log")
        ax.set_title("Learning curves", fontsize=9)
        ax.legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(out / "learning_curve.png", dpi=120)
        plt.close(fig)
        written.append("learning_curve.png")

    # The ROC curves and traces of the first training seed that has them.
    perturbed = [c for c in cfg.conditions if c != "normal"]
    scored = [
        (v, int(seed))
        for v, by_seed in results["uncertainty"].items()
        for seed in list(by_seed)[:1]
        if (v, "normal", int(seed), None) in cells
    ]
    if scored and perturbed:
        ncols = min(3, len(scored))
        nrows = -(-len(scored) // ncols)
        fig, axes = plt.subplots(nrows, ncols, figsize=(4 * ncols, 4 * nrows), squeeze=False)
        for ax in axes.flat[len(scored) :]:
            ax.set_visible(False)
        for ax, (v, seed) in zip(axes.flat, scored, strict=False):  # the grid may have spare axes
            clean_max = [max(t) for t in cells[(v, "normal", seed, None)]["u"]]
            aurocs = results["uncertainty"][v][str(seed)]["auroc"]
            for c in perturbed:
                if (v, c, seed, None) not in cells:
                    continue
                fpr, tpr = roc_curve(clean_max, [max(t) for t in cells[(v, c, seed, None)]["u"]])
                ax.plot(fpr, tpr, label=f"{c} ({aurocs[c]['episodes']:.2f})")
            ax.plot([0, 1], [0, 1], "k:", lw=0.8)
            ax.set_title(f"{VARIANTS[v].label}, seed {seed}: episode max u", fontsize=9)
            ax.set_xlabel("false-positive rate (clean)")
            ax.set_ylabel("true-positive rate (perturbed)")
            ax.legend(fontsize=7, loc="lower right")
        fig.tight_layout()
        fig.savefig(out / "roc.png", dpi=120)
        plt.close(fig)
        written.append("roc.png")

    if scored:
        v, seed = next(((v, s) for v, s in scored if v in ("vib", "vib_chosen")), scored[0])
        cell = cells[(v, "normal", seed, None)]
        picks = [
            (label, next((i for i, s in enumerate(cell["success"]) if s == want), None))
            for label, want in (("success", True), ("failure", False))
        ]
        fig, ax = plt.subplots(figsize=(8, 3.5))
        for label, i in picks:
            if i is not None:
                ax.plot(cell["u"][i], label=f"{label} (seed {cell['seeds'][i]})")
        th = results["uncertainty"][v][str(seed)]["thresholds"]
        if th["mean_2std"] is not None:
            ax.axhline(th["mean_2std"], color="k", ls=":", lw=1, label="mean + 2 std")
        if th["conformal"] is not None:
            ax.axhline(th["conformal"], color="r", ls="--", lw=1, label="conformal")
        if th["band"] is not None:
            ax.plot(th["band"], color="r", lw=1, label="time-indexed band")
        if th.get("std_band") is not None:
            ax.plot(th["std_band"], color="m", lw=1, label="std band (FAIL-Detect)")
        ax.set_xlabel("step")
        ax.set_ylabel("u (log scale)")
        ax.set_yscale("log")
        ax.set_title(f"{VARIANTS[v].label}, training seed {seed}, clean episodes (Fig. 3a/b)", fontsize=9)
        ax.legend(fontsize=7, loc="upper right", bbox_to_anchor=(1.0, 1.0))
        fig.tight_layout()
        fig.savefig(out / "traces.png", dpi=120)
        plt.close(fig)
        written.append("traces.png")
    return written
