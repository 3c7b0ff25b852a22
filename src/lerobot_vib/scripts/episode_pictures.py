"""One picture per evaluated episode (`lerobot-vib-eval`'s `pictures/`): the stop as a person checks it.

Top: what the stop compared with its threshold at every step (u, or u over the calibrated window), the threshold
in force at that step (a time band moves it), the stopped steps shaded, each stop's first step marked, and the
first missed grasp where the env reports one. Below, for the token network: the rate map (each image cell's
rate) at the episode's step of highest u and at its first stop, so that one can see where the policy's
uncertainty sits in the image.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

logger = logging.getLogger(__name__)


def _key_steps(ep: dict[str, Any]) -> list[tuple[str, int]]:
    value = np.asarray(ep.get("stop_value", ep["u"]), dtype=float)
    keys = []
    if len(value) and np.isfinite(value).any():
        keys.append(("highest u", int(np.nanargmax(value))))
    stops = np.flatnonzero(ep["just_stopped"])
    if len(stops):
        if keys and keys[0][1] == int(stops[0]):
            return [("highest u, first stop", int(stops[0]))]
        keys.append(("first stop", int(stops[0])))
    return keys


def draw_episode(ep: dict[str, Any], row: dict[str, Any], score: str | None, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    maps = ep.get("rate_map")
    keys = _key_steps(ep) if maps is not None else []
    fig = plt.figure(figsize=(8, 5.5 if keys else 3.2))
    grid = fig.add_gridspec(2 if keys else 1, max(len(keys), 1), height_ratios=[1.2, 1] if keys else [1])
    ax = fig.add_subplot(grid[0, :])
    steps = np.arange(len(ep["u"]))
    value = np.asarray(ep.get("stop_value", ep["u"]), dtype=float)
    ax.plot(steps, value, color="tab:blue", lw=1.5, label=f"what the stop reads ({score or 'rate'} / its mean)")
    threshold = np.asarray(ep.get("threshold", []), dtype=float)
    if len(threshold) and np.isfinite(threshold).any():
        ax.step(steps, threshold, where="mid", color="tab:red", lw=1.2, label="threshold in force")
    stopped = np.asarray(ep["stopped"], dtype=bool)
    for t in np.flatnonzero(stopped):
        ax.axvspan(t - 0.5, t + 0.5, color="tab:orange", alpha=0.25, lw=0)
    for t in np.flatnonzero(ep["just_stopped"]):
        ax.axvline(t, color="tab:orange", lw=1.5)
    if ep.get("grasp_missed_at") is not None:
        ax.axvline(ep["grasp_missed_at"], color="k", ls=":", lw=1.2, label="first missed grasp")
    outcome = "solved" if row.get("success") else "failed"
    ax.set(xlabel="episode step", ylabel="u", title=f"episode {row.get('episode_ix')} (seed {row.get('seed')}): "
           f"{outcome}, {row.get('stops', 0)} stop(s); shaded: stopped")  # fmt: skip
    ax.legend(fontsize=7, loc="upper left")
    for j, (label, t) in enumerate(keys):
        sub = fig.add_subplot(grid[1, j])
        image = np.asarray(maps[t])
        image = image[0] if image.ndim == 3 else image  # the first camera
        shown = sub.imshow(image, cmap="inferno")
        sub.set(title=f"rate map, {label} (step {t})", xticks=[], yticks=[])
        fig.colorbar(shown, ax=sub, fraction=0.046)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def write_pictures(episodes: list[dict[str, Any]], info: dict[str, Any], folder: Path) -> Path | None:
    """pictures/episode_<i>.png for every episode; None (and a warning) without matplotlib."""
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        logger.warning("matplotlib is not installed: no episode pictures.")
        return None
    folder.mkdir(parents=True, exist_ok=True)
    for ep, row in zip(episodes, info["per_episode"], strict=True):
        draw_episode(ep, row, info.get("score"), folder / f"episode_{row['episode_ix']}.png")
    return folder
