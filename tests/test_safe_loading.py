"""No file the project reads can run code: every torch.load reads tensors only, no array file needs pickle."""

import ast
import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).parents[1]
SCANNED = ("src", "benchmarks", "examples", "scripts")


def _load_module(name: str, path: Path):
    if str(path.parent) not in sys.path:  # the benchmarks import their siblings
        sys.path.insert(0, str(path.parent))
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _dotted(node: ast.AST) -> str:
    if isinstance(node, ast.Attribute):
        return f"{_dotted(node.value)}.{node.attr}"
    return node.id if isinstance(node, ast.Name) else ""


def _keyword(call: ast.Call, name: str):
    for kw in call.keywords:
        if kw.arg == name:
            return kw.value.value if isinstance(kw.value, ast.Constant) else "not a constant"
    return None


def _unpickles(name: str, call: ast.Call) -> bool:
    if name.split(".")[0] in ("pickle", "cloudpickle", "dill", "joblib") and name.endswith(("load", "loads")):
        return True
    return name in ("yaml.unsafe_load", "yaml.full_load") or (name == "yaml.load" and not call.keywords)


def unsafe_loads(source: str) -> list[tuple[int, str]]:
    """(line, call) of every load in `source` that could unpickle: torch.load without weights_only=True,
    numpy's load with allow_pickle=True, pickle and its relatives, yaml.load / yaml.unsafe_load."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if not isinstance(node, ast.Call):
            continue
        name = _dotted(node.func)
        if name == "torch.load" and _keyword(node, "weights_only") is not True:
            found.append((node.lineno, f"{name} without weights_only=True"))
        elif name in ("np.load", "numpy.load") and _keyword(node, "allow_pickle") not in (None, False):
            found.append((node.lineno, f"{name} with allow_pickle"))
        elif _unpickles(name, node):
            found.append((node.lineno, name))
    return found


@pytest.mark.parametrize(
    "source",
    [
        "import torch\ntorch.load('x.pt')",
        "import torch\ntorch.load('x.pt', weights_only=False)",
        "import numpy as np\nnp.load('x.npz', allow_pickle=True)",
        "import pickle\npickle.load(open('x', 'rb'))",
    ],
)
def test_the_scan_finds_an_unsafe_load(source):
    assert unsafe_loads(source)


def test_no_unsafe_load_under_src_benchmarks_examples_and_scripts():
    found = [
        f"{path.relative_to(ROOT)}:{line}: {what}"
        for top in SCANNED
        for path in sorted((ROOT / top).rglob("*.py"))
        for line, what in unsafe_loads(path.read_text())
    ]
    assert not found, "loads that can run code from a file:\n" + "\n".join(found)


class _Payload:
    """Unpickling it would write a file: the proof that loading ran code."""

    target: Path

    def __reduce__(self):
        return (Path.write_text, (self.target, "ran"))


def test_a_crafted_score_file_is_refused_without_running_its_payload(tmp_path):
    scores = _load_module("uncertainty_scores", ROOT / "benchmarks" / "uncertainty_scores.py")
    payload = _Payload()
    payload.target = tmp_path / "ran.txt"
    crafted = tmp_path / "clean.npz"
    np.savez(crafted, rate=np.asarray([payload, payload], dtype=object))
    with pytest.raises(SystemExit, match="pickle"):
        scores._read_cell(crafted)
    assert not payload.target.exists()


def test_episodes_of_different_lengths_round_trip_without_pickle(tmp_path):
    scores = _load_module("uncertainty_scores", ROOT / "benchmarks" / "uncertainty_scores.py")
    episodes = [np.array([1.0, 2.0, 3.0]), np.array([4.0]), np.array([5.0, 6.0])]
    path = tmp_path / "cell.npz"
    np.savez(path, seeds=np.arange(3), **scores._ragged_to_arrays("rate", episodes))
    cell = scores._read_cell(path)
    assert [e.tolist() for e in cell["rate"]] == [e.tolist() for e in episodes]
    assert cell["seeds"].tolist() == [0, 1, 2]
