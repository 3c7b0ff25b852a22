"""The benchmark report's failure prediction (failure.py), from the cells `lerobot-vib-benchmark` saved.

Per scored VIB row whose cells hold every score (`--calibrate=true`):

1. validation: each training seed's validation rollouts at the row's chosen run time, clean and (with
   `--failure_validation`) under every perturbed condition. Every candidate monitor the policy's stop can run
   (failure.candidate_monitors and failure.or_candidates over the scores the cells hold: each score alone, an
   AND with constant partners, an OR with constant partners, at a margin over their conformal thresholds) is
   calibrated on that seed's successful clean
   ones at `alpha` and judged on all of them, averaged over the seeds. What ships (`ship_rule`): among the
   monitors that meet the TPR, TNR and benign-stop targets on validation, the one that alarms earliest in
   failures; with none meeting them, the best balanced accuracy. Balanced accuracy alone does not ask when a
   monitor alarms, and a robot's user asks both whether an episode will fail and how early that is known.
2. test: the shipped monitor, each seed calibrated on its own validation successes, judged on every test
   cell: per condition, per training seed, pooled over conditions and seeds, and at every level of
   `failure_alphas` (the TPR-against-TNR curve). Beside it, for reference: each score alone at one step with
   a constant threshold (the stop as it is), and the best FIPER-like AND (embedding RND and chunk
   disagreement) on validation.

An RND on the policy's observation embedding is measured fitted two ways: on the training frames
("embedding_rnd", as `lerobot-vib-calibrate` fits it) and on clean rollouts ("embedding_rnd_rollouts", FIPER's
way). The second is fitted per training seed on every other successful clean validation rollout of the chosen
run time (the embeddings of those seeds' successful rollouts at every validation run time: the cells'
`*.embeddings.safetensors`); the other successes set its thresholds, and the rollouts it was fitted on neither
set nor judge them (failure.Episode.fitted_on). Its u is e over its mean on the frames it was fitted on.

A training seed whose policy succeeded in fewer clean validation rollouts than a conformal threshold at
`alpha` needs is set aside, by name and with its count: `lerobot-vib-calibrate --rollouts` refuses such a
policy, so no stop ships with it, and its failures are not the monitor's to predict. The numbers then cover
the other seeds, and say so.

Nothing on the test seeds chooses anything.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..calibration import conformal_min_scores
from ..failure import (
    BAND_FLAGS,
    CLEAN,
    THRESHOLDS,
    AnyOf,
    CalibrationError,
    Episode,
    FailureMetrics,
    Monitor,
    calibrate_monitor,
    calibration_episodes,
    candidate_monitors,
    choose_monitor,
    evaluate,
    judge_candidates,
    monitor_from_dict,
    or_candidates,
    rank,
)

VALIDATION = "validation"
PERTURBED = "validation:"  # + a condition: validation rollouts under it (benchmark.PERTURBED)
BENIGN = ("gaussian", "color")  # perturbations the policy mostly handles: a stop there costs success
FIPER_PAIR = ("embedding_rnd", "chunk_disagreement")
# Published figures, on their own tasks and policies (not this arm): what the targets are set against.
PUBLISHED = [
    ("FIPER (Römer et al., NeurIPS 2025), with its conformal guarantee", 0.72, 0.84, 0.47, None),
    ("FIPER, its best setting, no guarantee", 0.92, 0.65, 0.30, None),
    ("FAIL-Detect (Xu et al., RSS 2025), simulation", None, None, None, 0.78),
    ("FAIL-Detect, hardware", None, None, None, 0.72),
]
TARGETS = {"tpr": 0.90, "tnr": 0.90, "detection_time": 0.30, "benign_stopped": 0.10}
ROLLOUT_RND = "embedding_rnd_rollouts"  # the embedding RND fitted on clean validation rollouts
# ORs of two and of three scores, their partners at 1, 2 or 4 times their conformal thresholds (failure.AnyOf)
OR_SIZES, OR_MARGINS = (2, 3), (1.0, 2.0, 4.0)


def cell_episodes(cell: dict) -> list[Episode]:
    """The cell's rollouts as failure.Episode (its `scores`: u per step of every score)."""
    scores = cell.get("scores") or {}
    missed = cell.get("grasp_missed_at") or [None] * len(cell["success"])
    fitted = cell.get("fitted_on") or {}  # score -> the seeds of this cell's rollouts it was fitted on
    return [
        Episode(
            success=bool(ok),
            scores={name: np.asarray(traces[i], dtype=np.float64) for name, traces in scores.items()},
            condition=CLEAN if cell["condition"] == VALIDATION else cell["condition"].removeprefix(PERTURBED),
            failure_moment=missed[i],
            seed=cell["seeds"][i],
            fitted_on=frozenset(name for name, seeds in fitted.items() if cell["seeds"][i] in seeds),
        )
        for i, ok in enumerate(cell["success"])
    ]


