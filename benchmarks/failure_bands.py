"""What FAIL-Detect's band changes in the failure monitor that ships, on committed benchmark results.

The failure monitor (`lerobot_vib.failure`) is chosen on validation rollouts among candidates whose threshold
is a constant or a time-varying band. Two bands are offered: the proportional one, tau_t = q b_t, and
FAIL-Detect's, tau_t = mu_t + q s_t (`lerobot_vib.metrics.std_band`). The proportional band's one level q
must cover the largest ratio of any successful episode to the mean at any step, so where clean u spikes (a
grasp) it is wide at every step, and a scene wrong from the first frame (a black camera) alarms only when the
episode outlives the successful ones. The standard-deviation band is tight where clean episodes agree.

For each committed `lerobot-vib-benchmark` output folder (its cells/, validation/, validation_perturbed/ and
choices.json, as committed under benchmarks/results/), the report's failure prediction is run twice on the
same rollouts, once offering the constant threshold and the proportional band only (the candidates of every
report written before the standard-deviation band), once offering both bands; each time the monitor ships by
the report's rule (the earliest on validation among those meeting the TPR, TNR and benign-stop targets there,
else the best balanced accuracy), and its metrics are on the test seeds, which chose nothing. Validation
choose, test report: the rows compare the two candidate sets, not monitors picked on test.

The RND fitted on clean rollouts needs the rollouts' embeddings, which are not committed; it is left out of
both runs alike (it never ships).

    B=benchmarks/results N=benchmarks/results/tokens_narrow
    python benchmarks/failure_bands.py \
        ${N}_2seeds_cpu_2core,${N}_3seeds_cpu_2core,${N}_s3000_cpu_2core:vib_tokens_narrow \
        $B/tokens_act_trunk_2seeds_cpu_2core:vib_tokens_narrow_act_trunk \
        $B/tokens_act_trunk_l3_2seeds_cpu_2core:vib_tokens_narrow_act_trunk_l3 \
        $B/tokens_vib_trunk_l3_s1000_cpu_2core:vib_tokens_narrow_l3 \
        --output benchmarks/results/failure_bands_cpu_2core/report.md
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path
from types import SimpleNamespace

from lerobot_vib.failure import THRESHOLDS
from lerobot_vib.scripts.benchmark import PERTURBED, VALIDATION
from lerobot_vib.scripts.benchmark_report import runtime_of
from lerobot_vib.scripts.failure_report import failure_prediction, margin_lines
from lerobot_vib.sim.perturbations import CONDITIONS

# label: failure_prediction's candidate set; ORs of two at their conformal thresholds, as when this ran first
OFFERED = {
    "constant or proportional band (before)": {
        "thresholds": tuple(t for t in THRESHOLDS if t != "std_band"),
        "or_sizes": (2,),
        "or_margins": (1.0,),
    },
    "and FAIL-Detect's band": {"thresholds": THRESHOLDS, "or_sizes": (2,), "or_margins": (1.0,)},
}
TITLE = "What FAIL-Detect's band changes in the shipped failure monitor"


def load_cells(folder: Path, variant: str) -> tuple[dict, list[int]]:
    """The benchmark's cells of `variant` in a committed folder, keyed as `lerobot-vib-benchmark` keys them."""
    cells: dict = {}
    for path in sorted(folder.glob(f"cells/*/{variant}/seed_*.json")):
        cells[(variant, path.parent.parent.name, int(path.stem.removeprefix("seed_")), None)] = _read(path)
    for path in sorted(folder.glob(f"{VALIDATION}/{variant}/seed_*/*.json")):
        runtime = path.stem.replace("_", ":", 1)  # cell_path wrote "act:0.3+sample" as "act_0.3+sample"
        cells[(variant, VALIDATION, int(path.parent.name.removeprefix("seed_")), runtime)] = _read(path)
    for path in sorted(folder.glob(f"validation_perturbed/*/{variant}/seed_*.json")):
        key = (variant, PERTURBED + path.parent.parent.name, int(path.stem.removeprefix("seed_")), None)
        cells[key] = _read(path)
    if not cells:
        raise SystemExit(f"{folder} holds no cells of {variant!r}.")
    return cells, sorted({k[2] for k in cells})


