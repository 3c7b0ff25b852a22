"""Every command block of docs/ runs as it is written, page after page in one folder, as a reader pastes them.

Blocks run in the pages' reading order (a page may use what an earlier one recorded or trained) and each in a
shell of its own, so a block never leans on a variable set by another. Each command keeps its flags; the
wrappers below only append flags that make it small (a few training steps, 4-step evaluation episodes in
batches of 2, one ALOHA episode for every 50 asked, 48x64 images where a recording names no size, two rows and
two conditions of a benchmark or of the uncertainty scores) or that this machine needs (no GPU, no ImageNet
weights offline). A block that needs hardware says so in an HTML comment on the line above it,
`<!-- not run by tests/test_docs_commands.py: <why> -->`, and is the only kind left out.

The whole run records 50 arm episodes and four ALOHA ones and starts about 35 commands: 17.5 minutes on the
2-core CPU, too long for every `make test`, so it runs with `LEROBOT_VIB_DOCS=1` (`make test-docs`). The check
that no block holds a placeholder runs always.
"""

from __future__ import annotations

import os
import re
import subprocess
import time
from pathlib import Path

import pytest

from helpers import BIN

ROOT = Path(__file__).parents[1]
# Reading order where pages depend on each other: arm.md records and trains what uncertainty.md calibrates,
# aloha.md trains the transfer-cube checkpoints it reads. Other pages follow alphabetically.
ORDER = ["arm.md", "aloha.md", "uncertainty.md", "benchmark.md"]
NOT_RUN = re.compile(r"<!-- not run by tests/test_docs_commands\.py: (.+?) -->\s*$")
ALOHA_TASKS = ("transfer_cube", "insertion")

WRAPPERS = r"""
small_recording() {  # ALOHA's episodes are 400 steps: one for every 50 asked; 48x64 unless a size is given
  local args=() aloha=0 sized=0
  for a in "$@"; do
    case "$a" in --task=transfer_cube|--task=insertion) aloha=1;; --image_height=*) sized=1;; esac
  done
  for a in "$@"; do
    if [[ $aloha == 1 && "$a" == --num_episodes=* ]]; then
      local n=${a#--num_episodes=}; n=$(( n / 50 )); (( n < 1 )) && n=1; a="--num_episodes=$n"
    fi
    args+=("$a")
  done
  (( sized )) || args+=(--image_height=48 --image_width=64)
  command lerobot-vib-record-sim "${args[@]}"
}
lerobot-vib-record-sim() { small_recording "$@"; }
lerobot-train() { command lerobot-train "$@" --steps=2 --save_freq=2 --batch_size=2 --num_workers=0 --log_freq=1 \
  --policy.device=cpu --policy.pretrained_backbone_weights=null; }
lerobot-vib-calibrate() { command lerobot-vib-calibrate "$@" --rnd_steps=20; }
lerobot-vib-eval() { command lerobot-vib-eval "$@" --env.episode_length=4 --eval.batch_size=2; }
lerobot-eval() { command lerobot-eval "$@" --env.episode_length=4 --eval.batch_size=2; }
lerobot-vib-benchmark() { command lerobot-vib-benchmark "$@" --variants='[vib]' --conditions='[normal,occlusion]' \
  --steps=2 --rnd_steps=20 --n_episodes=2 --n_episodes_other=1 --validation_episodes=2 --alpha=0.5 \
  --eval_batch_size=2 --env.episode_length=4; }
python() {
  case "$1" in
    benchmarks/uncertainty_scores.py) command python "$@" --episodes 1 --episodes_clean 2 --episodes_validation 2 \
      --conditions clean occlusion --rnd_steps 20;;
    *) command python "$@";;
  esac
}
"""


def pages() -> list[Path]:
    docs = sorted((ROOT / "docs").glob("*.md"))
    ranked = {name: i for i, name in enumerate(ORDER)}
    return sorted(docs, key=lambda p: (ranked.get(p.name, len(ORDER)), p.name))


def bash_blocks(page: Path) -> list[tuple[int, str, str | None]]:
    """(line, text, why it is not run or None) of every ```bash block of the page."""
    lines = page.read_text().splitlines()
    blocks, i = [], 0
    while i < len(lines):
        if lines[i].strip() == "```bash":
            end = next(j for j in range(i + 1, len(lines)) if lines[j].strip() == "```")
            above = NOT_RUN.search(lines[i - 1]) if i else None
            blocks.append((i + 1, "\n".join(lines[i + 1 : end]) + "\n", above.group(1) if above else None))
            i = end
        i += 1
    return blocks


def test_every_docs_block_is_runnable_text_or_says_what_hardware_it_needs():
    problems = []
    for page in pages():
        for line, text, why in bash_blocks(page):
            if why is None:
                for bad in re.findall(r"<[a-z][^<>]*>|\[--[^\]]*\]|\.\.\.", text):
                    problems.append(f"{page.name}:{line}: placeholder {bad!r}")
    assert not problems, problems
    assert sum(len(bash_blocks(p)) for p in pages()) >= 10  # the extraction finds the blocks at all


@pytest.mark.slow
@pytest.mark.skipif(os.environ.get("LEROBOT_VIB_DOCS") != "1", reason="18 minutes: LEROBOT_VIB_DOCS=1 (make test-docs)")
def test_every_docs_command_runs_as_pasted_on_tiny_data(tmp_path):
    work = tmp_path / "work"
    work.mkdir()
    for shared in ("configs", "benchmarks", "examples"):
        (work / shared).symlink_to(ROOT / shared)
    env = {**os.environ, "PATH": f"{BIN}:{os.environ['PATH']}", "MUJOCO_GL": "egl", "HF_HUB_OFFLINE": "1"}
    ran, times = [], []
    for page in pages():
        for line, text, why in bash_blocks(page):
            if why is not None:
                continue
            start = time.monotonic()
            proc = subprocess.run(
                ["bash", "-c", f"set -euo pipefail\n{WRAPPERS}\n{text}"],
                cwd=work, capture_output=True, text=True, env=env, timeout=1200,
            )  # fmt: skip
            times.append(f"{page.name}:{line} {time.monotonic() - start:.0f}s")
            assert proc.returncode == 0, f"{page.name}, block at line {line}:\n{(proc.stdout + proc.stderr)[-6000:]}"
            ran.append(f"{page.name}:{line}")
    print("\n".join(times))
    assert len(ran) >= 10
    # what the pages promise is there afterwards
    for produced in (
        "data/arm_near/meta/info.json",
        "outputs/train/vib_arm/checkpoints/last/pretrained_model/config.json",
        "outputs/eval/arm_occlusion/eval_info.json",
        "outputs/train/vib_arm/calibrated_40_10/config.json",
        "outputs/train/vib_cpu/calibrated_on_rollouts/config.json",
        "outputs/scores/floor/report.md",
        "outputs/bench_arm/report.md",
        "outputs/unc/trace.png",
    ):
        assert (work / produced).exists(), produced