def _embeddings(cell: dict) -> list[np.ndarray] | None:
    from .eval_uncertainty import read_embeddings

    path = cell.get("embeddings_file")
    return read_embeddings(Path(path), len(cell["success"])) if path else None


def with_rollout_rnd(cells: dict, variant: str, seed: int, runtime: str, steps: int) -> dict:
    """The cells of (`variant`, training seed `seed`) with ROLLOUT_RND added to their scores (the module
    docstring): fitted on every other successful clean validation rollout at run time `runtime`, by seed. The
    cells are copied; without embeddings (cells recorded before they were kept) they come back as they are."""
    import torch

    from ..scores import EmbeddingRND, fit_embedding_rnd

    own = {k: c for k, c in cells.items() if k[0] == variant and k[2] == seed}
    chosen = own.get((variant, VALIDATION, seed, runtime))
    if chosen is None or not all(c.get("embeddings_file") and c.get("scores") for c in own.values()):
        return own
    successes = [s for s, ok in zip(chosen["seeds"], chosen["success"], strict=True) if ok]
    fit_seeds = set(successes[0::2])
    fit = [
        e
        for (_, condition, _, _), c in own.items()
        if condition == VALIDATION
        for s, ok, e in zip(c["seeds"], c["success"], _embeddings(c), strict=True)
        if ok and s in fit_seeds
    ]
    if len(fit) < 2:
        return own
    frames = torch.from_numpy(np.concatenate(fit)).float()
    rnd = EmbeddingRND(frames.shape[1])
    fit_embedding_rnd(rnd, frames, steps=steps)
    mean = float(rnd.error_mean)
    out = {}
    with torch.no_grad():
        for key, c in own.items():
            u = [np.round(rnd.error(torch.from_numpy(e).float()).double().numpy() / mean, 5) for e in _embeddings(c)]
            out[key] = {**c, "scores": {**c["scores"], ROLLOUT_RND: [x.tolist() for x in u]}}
            if key[1] == VALIDATION:
                out[key]["fitted_on"] = {ROLLOUT_RND: sorted(fit_seeds)}
    return out


def _test_metrics(monitor: Monitor | AnyOf, validation: dict, test: dict, alpha: float) -> dict | None:
    """Per condition and pooled over conditions and seeds; None if a seed cannot be calibrated."""
    calibrated = {}
    for seed, episodes in validation.items():
        try:
            calibrated[seed] = calibrate_monitor(monitor, episodes, alpha)
        except CalibrationError:
            return None
    conditions = sorted({c for by_condition in test.values() for c in by_condition})
    out: dict[str, Any] = {"per_condition": {}, "thresholds": {str(s): c.as_dict() for s, c in calibrated.items()}}
    pooled, benign = [], []
    out["per_seed"] = {
        str(s): _pool([evaluate(calibrated[s], eps) for eps in by_c.values()]).as_dict()
        for s, by_c in test.items()
        if s in calibrated and by_c
    }
    for condition in conditions:
        per = [
            (calibrated[s], eps)
            for s, by_c in test.items()
            if s in calibrated
            for c, eps in by_c.items()
            if c == condition
        ]
        metrics = [evaluate(cal, eps) for cal, eps in per]
        out["per_condition"][condition] = _pool(metrics).as_dict()
        pooled += metrics
        if condition in BENIGN:
            benign += metrics
    out["pooled"] = _pool(pooled).as_dict()
    b = _pool(benign)
    out["benign_stopped"] = b.alarmed_succeeded / b.n_succeeded if b.n_succeeded else None
    out["benign_successes"] = b.n_succeeded
    return out


