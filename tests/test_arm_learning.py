"""benchmarks/arm_learning.py: a checkpoint's training time is the time a trainer ran, resumes included; an
evaluation kept from an earlier run is read back only for the seeds and flags it was made with."""

import importlib.util
import json
import sys
from datetime import datetime
from pathlib import Path
from types import SimpleNamespace

import pytest

_bench = Path(__file__).parents[1] / "benchmarks"
sys.path.insert(0, str(_bench))  # arm_learning imports its sibling `report`
_spec = importlib.util.spec_from_file_location("arm_learning", _bench / "arm_learning.py")
arm_learning = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(arm_learning)


def _t(hms: str) -> float:
    return datetime.strptime(f"2026-11-24 {hms}", "%Y-%m-%d %H:%M:%S").timestamp()


def test_a_resumed_run_is_not_charged_for_the_time_it_was_stopped(tmp_path):
    log = tmp_path / "train.log"
    log.write_text(
        "INFO 2026-11-24 02:00:00 ot_train.py:272 {'batch_size': 16,\n"
        " 'steps': 100}\n"
        "INFO 2026-11-24 02:00:00 ot_train.py:280 Logs will be saved locally.\n"
        "Training:  1%|  | 1/100 [00:01]\rINFO 2026-11-24 02:10:00 ot_train.py:641 step:1K\n"
        "INFO 2026-11-24 02:20:00 ot_train.py:641 step:2K\n"
        # stopped here mid-bar; resumed three hours later
        "Training:  25%|  | 25/100 [20:30]\rINFO 2026-11-24 05:20:00 ot_train.py:272 {'batch_size': 16,\n"
        "INFO 2026-11-24 05:20:00 ot_train.py:280 Logs will be saved locally.\n"
        "INFO 2026-11-24 05:30:00 ot_train.py:641 step:3K\n"
    )
    runs = arm_learning.training_runs(log)
    assert runs == [(_t("02:00:00"), _t("02:20:00")), (_t("05:20:00"), _t("05:30:00"))]
    assert arm_learning.training_seconds(runs, _t("02:15:00")) == 15 * 60
    assert arm_learning.training_seconds(runs, _t("05:25:00")) == 25 * 60
    assert arm_learning.training_seconds(runs, _t("05:31:00")) == 31 * 60  # saved after the last log line
    assert arm_learning.training_seconds(runs, _t("03:00:00")) == 20 * 60  # between runs: nothing ran


def test_a_log_without_timestamps_is_an_error(tmp_path):
    log = tmp_path / "train.log"
    log.write_text("Traceback (most recent call last):\n")
    with pytest.raises(ValueError, match="No timestamp"):
        arm_learning.training_runs(log)


def _args(tmp_path, eval_seed: int):
    return SimpleNamespace(
        out=tmp_path, eval_seed=eval_seed, dataset_root=Path("data/arm"), eval_episodes=50, eval_batch_size=10
    )


def _cached_eval(folder: Path, pc_success: float) -> None:
    folder.mkdir(parents=True)
    (folder / "eval_info.json").write_text(json.dumps({"overall": {"pc_success": pc_success, "n_episodes": 50}}))


def test_an_evaluation_on_other_seeds_is_not_read_from_the_default_seeds_folder(tmp_path):
    default, fresh = _args(tmp_path, arm_learning.DEFAULT_EVAL_SEED), _args(tmp_path, 200000)
    assert arm_learning.eval_dir(default, "vib", "eval_7000") != arm_learning.eval_dir(fresh, "vib", "eval_7000")
    _cached_eval(arm_learning.eval_dir(default, "vib", "eval_7000"), 86.0)
    result = arm_learning.evaluate(Path("ckpt"), default, arm_learning.eval_dir(default, "vib", "eval_7000"))
    assert result == {"success": 43, "n": 50}


def test_a_cached_evaluation_made_with_other_flags_is_an_error(tmp_path):
    args = _args(tmp_path, arm_learning.DEFAULT_EVAL_SEED)
    folder = arm_learning.eval_dir(args, "vib", "eval_7000")
    _cached_eval(folder, 86.0)
    (folder / "eval_command.txt").write_text("lerobot-eval --policy.path=ckpt --seed=5\n")
    with pytest.raises(SystemExit, match="other flags"):
        arm_learning.evaluate(Path("ckpt"), args, folder)
