"""Two rows of `lerobot-vib-benchmark` on the same test episodes, episode by episode.

Every row of a condition is evaluated on the same episode seeds, so each episode of one row has a twin in the
other: same scene, another policy. Only the discordant twins (one solved, the other not) tell the rows apart;
under "neither row is better" each of them falls either way with probability 1/2, and the exact two-sided sign
test (McNemar's, exact) gives the p-value. Cells may come from two output folders, as long as their seeds match.

    python benchmarks/paired_rows.py outputs/token_comparison/cells/normal/vib_tokens/seed_1000.json \
        benchmarks/results/arm_comparison_cpu_2core/cells/normal/act_chosen/seed_1000.json
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path


def sign_test(wins: int, losses: int) -> float:
    """Exact two-sided p of `wins` against `losses` among the discordant pairs, each 1/2 under the null."""
    n, k = wins + losses, min(wins, losses)
    if n == 0:
        return 1.0
    tail = sum(math.comb(n, i) for i in range(k + 1)) / 2**n
    return min(1.0, 2 * tail)


def paired(a: dict, b: dict) -> dict:
    if a["seeds"] != b["seeds"]:
        raise ValueError(
            f"The cells were evaluated on other seeds ({a['seeds'][0]}.. against {b['seeds'][0]}..): no twins."
        )
    only_a = sum(x and not y for x, y in zip(a["success"], b["success"], strict=True))
    only_b = sum(y and not x for x, y in zip(a["success"], b["success"], strict=True))
    return {
        "episodes": len(a["seeds"]),
        "a": sum(a["success"]),
        "b": sum(b["success"]),
        "only_a": only_a,
        "only_b": only_b,
        "p": sign_test(only_a, only_b),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("a", type=Path, help="a cell file (cells/<condition>/<row>/seed_<s>.json)")
    parser.add_argument("b", type=Path, help="the other row's cell on the same condition and seeds")
    args = parser.parse_args()
    a, b = (json.loads(p.read_text()) for p in (args.a, args.b))
    r = paired(a, b)
    print(
        f"{a['condition']}, seeds {a['seeds'][0]}-{a['seeds'][-1]}: {a['variant']} {r['a']}/{r['episodes']}, "
        f"{b['variant']} {r['b']}/{r['episodes']}; solved by {a['variant']} only {r['only_a']}, by {b['variant']} "
        f"only {r['only_b']}; exact sign test on the discordant twins, two-sided p = {r['p']:.3g}"
    )


if __name__ == "__main__":
    main()
