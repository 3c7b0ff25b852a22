"""`lerobot-vib-eval`: LeRobot's `lerobot-eval`, and the VIB policy's uncertainty in every episode.

    lerobot-vib-eval --policy.path=<checkpoint> --env.type=aloha_fast --env.dataset_root=data/tc_120x160 \
        --eval.n_episodes=50 --eval.batch_size=10 [--policy.safety.enabled=true] --output_dir=outputs/eval/vib

The flags are lerobot-eval's and the evaluation is LeRobot's own (`eval_main`: same envs, seeds, success
and `eval_info.json`). Beside `eval_info.json` it writes

  uncertainty_info.json  per episode, in eval_info's order: seed, success, max reward, steps, mean and max u,
                         the steps at which the safety stop fired, how many steps it held and the step at
                         which it became terminal (`halted_at`, safety.max_hold_steps); then the same
                         summed up over all episodes, and over successes and failures apart; and R_bar,
                         the mean rate u was normalized by (`lerobot-vib-calibrate --rollouts` checks it);
                         and the env the rollouts ran in (`env`: type, task, workspace, episode length, image
                         size, cameras, perturbation), which `--rollouts` calibration also checks
  pictures/episode_<i>.png  per episode: what the stop read at every step against the threshold in force, the
                         stopped steps, the first missed grasp, and (token network) the rate map over the
                         image at the episode's step of highest u and at its first stop
  uncertainty_trace.csv  one row per step of every episode: episode, seed, step, rate, u, stopped, just_stopped,
                         and threshold, the stop threshold gamma at that step (a time-indexed band moves it;
                         it stops the policy only with the stop on, `safety_enabled` in uncertainty_info.json),
                         and stop_value, what the stop compared with it (u, or u over the calibrated window),
                         then u_<score> for every score whose training mean is known (an AND's thresholds
                         are set on them: `lerobot-vib-calibrate --rollouts=... --and_scores=[...]`)
  embeddings.safetensors  per episode (`episode_<i>`, in eval_info's order), the observation embedding
                         "embedding_rnd" reads at every step, (steps, D): an RND can be fitted on rollouts
                         (`lerobot-vib-calibrate --rollouts=... --rnd_fit=rollouts`)

Every `select_action` of a VIB policy leaves the step's rate, u and stop decision per env in
`policy.last_step`; this command keeps them while LeRobot's `rollout` runs a batch of envs, then cuts each
env's record at the end of its episode with the rollout's own `done` flags, as LeRobot cuts its rewards.
Steps that an env spends waiting for the rest of its batch are not counted.

The env must show the policy what it was trained on: an env given no `--env.dataset_root` takes the settings of
the checkpoint's training recording where its `train_config.json` names one, and cameras, image size, task or
workspace that differ from the checkpoint's are refused by name before any episode runs (provenance.py).
"""

import csv
import dataclasses
import json
import logging
import math
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any
from unittest import mock

import numpy as np
from lerobot.configs import parser
from lerobot.configs.eval import EvalPipelineConfig
from lerobot.scripts import lerobot_eval
from lerobot.utils.import_utils import register_third_party_plugins
from lerobot.utils.utils import init_logging

from ..configuration_vib import VIBConfigError
from ..provenance import env_record, input_mismatches, recording_mismatches, training_recording
from ..safety import NothingSafeToHoldError
from ..scores import SCORES
from .episode_pictures import write_pictures

logger = logging.getLogger(__name__)

TRACE_FIELDS = ("episode", "seed", "step", "rate", "u", "stopped", "just_stopped", "threshold", "stop_value")