def uncalibrated_seeds(validation: dict, alpha: float) -> dict[str, dict]:
    """The training seeds whose successful clean validation rollouts are too few for any conformal threshold
    at `alpha` (failure.calibrate_monitor's minimum for one score and a constant threshold), with the counts
    that say why."""
    needed = conformal_min_scores(alpha)
    out = {}
    for seed, episodes in validation.items():
        successes = len(calibration_episodes(episodes))
        if successes < needed:
            clean = sum(e.condition == CLEAN for e in episodes)
            out[str(seed)] = {"successes": successes, "clean": clean, "needed": needed}
    return out


def set_aside_text(uncalibrated: dict[str, dict], alpha: float) -> str:
    """One sentence on the seeds `uncalibrated_seeds` set aside."""
    return (
        "; ".join(
            f"training seed {s} solved {c['successes']} of {c['clean']} clean validation episodes, and a threshold "
            f"at alpha = {alpha} needs {c['needed']} successes"
            for s, c in uncalibrated.items()
        )
        + " (lerobot-vib-calibrate --rollouts refuses such a policy: no stop ships with it)"
    )


def _pool(metrics: list[FailureMetrics]) -> FailureMetrics:
    return FailureMetrics(
        sum(m.n_failed for m in metrics),
        sum(m.n_succeeded for m in metrics),
        sum(m.alarmed_failed for m in metrics),
        sum(m.alarmed_succeeded for m in metrics),
        [t for m in metrics for t in m.detection_times],
        [t for m in metrics for t in m.lead_times],
    )


EARLIEST = "the earliest on validation among those meeting the TPR, TNR and benign-stop targets there"
BEST_BALANCED = "the best balanced accuracy on validation"
# How far inside the targets a monitor must be on validation to ship (TPR and TNR >= 0.9 + m, benign stops
# <= 0.1 - m). The earliest of thousands of candidates that just meet a target on a few hundred rollouts meets
# it by luck as often as not; a margin asks for room. Which margin: `cross_validated_margin`.
SHIP_MARGINS = (0.0, 0.02, 0.05)


def meets_targets(row: dict, margin: float = 0.0) -> bool:
    """Whether a ranking row meets the TPR, TNR and benign-stop targets with `margin` to spare; a row without
    benign rollouts is judged on TPR and TNR alone."""
    benign = row.get("benign_stopped")
    return (
        row["tpr"] >= TARGETS["tpr"] + margin
        and row["tnr"] >= TARGETS["tnr"] + margin
        and (benign is None or benign <= TARGETS["benign_stopped"] - margin)
    )


def earliest_meeting_targets(ranking: list[dict], margin: float = 0.0) -> Monitor | AnyOf | None:
    """Of `choose_monitor`'s rows, the monitor that alarms earliest in failures among those meeting the targets
    on validation with `margin` to spare (ties: the better balanced accuracy, then the order listed); None if
    none does."""
    meets = [r for r in ranking if meets_targets(r, margin)]
    if not meets:
        return None
    return min(meets, key=lambda r: (r["detection_time"], -r["balanced_accuracy"], r["order"]))["monitor"]


def ship_rule(ranking: list[dict], margin: float = 0.0) -> tuple[Monitor | AnyOf, str]:
    """The monitor that ships, from `choose_monitor`'s rows (best balanced accuracy first), and the rule that
    picked it: the earliest of those meeting the targets on validation with `margin` to spare, else the best
    balanced accuracy."""
    earliest = earliest_meeting_targets(ranking, margin)
    if earliest is not None:
        return earliest, EARLIEST
    return ranking[0]["monitor"], BEST_BALANCED


