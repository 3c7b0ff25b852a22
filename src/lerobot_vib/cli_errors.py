"""One line instead of a traceback when LeRobot's own commands meet a refusal of this plugin's.

`lerobot-train`, `lerobot-eval` and `lerobot-rollout` import the plugin, then build and load the policy in
their own code, where a `VIBConfigError` (a refusal that names the problem and its fix) or a stop with
nothing safe to hold at an episode's first step (`NothingSafeToHoldError`) would end in a Python traceback. While one
of LeRobot's console scripts runs, such an uncaught error, raised directly or as the cause of another error,
prints as `<command>: <message>` and the command exits with status 1. Every other exception reaches Python's
own hook unchanged.
"""

from __future__ import annotations

import sys
from pathlib import Path
from types import TracebackType

from .configuration_vib import VIBConfigError
from .safety import NothingSafeToHoldError

# What prints as one line: a refusal that names its cause and fix.
REFUSALS = (VIBConfigError, NothingSafeToHoldError)


def refusal_in(error: BaseException | None) -> BaseException | None:
    """The refusal (`REFUSALS`) that `error` is or was caused by, if any."""
    seen = set()
    while error is not None and id(error) not in seen:
        if isinstance(error, REFUSALS):
            return error
        seen.add(id(error))
        error = error.__cause__ or error.__context__
    return None


def install(argv0: str | None = None) -> bool:
    """Install the hook when the running program is one of LeRobot's console scripts; returns whether it was."""
    program = Path(argv0 if argv0 is not None else (sys.argv[0] if sys.argv else "")).name
    if not program.startswith("lerobot-") or getattr(sys.excepthook, "_lerobot_vib", False):
        return False
    previous = sys.excepthook

    def hook(kind: type[BaseException], error: BaseException, tb: TracebackType | None) -> None:
        refusal = refusal_in(error)
        if refusal is None:
            previous(kind, error, tb)
            return
        print(f"{program}: {refusal}", file=sys.stderr)

    hook._lerobot_vib = True  # type: ignore[attr-defined]
    sys.excepthook = hook
    return True