def _read(path: Path) -> dict:
    cell = json.loads(path.read_text())
    cell.pop("embeddings_file", None)  # never committed: the RND fitted on rollouts is left out (module docstring)
    return cell


def compare(folders: list[Path], variant: str, alpha: float, offered: dict = OFFERED) -> list[dict]:
    """Each of the `offered` candidate sets on the union of `folders`' cells of `variant` (one folder per
    training seed, or one holding them all) with their merged run-time choices."""
    cells, choices = {}, {}
    for folder in folders:
        cells.update(load_cells(folder, variant)[0])
        for v, by_seed in json.loads((folder / "choices.json").read_text()).items():
            choices.setdefault(v, {}).update(by_seed)
    seeds = sorted({k[2] for k in cells})
    conditions = [c for c in CONDITIONS if c in {k[1] for k in cells}]
    cfg = SimpleNamespace(
        variants=[variant], train_seeds=seeds, conditions=conditions, alpha=alpha, rnd_steps=0, failure_alphas=[alpha]
    )
    rows = []
    for label, candidates in offered.items():
        result = failure_prediction(cfg, cells, lambda v, s: runtime_of(choices, v, s), **candidates)
        result = result.get(variant) or {}
        if "shipped" not in result:
            rows.append({"offered": label, "error": result.get("error", "no monitor")})
            continue
        test = result["test"] or {}
        rows.append(
            {
                "offered": label,
                "candidates": result["candidates"],
                "shipped": result["shipped"]["name"],
                "rule": result["shipped"]["rule"],
                "margin": result["shipped"].get("margin", 0.0),
                "margin_cross_validation": result.get("margin_cross_validation") or [],
                "validation": result["shipped"]["validation"],
                "test": test.get("pooled"),
                "per_seed": test.get("per_seed"),
                "per_condition": test.get("per_condition"),
                "benign_stopped": test.get("benign_stopped"),
                "benign_successes": test.get("benign_successes"),
                "validation_episodes": result["validation_episodes"],
            }
        )
    return rows


def _f(x, fmt: str = ".2f") -> str:
    return "-" if x is None else format(x, fmt)