def cross_validated_margin(judged: list[dict], margins: Sequence[float] = SHIP_MARGINS) -> tuple[float, list[dict]]:
    """The ship rule's margin, chosen by leaving one training seed out of the validation rollouts.

    For each margin and each seed g: the rule picks a monitor on the other seeds' validation rollouts, and that
    monitor is judged on g's (calibrated on g's own successful clean rollouts, as it would be shipped there).
    Pooled over the held-out seeds, the margins whose monitors still meet the targets are kept, and the one
    whose monitors alarm earliest wins (a tie: the smaller margin); with none kept, the best held-out balanced
    accuracy. So the margin is what a rule needed to meet the targets on a seed it had not seen, and the test
    seeds choose nothing. With one seed nothing can be held out: the smallest margin, and no rows.
    `judged`: failure.judge_candidates' rows. Returns the margin and one row per margin."""
    groups = list(judged[0]["groups"]) if judged else []
    if len(groups) < 2:
        return margins[0], []
    table = []
    for margin in margins:
        held, held_benign, picked = [], [], {}
        for g in groups:
            ranking = rank(judged, [h for h in groups if h != g])
            if not ranking:
                continue
            monitor, _ = ship_rule(ranking, margin)
            row = next(r for r in judged if r["monitor"] == monitor)
            held.append(row["groups"][g][0])
            held_benign.append(row["groups"][g][1])
            picked[str(g)] = monitor.name
        pooled, benign = _pool(held), _pool(held_benign)
        table.append(
            {
                "margin": margin,
                "picked": picked,
                **{k: v for k, v in pooled.as_dict().items() if k != "median_lead_time"},
                "benign_stopped": None if benign.tnr is None else 1 - benign.tnr,
                "benign_successes": benign.n_succeeded,
            }
        )
    scored = [r for r in table if r["tpr"] is not None and r["tnr"] is not None]
    if not scored:
        return margins[0], table
    kept = [r for r in scored if meets_targets(r)]
    if kept:
        best = min(kept, key=lambda r: (math.inf if r["detection_time"] is None else r["detection_time"], r["margin"]))
    else:
        best = max(scored, key=lambda r: (r["balanced_accuracy"], -r["margin"]))
    return best["margin"], table


