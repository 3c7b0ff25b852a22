"""Shared by the benchmark scripts: the machine's name and writing a result table."""

from __future__ import annotations

import os
import platform
import sys
from pathlib import Path

PROJECT = Path(__file__).resolve().parents[1]


def cpu_name() -> str:
    """The CPU model and core count, from /proc/cpuinfo where there is one."""
    name = platform.processor() or platform.machine()
    cpuinfo = Path("/proc/cpuinfo")
    if cpuinfo.exists():
        for line in cpuinfo.read_text().splitlines():
            if line.startswith("model name"):
                name = line.split(":", 1)[1].strip()
                break
    return f"{name}, {os.cpu_count()} cores"


def emit(table: str, output: Path | None) -> None:
    """Print the table and, with an output path, write it there."""
    print(table)
    if output:
        output.parent.mkdir(parents=True, exist_ok=True)
        output.write_text(table)


def as_typed(cmd: list[str]) -> str:
    """A command as a user would type it in the project folder: the venv's entry points by name, paths under
    the project relative to it (reports travel; the machine's folders do not)."""
    bin_dir = str(Path(sys.executable).parent) + "/"
    project = str(PROJECT) + "/"
    words = [w[len(bin_dir) :] if w.startswith(bin_dir) else w for w in cmd]
    return " ".join(w.replace(project, "") for w in words)
