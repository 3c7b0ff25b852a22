"""Every score's paired frame AUROC from a benchmark run's saved cells, without rerunning a rollout.

`lerobot-vib-benchmark` writes this table into its report; this script reads it back from the cells of a run
made before the table existed (or whose checkpoint is no longer on disk):

    python benchmarks/score_aurocs.py --cells benchmarks/results/failure_prediction_tokens_2k_cpu_2core/cells \
        --variant vib_tokens --output benchmarks/results/failure_prediction_tokens_2k_cpu_2core/score_aurocs.md
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from lerobot_vib.scripts.benchmark_report import score_auroc_table, score_aurocs


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument(
        "--cells", type=Path, required=True, help="a run's cells/ folder (<condition>/<variant>/seed_<s>.json)"
    )
    p.add_argument("--variant", required=True)
    p.add_argument("--output", type=Path, default=None, help="write the Markdown table here")
    args = p.parse_args()
    conditions = sorted(c.name for c in args.cells.iterdir() if (c / args.variant).is_dir())
    if "normal" not in conditions:
        raise SystemExit(f"{args.cells} has no clean (normal) cells of {args.variant!r}: nothing to pair against.")
    seeds = sorted({f.stem for c in conditions for f in (args.cells / c / args.variant).glob("seed_*.json")})
    every = {}
    for seed in seeds:
        cells = {
            c: json.loads((args.cells / c / args.variant / f"{seed}.json").read_text())
            for c in conditions
            if (args.cells / c / args.variant / f"{seed}.json").exists()
        }
        every[seed.removeprefix("seed_")] = score_aurocs(cells)
    perturbed = [c for c in conditions if c != "normal"]
    lines = [
        f"# Every score's frame AUROC: `{args.variant}`, training seeds {', '.join(every)}",
        "",
        f"Command: `python benchmarks/score_aurocs.py {' '.join(sys.argv[1:])}`",
        *score_auroc_table({args.variant: every}, perturbed),
        "",
    ]
    text = "\n".join(lines)
    print(text)
    if args.output:
        args.output.write_text(text)


if __name__ == "__main__":
    main()