def failure_prediction(
    cfg,
    cells: dict,
    runtime_of,
    thresholds: Sequence[str] = THRESHOLDS,
    or_sizes: Sequence[int] = OR_SIZES,
    or_margins: Sequence[float] = OR_MARGINS,
    ship_margins: Sequence[float] = SHIP_MARGINS,
) -> dict:
    """results["failure_prediction"]: per scored row, the validation ranking, the shipped monitor and its test
    metrics. `runtime_of(variant, seed)`: the row's chosen run time at that training seed. `thresholds`: the
    kinds of threshold the candidates may have (failure.THRESHOLDS); `or_sizes`, `or_margins`: the ORs among
    them (failure.or_candidates); `ship_margins`: the margins the ship rule chooses among
    (`cross_validated_margin`)."""
    out = {}
    cells = dict(cells)
    for variant in cfg.variants:
        validation, test = {}, {}
        for seed in cfg.train_seeds:
            cells.update(with_rollout_rnd(cells, variant, seed, runtime_of(variant, seed), cfg.rnd_steps))
            cell = cells.get((variant, VALIDATION, seed, runtime_of(variant, seed)))
            if cell is None or not cell.get("scores"):
                continue
            validation[seed] = cell_episodes(cell) + [
                e
                for c in cfg.conditions
                if (perturbed := cells.get((variant, PERTURBED + c, seed, None))) is not None
                for e in cell_episodes(perturbed)
            ]
            test[seed] = {
                c: cell_episodes(cells[(variant, c, seed, None)])
                for c in cfg.conditions
                if (variant, c, seed, None) in cells and cells[(variant, c, seed, None)].get("scores")
            }
        if not validation or not any(test.values()):
            continue
        uncalibrated = uncalibrated_seeds(validation, cfg.alpha)
        validation = {s: eps for s, eps in validation.items() if str(s) not in uncalibrated}
        test = {s: by_c for s, by_c in test.items() if str(s) not in uncalibrated}
        if not validation:
            out[variant] = {
                "error": "no monitor could be calibrated: " + set_aside_text(uncalibrated, cfg.alpha),
                "uncalibrated_seeds": uncalibrated,
            }
            continue
        names = sorted(set.intersection(*[set(e.scores) for eps in validation.values() for e in eps]))
        candidates = [
            *candidate_monitors(names, thresholds=thresholds),
            *or_candidates(names, thresholds=thresholds, sizes=or_sizes, margins=or_margins),
        ]
        # The policy's stop runs any candidate with a constant threshold on its partners (an AND's or an OR's
        # first score may have a band): `lerobot-vib-calibrate --rollouts --window --and_scores|--or_scores` sets
        # it. The RND fitted on rollouts is measured beside them, not shipped: the policy's stop reads the RND
        # that `lerobot-vib-calibrate` fitted on the training frames.
        runnable = [
            m
            for m in candidates
            if (isinstance(m, AnyOf) or len(m.scores) == 1 or m.threshold == "constant") and ROLLOUT_RND not in m.scores
        ]
        if all(e.success for eps in validation.values() for e in eps):
            out[variant] = {
                "error": "no monitor could be chosen: every validation rollout succeeded, so none shows what a"
                " failure looks like (`--failure_validation=true` adds perturbed validation rollouts)",
                "uncalibrated_seeds": uncalibrated,
            }
            continue
        judged = judge_candidates(runnable, validation, cfg.alpha, benign=BENIGN)
        ranking = rank(judged)
        best = ranking[0]["monitor"] if ranking else None
        if best is None:
            out[variant] = {
                "error": "no monitor could be calibrated on the validation rollouts' successes",
                "uncalibrated_seeds": uncalibrated,
            }
            continue
        margin, margin_table = cross_validated_margin(judged, ship_margins)
        shipped, rule = ship_rule(ranking, margin)
        references = {f"{n} alone": Monitor((n,)) for n in names if Monitor((n,)) != shipped}
        if "low_image_rate" in names:
            references["the stop as shipped today"] = Monitor(("low_image_rate",), threshold="band")
        fiper = [
            r["monitor"]
            for r in ranking
            if isinstance(r["monitor"], Monitor) and set(r["monitor"].scores) == set(FIPER_PAIR)
        ]
        if fiper:
            references["FIPER-like: embedding RND AND chunk disagreement, best on validation"] = fiper[0]
        if best != shipped:
            references[BEST_BALANCED] = best
        ands = [r["monitor"] for r in ranking if isinstance(r["monitor"], Monitor) and len(r["monitor"].scores) > 1]
        if ands and ands[0] not in (shipped, best):
            references["the best AND on validation"] = ands[0]
        if ROLLOUT_RND in names:
            _, on_rollouts = choose_monitor([m for m in candidates if ROLLOUT_RND in m.scores], validation, cfg.alpha)
            if on_rollouts:
                references["best with the RND fitted on clean rollouts, on validation"] = on_rollouts[0]["monitor"]
        result = {
            "validation_seeds": {
                str(s): [e.seed for e in eps][:1] + [e.seed for e in eps][-1:] for s, eps in validation.items()
            },
            "validation_episodes": {str(s): len(eps) for s, eps in validation.items()},
            "validation_successes": {str(s): sum(e.success for e in eps) for s, eps in validation.items()},
            "calibration_episodes": {str(s): len(calibration_episodes(eps)) for s, eps in validation.items()},
            "rollout_rnd_fit_episodes": {
                str(s): sum(ROLLOUT_RND in e.fitted_on for e in eps) for s, eps in validation.items()
            },
            "uncalibrated_seeds": uncalibrated,
            "candidates": len(runnable),
            "or_sizes": list(or_sizes),
            "or_margins": list(or_margins),
            "ranking": [{**r, "monitor": r["monitor"].as_dict(), "name": r["monitor"].name} for r in ranking[:15]],
            "shipped": {
                "monitor": shipped.as_dict(),
                "name": shipped.name,
                "alpha": cfg.alpha,
                "rule": rule,
                "margin": margin,
                "validation": {
                    k: v for r in ranking if r["monitor"] == shipped for k, v in r.items() if k != "monitor"
                },
            },
            "margin_cross_validation": margin_table,
            "test": _test_metrics(shipped, validation, test, cfg.alpha),
            "sweep": {},
            "references": {},
        }
        for label, monitor in {"shipped": shipped, **references}.items():
            if label != "shipped":
                result["references"][label] = {
                    "name": monitor.name,
                    "test": _test_metrics(monitor, validation, test, cfg.alpha),
                }
            result["sweep"][label] = {
                str(a): (m or {}).get("pooled")
                for a in cfg.failure_alphas
                for m in [_test_metrics(monitor, validation, test, a)]
            }
        out[variant] = result
    return out