def markdown(
    results: dict, alpha: float, command: str, machine: str, seconds: float, title: str = TITLE, script: str = __file__
) -> str:
    lines = [
        f"# {title}",
        "",
        f"`benchmarks/{Path(script).name}` on committed benchmark results, alpha = {alpha}: the report's failure "
        "prediction run on the same rollouts with two candidate sets, the monitor shipped by the report's rule "
        "(chosen on validation rollouts), its metrics on the test seeds. Failed episodes are the positives, "
        "successful ones (perturbed included) the negatives; detection time is the first alarm's step over the "
        "episode's length in alarmed failures (mean); lead time is the missed grasp's step minus the alarm's "
        "(median). Targets: TPR and TNR >= 0.90, detection time <= 0.30, lead time > 0, benign successes "
        "stopped <= 10%.",
        "",
        f"Command: `{command}` ({seconds / 60:.1f} min on {machine}).",
        "",
    ]
    for (folder, variant), rows in results.items():
        lines += [f"## {variant} ({folder})", ""]
        lines += [
            "| candidates offered | n | shipped monitor (rule) | val TPR / TNR / detection | test TPR | TNR | "
            "detection time | median lead (n) | benign stopped | TPR / TNR per training seed |",
            "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
        ]
        for r in rows:
            if "error" in r:
                lines.append(f"| {r['offered']} | | {r['error']} | | | | | | | |")
                continue
            t, v = r["test"] or {}, r["validation"]
            rule = "earliest meeting the targets" if r["rule"].startswith("the earliest") else "best balanced"
            if r.get("margin"):
                rule += f" with {r['margin']:g} to spare"
            seeds = ", ".join(
                f"{s}: {_f(m.get('tpr'))} / {_f(m.get('tnr'))}" for s, m in sorted((r["per_seed"] or {}).items())
            )
            benign = "-" if r["benign_stopped"] is None else f"{r['benign_stopped']:.2f} of {r['benign_successes']}"
            lines.append(
                f"| {r['offered']} | {r['candidates']} | {r['shipped']} ({rule}) | {_f(v.get('tpr'))} / "
                f"{_f(v.get('tnr'))} / {_f(v.get('detection_time'))} | {_f(t.get('tpr'))} | {_f(t.get('tnr'))} | "
                f"{_f(t.get('detection_time'))} | {_f(t.get('median_lead_time'), '.0f')} "
                f"({t.get('n_lead_times', 0)}) | "
                f"{benign} | {seeds} |"
            )
        lines.append("")
        for r in rows:
            if r.get("margin_cross_validation"):
                lines += [f"{r['offered']}:", *margin_lines(r["margin_cross_validation"], r["margin"]), ""]
        shown = next((r for r in rows if "validation_episodes" in r), None)
        if shown:
            per_seed = ", ".join(f"{s}: {n}" for s, n in sorted(shown["validation_episodes"].items()))
            lines += [
                f"Validation rollouts per training seed (clean, and where the folder has them, under every "
                f"condition): {per_seed}.",
                "",
            ]
        last = rows[-1]
        if last.get("per_condition"):
            lines += [
                f"Per condition, the monitor shipped with the last candidate set ({last['shipped']}):",
                "",
                "| condition | failed / succeeded | TPR | TNR | detection time | median lead (n) |",
                "| --- | --- | --- | --- | --- | --- |",
            ]
            for c, m in last["per_condition"].items():
                lines.append(
                    f"| {c} | {m['n_failed']} / {m['n_succeeded']} | {_f(m.get('tpr'))} | {_f(m.get('tnr'))} | "
                    f"{_f(m.get('detection_time'))} | {_f(m.get('median_lead_time'), '.0f')} "
                    f"({m.get('n_lead_times', 0)}) |"
                )
            lines.append("")
    return "\n".join(lines)


def cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown CPU"


def main(offered: dict = OFFERED, title: str = TITLE, script: str = __file__, doc: str = __doc__) -> None:
    """The command line of this script, and of another that compares its own candidate sets (`offered`)."""
    parser = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    parser.add_argument("rows", nargs="+", help="<benchmark output folder>[,<folder>...]:<variant>")
    parser.add_argument("--alpha", type=float, default=0.1)
    parser.add_argument("--output", type=Path, required=True, help="the report (markdown; results.json beside it)")
    args = parser.parse_args()
    start = time.time()
    results = {}
    for spec in args.rows:
        folder, sep, variant = spec.rpartition(":")
        if not sep or not folder:
            raise SystemExit(f"A row is <folder>[,<folder>...]:<variant>, got {spec!r}.")
        results[(folder, variant)] = compare([Path(f) for f in folder.split(",")], variant, args.alpha, offered)
        shipped = [f"{r['offered']}: {r.get('shipped', r.get('error'))}" for r in results[(folder, variant)]]
        print(f"{variant}: " + "; ".join(shipped))
    args.output.parent.mkdir(parents=True, exist_ok=True)
    machine = f"{cpu_name()}, {os.cpu_count()} CPUs"
    command = f"python benchmarks/{Path(script).name} " + " ".join(args.rows) + f" --output {args.output}"
    args.output.write_text(markdown(results, args.alpha, command, machine, time.time() - start, title, script))
    (args.output.parent / "results.json").write_text(
        json.dumps({f"{f}:{v}": rows for (f, v), rows in results.items()}, indent=1, default=str)
    )
    print(f"Wrote {args.output}")


if __name__ == "__main__":
    main()
