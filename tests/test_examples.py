"""The examples run: the uncertainty trace of a rollout with an occlusion and the safety stop on."""

import csv
import json
import subprocess
import sys
from pathlib import Path

EXAMPLES = Path(__file__).parents[1] / "examples"


def test_rollout_uncertainty_writes_a_trace_a_summary_and_a_plot(tiny_checkpoint, tmp_path):
    out = tmp_path / "trace"
    proc = subprocess.run(
        [
            sys.executable,
            str(EXAMPLES / "rollout_uncertainty.py"),
            f"--policy_path={tiny_checkpoint}",
            "--steps=12",
            "--occlude=4:8",
            "--safety",
            "--gamma=1e6",
            f"--out={out}",
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    with open(out / "trace.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 12 and {"step", "rate", "u", "gamma", "stopped", "occluded", "reward"} <= set(rows[0])
    assert [r["occluded"] for r in rows] == ["False"] * 4 + ["True"] * 4 + ["False"] * 4
    assert all(float(r["gamma"]) == 1e6 for r in rows)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["safety_enabled"] and summary["stop_intervals"] == []  # gamma = 1e6: never above
    assert summary["mean_u_occluded"] is not None
    assert (out / "trace.png").stat().st_size > 10_000


def test_the_trace_says_what_ended_each_stop():
    import importlib.util

    path = Path(__file__).parents[1] / "examples" / "rollout_uncertainty.py"
    spec = importlib.util.spec_from_file_location("rollout_uncertainty", path)
    example = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(example)
    rows = [{"halted": False} for _ in range(100)]
    board = set(range(30, 60))
    assert "the scene cleared" in example.what_ended(32, 65, rows, board)["ended"]
    assert "still in view" in example.what_ended(32, 56, rows, board)["ended"]
    assert "episode ended" in example.what_ended(32, 99, rows, board)["ended"]
    rows[80]["halted"] = True
    assert example.what_ended(32, 80, rows, board)["ended"].startswith("halted")