def ship_command(monitor: Monitor | AnyOf, alpha: float) -> str:
    """The commands that put `monitor` into a checkpoint's stop."""
    m = monitor.members[0] if isinstance(monitor, AnyOf) else monitor
    partners = f" --and_scores='[{','.join(m.scores[1:])}]'" if len(m.scores) > 1 else ""
    if isinstance(monitor, AnyOf):
        others = monitor.members[1:]
        partners += f" --or_scores='[{','.join(o.scores[0] for o in others)}]' --or_window={others[0].window}"
        partners += f" --or_margin={monitor.margin:g}" if monitor.margin != 1 else ""
    return (
        f"To ship it on a checkpoint: evaluate clean rollouts of the calibrated checkpoint with `lerobot-vib-eval "
        f"--policy.uncertainty_score={m.scores[0]}` (the stop off; it records every score's u), then "
        "`lerobot-vib-calibrate --policy.path=<checkpoint> "
        f"--policy.uncertainty_score={m.scores[0]} --rollouts=<their uncertainty_info.json> --conformal_alpha={alpha} "
        f"--threshold={BAND_FLAGS[m.threshold]} --window={m.window} "
        f"--window_aggregate={m.aggregate}{partners} --rollout_episodes=successes`: the policy's stop then runs "
        "this monitor, its thresholds set on the successful rollouts as here."
    )


def _f(x: float | None, fmt: str = ".2f") -> str:
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "-"
    text = format(x, fmt)
    return text[1:] if text.startswith("-") and float(text) == 0 else text  # no "-0"


def shipped_line(result: dict) -> str:
    """The report's first line on failure prediction: what the shipped monitor measured on the test seeds."""
    p = (result.get("test") or {}).get("pooled") or {}
    return (
        f"shipped monitor: TPR {_f(p.get('tpr'))}, TNR {_f(p.get('tnr'))}, detection time "
        f"{_f(p.get('detection_time'))}, median lead time {_f(p.get('median_lead_time'), '.0f')} steps"
    )