class UncertaintyCapture:
    """Per-episode uncertainty records of every LeRobot `rollout` run inside `capture()`, in rollout order."""

    def __init__(self) -> None:
        self.episodes: list[dict[str, Any]] = []  # {"seed", "gamma", "safety", and per-step arrays}
        self.score_means: dict[str, float] = {}  # each traced score's training mean, its u = s / mean

    @contextmanager
    def capture(self) -> Iterator["UncertaintyCapture"]:
        with mock.patch.object(lerobot_eval, "rollout", self._wrap(lerobot_eval.rollout)):
            yield self

    def _wrap(self, rollout: Callable[..., dict]) -> Callable[..., dict]:
        def recording_rollout(*args: Any, **kwargs: Any) -> dict:
            policy = kwargs["policy"]
            steps: list[dict[str, np.ndarray]] = []
            select_action = policy.select_action

            def select_and_record(batch: dict, **select_kwargs: Any):
                action = select_action(batch, **select_kwargs)
                s = getattr(policy, "last_step", None)
                if s is None:  # a policy without a score (LeRobot's ACT): the steps still count
                    nan, no = np.full(action.shape[0], np.nan), np.zeros(action.shape[0], dtype=bool)
                    steps.append(
                        {
                            "score": None, "score_value": nan, "rate": nan, "u": nan, "stopped": no,
                            "just_stopped": no, "halted": no, "gamma": nan, "safety": False,
                        }
                    )  # fmt: skip
                    return action
                raw = (s.scores or {}).get(s.score, s.rate)
                means = {k: policy.score_mean(k) for k in (s.scores or {})} if hasattr(policy, "score_mean") else {}
                means = {k: m for k, m in means.items() if math.isfinite(m) and m > 0}
                self.score_means.update(means)
                steps.append(
                    {
                        "score": s.score,
                        "score_value": raw.float().cpu().numpy(),
                        "rate": s.rate.float().cpu().numpy(),
                        "u": s.u.float().cpu().numpy(),
                        "stopped": s.stopped.cpu().numpy(),
                        "just_stopped": s.just_stopped.cpu().numpy(),
                        "halted": (s.halted if s.halted is not None else s.stopped & False).cpu().numpy(),
                        "gamma": s.gamma,
                        "thresholds": None if s.thresholds is None else s.thresholds.float().cpu().numpy(),
                        "safety": s.threshold_active,
                        "stop_value": (s.u if s.stop_value is None else s.stop_value).float().cpu().numpy(),
                        "rate_map": None if s.rate_map is None else s.rate_map.float().cpu().numpy(),
                        "embedding": None if s.embedding is None else s.embedding.float().cpu().numpy(),
                        "all_scores": {k: v.float().cpu().numpy() for k, v in (s.scores or {}).items()},
                        "all_u": {k: s.scores[k].float().cpu().numpy() / m for k, m in means.items()},
                    }
                )
                return action

            env = kwargs["env"]
            env_step = env.step
            missed: list[np.ndarray] = []  # per env step: the envs whose gripper closed on nothing (arm_env.py)

            def step_and_record(action):
                out = env_step(action)
                missed.append(_info_flags(out[-1], "grasp_missed", env.num_envs))
                return out

            if kwargs.get("render_callback") is not None:  # LeRobot's video frames get u and the stop drawn on
                kwargs["render_callback"] = _drawing_u(kwargs["render_callback"], steps)
            traced = getattr(policy, "trace_all_scores", None)
            if traced is not None:  # every score at every step: calibration can then set an AND's thresholds
                policy.trace_all_scores = True
            policy.select_action = select_and_record  # instance attributes, removed below
            env.step = step_and_record
            try:
                data = rollout(*args, **kwargs)
            finally:
                del policy.select_action
                del env.step
                if traced is not None:
                    policy.trace_all_scores = traced
            self._add_batch(steps, data["done"].cpu().numpy(), kwargs.get("seeds"), missed)
            return data

        return recording_rollout

    def _add_batch(
        self, steps: list[dict], done: np.ndarray, seeds: list[int] | None, missed: list[np.ndarray] | None = None
    ) -> None:
        if len(steps) != done.shape[1]:
            raise RuntimeError(f"{len(steps)} policy steps for {done.shape[1]} env steps: the record is misaligned.")
        for i in range(done.shape[0]):
            ended = np.flatnonzero(done[i])
            n = int(ended[0]) + 1 if len(ended) else done.shape[1]  # the done step itself belongs to the episode
            missed_steps = np.flatnonzero([m[i] for m in (missed or [])[:n]])
            self.episodes.append(
                {
                    "seed": None if seeds is None else int(seeds[i]),
                    # the first step whose action closed the gripper on nothing; None: never, or not measurable
                    "grasp_missed_at": int(missed_steps[0]) if len(missed_steps) else None,
                    "gamma": steps[0]["gamma"] if steps else float("nan"),
                    "safety": steps[0]["safety"] if steps else False,
                    "score": steps[0].get("score", "rate") if steps else None,
                    # a record without the score's own value is the rate's (every record before the scores)
                    "score_value": np.array([s.get("score_value", s["rate"])[i] for s in steps[:n]]),
                    **{
                        key: np.array([s[key][i] for s in steps[:n]])
                        for key in ("rate", "u", "stopped", "just_stopped")
                    },
                    "halted": np.array([s.get("halted", np.zeros(done.shape[0], dtype=bool))[i] for s in steps[:n]]),
                    # every score's u at every step (each over its training mean), where that mean is known
                    "score_u": {
                        name: np.array([s["all_u"][name][i] for s in steps[:n]])
                        for name in (steps[0].get("all_u") or {} if steps else {})
                        if all(name in s.get("all_u", {}) for s in steps[:n])
                    },
                    # every score the policy computed at every step (VIBPolicy.trace_all_scores), raw values
                    "scores": {
                        name: np.array([s["all_scores"][name][i] for s in steps[:n]])
                        for name in (steps[0].get("all_scores") or {} if steps else {})
                        if all(name in s.get("all_scores", {}) for s in steps[:n])
                    },
                    "stop_value": np.array([s.get("stop_value", s["u"])[i] for s in steps[:n]], dtype=float),
                    # (T, cameras, H', W') the token network's image-token rates at each step, else None
                    "rate_map": np.stack([s["rate_map"][i] for s in steps[:n]])
                    if steps and all(s.get("rate_map") is not None for s in steps[:n])
                    else None,
                    # (T, D) the observation embedding "embedding_rnd" reads, at each step (traced VIB rows only)
                    "embedding": np.stack([s["embedding"][i] for s in steps[:n]])
                    if steps and all(s.get("embedding") is not None for s in steps[:n])
                    else None,
                    "threshold": np.array(
                        [s["gamma"] if s.get("thresholds") is None else s["thresholds"][i] for s in steps[:n]],
                        dtype=float,
                    ),
                }
            )

    def kept(self, n_episodes: int, batch_size: int) -> list[dict[str, Any]]:
        """The episodes LeRobot keeps: per task, the first `n_episodes` of its ceil(n / batch) full batches."""
        per_task = math.ceil(n_episodes / batch_size) * batch_size
        return [
            ep
            for start in range(0, len(self.episodes), per_task)
            for ep in self.episodes[start : start + per_task][:n_episodes]
        ]


