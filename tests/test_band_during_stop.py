"""benchmarks/band_during_stop.py: what ended each stop that began under the occluder."""

import importlib.util
import sys
from pathlib import Path

BENCHMARKS = Path(__file__).parents[1] / "benchmarks"
sys.path.insert(0, str(BENCHMARKS))
_spec = importlib.util.spec_from_file_location("band_during_stop", BENCHMARKS / "band_during_stop.py")
band = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(band)


def test_stops_are_read_as_intervals_and_an_unended_one_has_no_end():
    stopped = [False, True, True, False, False, True, True]
    assert band.stops(stopped) == [(1, 3), (5, None)]


def test_a_stop_is_ended_by_the_scene_only_at_or_after_the_board_left():
    board = range(30, 60)
    assert band.classify((32, 66), board) == "scene cleared"
    assert band.classify((32, 60), board) == "scene cleared"
    assert band.classify((32, 57), board) == "clock"  # released while the board was still in view
    assert band.classify((32, None), board) == "never"
    assert band.classify((10, 20), board) is None  # began before the board came: not this question's