def markdown(cfg, failure: dict, labels: dict[str, str]) -> list[str]:
    lines: list[str] = []
    for variant, result in failure.items():
        lines += ["", f"## Failure prediction: {labels.get(variant, variant)}", ""]
        set_aside = result.get("uncalibrated_seeds") or {}
        if "error" in result:
            lines += [result["error"] + "."]
            if set_aside and not result["error"].startswith("no monitor could be calibrated: "):
                lines += ["", "Set aside: " + set_aside_text(set_aside, cfg.alpha) + "."]
            continue
        lines += [shipped_line(result), ""]
        seeds = ", ".join(result["validation_episodes"])
        lines += [
            f"Training seeds {seeds}"
            + (
                f"; set aside: {set_aside_text(set_aside, cfg.alpha)}. Every number below covers the other seeds."
                if set_aside
                else "."
            ),
            "",
        ]
        lines += [ship_command(monitor_from_dict(result["shipped"]["monitor"]), cfg.alpha), ""]
        test = result["test"] or {}
        pooled = test.get("pooled") or {}
        rule = result["shipped"].get("rule", BEST_BALANCED)
        margin = result["shipped"].get("margin", 0.0)
        sizes = " or ".join(map(str, result.get("or_sizes", [2])))
        margins = ", ".join(f"{c:g}" for c in result.get("or_margins", [1]))
        lines += [
            f"The shipped monitor is **{result['shipped']['name']}** at alpha = {cfg.alpha}: among "
            f"{result['candidates']} candidates (each score alone, every AND of two and every OR of {sizes}; "
            "windows 1, 5, 10 steps; mean or sum; a constant threshold or a time-varying band, proportional to the "
            "mean or FAIL-Detect's mean + q standard deviations, the band on the first score only, as the policy's "
            "stop runs them; an OR's k members each at alpha / k, its partners over one window at "
            f"{margins} times their conformal thresholds), "
            + (
                "the one that alarms earliest in failed episodes among those with TPR and TNR >= "
                f"{TARGETS['tpr'] + margin:g} and at most {100 * (TARGETS['benign_stopped'] - margin):g}% of "
                "successful noise and colour-jitter rollouts alarmed"
                + (f" (the targets with a margin of {margin:g}, chosen below)" if margin else "")
                if rule == EARLIEST
                else f"none met TPR and TNR >= {TARGETS['tpr'] + margin:g} with at most "
                f"{100 * (TARGETS['benign_stopped'] - margin):g}% of benign successes alarmed, so the one with "
                "the best balanced accuracy"
            )
            + " on the validation rollouts, clean and under every condition ("
            + ", ".join(
                f"seed {s}: {result['validation_successes'][s]} successes of {n}, "
                f"{result['calibration_episodes'][s]} of them clean"
                for s, n in result["validation_episodes"].items()
            )
            + "), each seed's thresholds set by split-conformal prediction on its own successful clean validation "
            "rollouts only (with n of them the constant threshold is the ceil((n + 1)(1 - alpha))-th largest "
            "maximum; a band needs twice the conformal minimum). Every number below is on the test seeds, which "
            "nothing chose on. Failed episodes are the positives, successful ones (perturbed ones included) the "
            "negatives; the failure moment is the first missed grasp (the gripper closed on nothing), where one "
            "happened.",
            "",
            "| condition | failed / succeeded | TPR | TNR | accuracy | balanced accuracy | detection time | "
            "median lead time (steps, n) |",
            "| --- | --- | --- | --- | --- | --- | --- | --- |",
        ]
        for condition, m in [*test.get("per_condition", {}).items(), ("**pooled**", pooled)]:
            lines.append(
                f"| {condition} | {m['n_failed']} / {m['n_succeeded']} | {_f(m['tpr'])} | {_f(m['tnr'])} | "
                f"{_f(m['accuracy'])} | {_f(m['balanced_accuracy'])} | {_f(m['detection_time'])} | "
                f"{_f(m['median_lead_time'], '.0f')} ({m['n_lead_times']}) |"
            )
        benign = test.get("benign_stopped")
        lines += [
            "",
            f"Successful noise and colour-jitter episodes stopped: {_f(benign)} of {test.get('benign_successes', 0)}.",
            "",
            "Per training seed, pooled over conditions (each seed's thresholds from its own validation successes):",
            "",
            "| training seed | failed / succeeded | TPR | TNR | balanced accuracy | detection time | "
            "median lead time (steps, n) |",
            "| --- | --- | --- | --- | --- | --- | --- |",
            *[
                f"| {s} | {m['n_failed']} / {m['n_succeeded']} | {_f(m['tpr'])} | {_f(m['tnr'])} | "
                f"{_f(m['balanced_accuracy'])} | {_f(m['detection_time'])} | "
                f"{_f(m['median_lead_time'], '.0f')} ({m['n_lead_times']}) |"
                for s, m in test.get("per_seed", {}).items()
            ],
            "",
            "Against the published figures (their tasks and policies, not this arm, so a frame of reference rather "
            "than a like-for-like comparison), and the targets:",
            "",
            "| monitor | TPR | TNR | detection time | balanced accuracy |",
            "| --- | --- | --- | --- | --- |",
            f"| this row's shipped monitor, alpha = {cfg.alpha}, pooled | {_f(pooled.get('tpr'))} | "
            f"{_f(pooled.get('tnr'))} | {_f(pooled.get('detection_time'))} | {_f(pooled.get('balanced_accuracy'))} |",
        ]
        for label, ref in result["references"].items():
            p = ((ref.get("test") or {}).get("pooled")) or {}
            lines.append(
                f"| {label}: {ref['name']} | {_f(p.get('tpr'))} | {_f(p.get('tnr'))} | "
                f"{_f(p.get('detection_time'))} | {_f(p.get('balanced_accuracy'))} |"
            )
        for label, tpr, tnr, det, bacc in PUBLISHED:
            lines.append(f"| {label} | {_f(tpr)} | {_f(tnr)} | {_f(det)} | {_f(bacc)} |")
        if fitted := {s: n for s, n in (result.get("rollout_rnd_fit_episodes") or {}).items() if n}:
            lines += [
                "",
                f"`{ROLLOUT_RND}` is the embedding RND fitted on clean rollouts instead of the training frames: per "
                "training seed on every other successful clean validation rollout ("
                + ", ".join(f"seed {s}: {n}" for s, n in fitted.items())
                + "), the rest setting its thresholds. It is measured here and not shipped: the policy's stop "
                "reads the RND that `lerobot-vib-calibrate` fits on the training frames (`embedding_rnd`).",
            ]
        if any(ref.get("test") is None for ref in result["references"].values()):
            lines += ["", "A row of dashes could not be calibrated: too few successful clean validation rollouts."]
        met = _targets(test)
        lines += ["", "Targets (alpha = " + str(cfg.alpha) + ", pooled, test seeds): " + "; ".join(met) + "."]
        lines += [
            "",
            "Validation: the shipped monitor, then the first 15 candidates by balanced accuracy (averaged over the "
            "seeds):",
            "",
            "| monitor | balanced accuracy | TPR | TNR | detection time | benign successes alarmed |",
            "| --- | --- | --- | --- | --- | --- |",
        ]
        shipped_row = result["shipped"].get("validation")
        ranked = [*([{**shipped_row, "name": "shipped: " + result["shipped"]["name"]}] if shipped_row else [])]
        for r in [*ranked, *result["ranking"]]:
            lines.append(
                f"| {r['name']} | {_f(r['balanced_accuracy'])} | {_f(r['tpr'])} | {_f(r['tnr'])} | "
                f"{_f(r['detection_time'] if math.isfinite(r['detection_time']) else None)} | "
                f"{_f(r.get('benign_stopped'))} |"
            )
        lines += margin_lines(result.get("margin_cross_validation") or [], margin)
    return lines