def _drawing_u(render_callback: Callable, steps: list[dict]) -> Callable:
    """LeRobot's render callback with each sub-env's frame overlaid by the last policy step's record: what
    the stop read against its threshold, and whether the env is stopped. Async envs render in their workers;
    their frames stay as they are."""

    def render(env) -> None:
        subs = getattr(env, "envs", None)
        if not steps or subs is None:
            return render_callback(env)
        last = steps[-1]
        own = [vars(sub).get("render") for sub in subs]  # a render set on the instance itself, to put back
        for i, sub in enumerate(subs):
            sub.render = lambda i=i, original=sub.render: draw_u(original(), last, i)
        try:
            return render_callback(env)
        finally:
            for sub, render_fn in zip(subs, own, strict=True):
                if render_fn is None:
                    del sub.render
                else:
                    sub.render = render_fn

    return render


def draw_u(frame: np.ndarray, step: dict, i: int) -> np.ndarray:
    """The frame with a band on top: the score, what the stop reads, the threshold in force, STOPPED in red."""
    from PIL import Image, ImageDraw

    if step.get("score") is None:  # a policy without a score
        return frame
    value = float(step.get("stop_value", step["u"])[i])
    threshold = step["gamma"] if step.get("thresholds") is None else float(step["thresholds"][i])
    stopped = bool(step["stopped"][i])
    image = Image.fromarray(np.ascontiguousarray(frame))
    draw = ImageDraw.Draw(image)
    band = max(12, frame.shape[0] // 12)
    draw.rectangle([0, 0, frame.shape[1], band], fill=(150, 0, 0) if stopped else (0, 0, 0))
    text = f"{step['score']} u {value:.2f} / threshold {threshold:.2f}" + ("  STOPPED" if stopped else "")
    draw.text((3, max(band // 2 - 5, 0)), text, fill=(255, 255, 255))
    if threshold and np.isfinite(threshold) and np.isfinite(value):
        width = int(min(value / threshold, 2.0) / 2.0 * frame.shape[1])  # the threshold at half the width
        draw.rectangle([0, band, width, band + 3], fill=(255, 80, 80) if value > threshold else (80, 200, 80))
    return np.asarray(image)


def _info_flags(info: dict, key: str, n_envs: int) -> np.ndarray:
    """A per-env boolean of a vector env's step `info` (False where an env did not report it), also read from
    `final_info` where a sub-env ended at this step."""
    flags = np.zeros(n_envs, dtype=bool)
    for source in (info, info.get("final_info")):
        if isinstance(source, dict) and key in source:
            values = np.asarray(source[key]).reshape(-1)
            mask = np.asarray(source.get(f"_{key}", np.ones(len(values), dtype=bool))).reshape(-1)
            if len(values) == n_envs:
                flags |= values.astype(bool) & mask.astype(bool)
    return flags


def summarize(episodes: list[dict[str, Any]], eval_info: dict) -> dict:
    """uncertainty_info.json: per-episode u and stops beside LeRobot's success, and their aggregates."""
    successes = [s for task in eval_info["per_task"] for s in task["metrics"]["successes"]]
    max_rewards = [r for task in eval_info["per_task"] for r in task["metrics"]["max_rewards"]]
    if len(successes) != len(episodes):
        raise RuntimeError(f"eval_info.json lists {len(successes)} episodes, the uncertainty record {len(episodes)}.")
    per_episode = []
    for i, (ep, success, max_reward) in enumerate(zip(episodes, successes, max_rewards, strict=True)):
        u = ep["u"]
        per_episode.append(
            {
                "episode_ix": i,
                "seed": ep["seed"],
                "success": bool(success),
                "max_reward": float(max_reward),
                "steps": len(u),
                "u_mean": _mean(u),
                "u_max": float(np.max(u)) if len(u) else None,
                "stops": int(ep["just_stopped"].sum()),
                "stop_steps": [int(t) for t in np.flatnonzero(ep["just_stopped"])],
                "stopped_steps": int(ep["stopped"].sum()),
                # the first step of a terminal stop (safety.max_hold_steps): only policy.resume() ends it
                "halted_at": int(np.argmax(ep["halted"])) if ep.get("halted", np.zeros(0)).any() else None,
                "grasp_missed_at": ep.get("grasp_missed_at"),
            }
        )

    def aggregate(rows: list[dict]) -> dict:
        return {
            "n_episodes": len(rows),
            "u_mean": _mean([r["u_mean"] for r in rows if r["u_mean"] is not None]),
            "u_max_mean": _mean([r["u_max"] for r in rows if r["u_max"] is not None]),
            "episodes_with_stop": sum(r["stops"] > 0 for r in rows),
            "stops_per_episode": _mean([r["stops"] for r in rows]),
            "stopped_step_fraction": _ratio(sum(r["stopped_steps"] for r in rows), sum(r["steps"] for r in rows)),
        }

    return {
        "rate_mean": _rate_mean(episodes),
        "score": episodes[0].get("score") if episodes else None,
        "score_mean": _rate_mean(episodes, key="score_value"),
        "gamma": episodes[0]["gamma"] if episodes and math.isfinite(episodes[0]["gamma"]) else None,
        "safety_enabled": bool(episodes[0]["safety"]) if episodes else None,
        "overall": {
            "pc_success": _ratio(100 * sum(r["success"] for r in per_episode), len(per_episode)),
            **aggregate(per_episode),
        },
        "successes": aggregate([r for r in per_episode if r["success"]]),
        "failures": aggregate([r for r in per_episode if not r["success"]]),
        "per_episode": per_episode,
    }


def _rate_mean(episodes: list[dict[str, Any]], key: str = "rate") -> float | None:
    """R_bar the rollouts' u was normalized by (u = R / R_bar): calibrating on these u needs the same R_bar.
    With `key="score_value"`, the mean of the score u was read from, whichever it was."""
    if key == "rate" and episodes and episodes[0].get("score", "rate") not in (None, "rate"):
        return None  # u was another score's: the rate's mean cannot be read off it
    rate = np.concatenate([ep.get(key, ep["rate"]) for ep in episodes]) if episodes else np.zeros(0)
    u = np.concatenate([ep["u"] for ep in episodes]) if episodes else np.zeros(0)
    ok = np.isfinite(rate) & np.isfinite(u) & (u > 0)
    return float(np.median(rate[ok] / u[ok])) if ok.any() else None


def _mean(values) -> float | None:
    """None, not NaN, for no values: NaN is not JSON."""
    return float(np.mean(values)) if len(values) else None


def _ratio(a: float, b: float) -> float | None:
    return a / b if b else None


def _fmt(value: float | None) -> str:
    return "-" if value is None else f"{value:.3f}"


EMBEDDINGS_FILE = "embeddings.safetensors"


def write_embeddings(episodes: list[dict[str, Any]], path: Path) -> bool:
    """Each episode's (steps, D) observation embeddings as `episode_<i>`; nothing written (False) when an episode
    has none (a policy without them, or a record made before they were kept)."""
    from safetensors.numpy import save_file

    if not episodes or any(e.get("embedding") is None for e in episodes):
        return False
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    save_file({f"episode_{i}": np.ascontiguousarray(e["embedding"], dtype=np.float32) for i, e in enumerate(episodes)},
              str(tmp))  # fmt: skip
    tmp.replace(path)  # a file that exists is complete
    return True


def read_embeddings(path: Path, n_episodes: int) -> list[np.ndarray]:
    """What `write_embeddings` wrote, in episode order; a clear error for a file that does not match."""
    from safetensors.numpy import load_file

    if not path.is_file():
        raise FileNotFoundError(
            f"No observation embeddings at {path}: these rollouts were recorded without them (rerun them with this "
            "version's lerobot-vib-eval)."
        )
    arrays = load_file(str(path))
    keys = [f"episode_{i}" for i in range(n_episodes)]
    if sorted(arrays) != sorted(keys):
        raise ValueError(f"{path} holds {len(arrays)} episodes' embeddings, expected {n_episodes} ({keys[0]}..).")
    return [arrays[k] for k in keys]


def write_trace(episodes: list[dict[str, Any]], path: Path) -> None:
    traced = [n for n in SCORES if episodes and all(n in ep.get("score_u", {}) for ep in episodes)]
    with path.open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow([*TRACE_FIELDS, *(f"u_{n}" for n in traced)])
        for i, ep in enumerate(episodes):
            for t in range(len(ep["u"])):
                writer.writerow(
                    [
                        i,
                        ep["seed"],
                        t,
                        f"{ep['rate'][t]:.6g}",
                        f"{ep['u'][t]:.6g}",
                        int(ep["stopped"][t]),
                        int(ep["just_stopped"][t]),
                        f"{ep['threshold'][t]:.6g}" if "threshold" in ep else "",
                        f"{ep['stop_value'][t]:.6g}" if "stop_value" in ep else "",
                        *(f"{ep['score_u'][n][t]:.6g}" for n in traced),
                    ]
                )


def check(cfg: EvalPipelineConfig) -> None:
    if cfg.policy is None or cfg.policy.type != "vib":
        kind = "no policy" if cfg.policy is None else f"a {cfg.policy.type!r} policy"
        raise VIBConfigError(
            f"lerobot-vib-eval reports a VIB policy's uncertainty, but --policy.path gives {kind}; use lerobot-eval."
        )
    if cfg.env.max_parallel_tasks > 1:
        raise VIBConfigError(
            "lerobot-vib-eval matches episodes to eval_info.json in order, so tasks must run one after another: "
            "set --env.max_parallel_tasks=1."
        )
    use_training_recording(cfg)
    record = env_record(cfg.env)
    if problems := input_mismatches(record, cfg.policy):
        raise VIBConfigError(
            f"--env.type={cfg.env.type} gives {' and '.join(problems)}: set --env.dataset_root=<the training "
            "data> (or the env's image and camera flags) so that the env shows the policy what it was trained on."
        )
    recorded = training_recording(cfg.policy.pretrained_path) if cfg.policy.pretrained_path else None
    if recorded is not None and (problems := recording_mismatches(record, recorded[1])):
        raise VIBConfigError(
            f"The env has {' and '.join(problems)}, recorded at {recorded[0]}: evaluate with "
            f"--env.dataset_root={recorded[0]}, or drop the flags that contradict it."
        )


def use_training_recording(cfg: EvalPipelineConfig) -> None:
    """An env that can take its settings from a recording (`--env.dataset_root`) and was given none takes the
    checkpoint's training recording: a policy trained in the `near` workspace is evaluated there, not in the
    env's default. A flag that contradicts the recording is refused by the env config itself."""
    if not hasattr(cfg.env, "dataset_root") or cfg.env.dataset_root is not None or not cfg.policy.pretrained_path:
        return
    recorded = training_recording(cfg.policy.pretrained_path)
    if recorded is None or recording_mismatches({"type": cfg.env.type, "task": None}, recorded[1]):
        return
    cfg.env = dataclasses.replace(cfg.env, dataset_root=str(recorded[0]))
    logger.info("The env takes the settings of the policy's training recording at %s.", recorded[0])


@parser.wrap()
def eval_with_uncertainty(cfg: EvalPipelineConfig) -> dict:
    check(cfg)
    with UncertaintyCapture().capture() as record:
        lerobot_eval.eval_main(cfg)
    out = Path(cfg.output_dir)
    episodes = record.kept(cfg.eval.n_episodes, cfg.eval.batch_size)
    info = summarize(episodes, json.loads((out / "eval_info.json").read_text()))
    info["command"] = " ".join(["lerobot-vib-eval", *sys.argv[1:]])  # the model card cites it
    # What the rollouts ran in: `lerobot-vib-calibrate --rollouts` sets a threshold on clean ones of this policy.
    info["env"] = env_record(cfg.env)
    info["policy_path"] = str(cfg.policy.pretrained_path) if cfg.policy.pretrained_path else None
    info["score_means"] = record.score_means  # what each u_<score> column of the trace was normalized by
    (out / "uncertainty_info.json").write_text(json.dumps(info, indent=2))
    write_trace(episodes, out / "uncertainty_trace.csv")
    write_embeddings(episodes, out / EMBEDDINGS_FILE)
    pictures = write_pictures(episodes, info, out / "pictures")
    o = info["overall"]
    logger.info(
        "Uncertainty over %d episodes: mean u %s, mean max u %s, gamma %s (stop %s); %d episodes with a stop. "
        "Written to %s, one picture per episode in %s",
        o["n_episodes"],
        _fmt(o["u_mean"]),
        _fmt(o["u_max_mean"]),
        _fmt(info["gamma"]),
        "on" if info["safety_enabled"] else "off",
        o["episodes_with_stop"],
        out / "uncertainty_info.json",
        pictures,
    )
    return info


def main() -> None:
    init_logging()
    register_third_party_plugins()
    try:
        eval_with_uncertainty()
    except (VIBConfigError, NothingSafeToHoldError) as e:
        raise SystemExit(f"lerobot-vib-eval: {e}") from None


if __name__ == "__main__":
    main()
