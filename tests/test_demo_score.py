"""benchmarks/demo_score.py: lerobot-vib-eval's files read back as the benchmark's cells."""

import csv
import importlib.util
import json
import sys
from pathlib import Path

BENCHMARKS = Path(__file__).parents[1] / "benchmarks"
sys.path.insert(0, str(BENCHMARKS))
_spec = importlib.util.spec_from_file_location("demo_score", BENCHMARKS / "demo_score.py")
demo_score = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(demo_score)


def test_a_cell_keeps_each_episode_its_own_steps_seed_success_and_every_score(tmp_path):
    episodes = [{"episode_ix": 0, "seed": 7, "success": True}, {"episode_ix": 1, "seed": 8, "success": False}]
    info = {"per_episode": episodes}
    (tmp_path / "uncertainty_info.json").write_text(json.dumps(info))
    fields = ["episode", "seed", "step", "u", "u_rate", "u_embedding_rnd"]
    rows = [  # episodes interleaved, as a batched eval writes them
        (0, 7, 0, 1.0, 0.5, 2.0), (1, 8, 0, 3.0, 0.6, 4.0), (0, 7, 1, 1.5, 0.7, 2.5), (1, 8, 1, 3.5, 0.8, 4.5),
    ]  # fmt: skip
    with (tmp_path / "uncertainty_trace.csv").open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(fields)
        writer.writerows(rows)

    cell = demo_score.cell(tmp_path)

    assert cell["seeds"] == [7, 8] and cell["success"] == [True, False]
    assert cell["u"] == [[1.0, 1.5], [3.0, 3.5]]
    assert cell["scores"] == {"rate": [[0.5, 0.7], [0.6, 0.8]], "embedding_rnd": [[2.0, 2.5], [4.0, 4.5]]}