def margin_lines(table: list[dict], chosen: float) -> list[str]:
    """The ship rule's margins as `cross_validated_margin` judged them, on held-out training seeds."""
    if not table:
        return []
    lines = [
        "",
        "The ship rule's margin, chosen by leaving one training seed out: for each seed, the rule with that margin "
        "picks a monitor on the other seeds' validation rollouts, judged on the held-out seed's (calibrated on "
        "its own successful clean rollouts); pooled over the held-out seeds, the earliest margin whose picks meet "
        "the targets ships (none meeting them: the best balanced accuracy):",
        "",
        "| margin | held-out TPR | TNR | detection time | benign successes alarmed | picked, per held-out seed |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for m in table:
        picked = "; ".join(f"{s}: {name}" for s, name in m["picked"].items())
        mark = " (shipped)" if m["margin"] == chosen else ""
        lines.append(
            f"| {m['margin']:g}{mark} | {_f(m['tpr'])} | {_f(m['tnr'])} | {_f(m['detection_time'])} | "
            f"{_f(m['benign_stopped'])} of {m['benign_successes']} | {picked} |"
        )
    return lines


def _targets(test: dict) -> list[str]:
    pooled = test.get("pooled") or {}
    checks = [
        ("TPR >= 0.90", pooled.get("tpr"), lambda x: x >= TARGETS["tpr"]),
        ("TNR >= 0.90", pooled.get("tnr"), lambda x: x >= TARGETS["tnr"]),
        ("detection time <= 0.30", pooled.get("detection_time"), lambda x: x <= TARGETS["detection_time"]),
        ("median lead time > 0", pooled.get("median_lead_time"), lambda x: x > 0),
        ("benign successes stopped <= 10%", test.get("benign_stopped"), lambda x: x <= TARGETS["benign_stopped"]),
    ]
    # three decimals: a rate just under its target must not print as the target itself
    return [f"{name}: {'met' if v is not None and ok(v) else 'not met'} ({_f(v, '.3f')})" for name, v, ok in checks]


def plot(failure: dict, out: Path, labels: dict[str, str]) -> list[str]:
    """failure_roc.png: pooled test TPR against TNR as alpha sweeps, one line per monitor."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [(v, r) for v, r in failure.items() if "sweep" in r]
    if not rows:
        return []
    fig, axes = plt.subplots(1, len(rows), figsize=(6 * len(rows), 5), squeeze=False)
    for ax, (variant, result) in zip(axes[0], rows, strict=True):
        for label, by_alpha in result["sweep"].items():
            points = [
                (p["tnr"], p["tpr"]) for p in by_alpha.values() if p and p["tnr"] is not None and p["tpr"] is not None
            ]
            if points:
                x, y = zip(*points, strict=True)
                name = result["shipped"]["name"] if label == "shipped" else result["references"][label]["name"]
                ax.plot(
                    x,
                    y,
                    "o-" if label == "shipped" else ".--",
                    label=("shipped: " if label == "shipped" else "") + name,
                    lw=2 if label == "shipped" else 1,
                )
        ax.plot([0.84], [0.72], "k*", ms=12, label="FIPER, published (its tasks)")
        ax.set(
            xlabel="TNR (successes not alarmed)",
            ylabel="TPR (failures alarmed)",
            xlim=(0, 1.02),
            ylim=(0, 1.02),
            title=f"{labels.get(variant, variant)}: alpha swept",
        )
        ax.legend(fontsize=6, loc="lower left")
    fig.tight_layout()
    fig.savefig(out / "failure_roc.png", dpi=120)
    plt.close(fig)
    return ["failure_roc.png"]
