"""The model card of a VIB checkpoint: LeRobot's card, told what the policy is and what was measured.

LeRobot writes its card from a template (`PreTrainedPolicy.generate_model_card`). On top of it:

1. its generic first line becomes what VIB is and how the plugin is installed (it is on no registry);
2. the evaluation table and the Hub's evaluation results (`eval_results`) get the success measured on the
   rollouts gamma was set on, where a calibration recorded one;
3. a section says how uncertain the policy is allowed to be: the data, the score, R_bar, gamma and how it was
   set, the stop's settings, and the failure-prediction figures of its monitor.
"""

from __future__ import annotations

from huggingface_hub import EvalResult, ModelCard

MODEL_CARD_INTRO = """\
**VIB** (Variational Information Bottleneck) is an ACT-style action-chunking policy whose observation \
encoding passes through an Information Bottleneck; its *rate*, KL(p(z|s) || m(z)), is an epistemic-uncertainty \
score available at run time (Uncertainty-Guided Robotic Manipulation Through Variational Information \
Bottleneck in Imitation Learning, VIB-ILCtrl).

The policy type comes from the LeRobot plugin `lerobot_policy_vib` (the lerobot-vib project), which is not on \
PyPI: install it from its source next to LeRobot (`pip install -e .` in a checkout of lerobot-vib) before \
`lerobot-eval` / `lerobot-rollout` / `--policy.path=...` can load it."""

# LeRobot's card template says this until someone fills its table in.
NO_EVALUATION = "_No evaluation results have been provided for this policy yet._"


def vib_model_card(card: ModelCard, config, rate_mean: float, dataset: str | None = None) -> ModelCard:
    """LeRobot's `card` of a VIB policy, rewritten in place as the module docstring says; `config`: its
    VIBConfig, `rate_mean`: the R_bar it acts with, `dataset`: its training data's repo id."""
    generic = "This is a **vib** policy trained with [LeRobot](https://github.com/huggingface/lerobot)."
    if generic in card.text:
        card.text = card.text.replace(generic, MODEL_CARD_INTRO)
    else:
        card.text = MODEL_CARD_INTRO + "\n\n" + card.text
    card.data.tags = sorted(set(card.data.tags or []) | {"vib", "uncertainty"})
    measured = measured_success(config.calibration)
    if measured is not None:  # LeRobot's table, and the Hub's evaluation results, from what was measured
        trials, successes, where = measured
        table = (
            "| Task | Trials | Successes | Success rate |\n| ---- | ------ | --------- | ------------ |\n"
            f"| {where} | {trials} | {successes} | {100 * successes / trials:.0f}% |"
        )
        card.text = card.text.replace(NO_EVALUATION, table)
        card.data.model_name = card.data.model_name or config.repo_id or "vib"
        card.data.eval_results = [
            EvalResult(
                task_type="robotics",
                dataset_type=dataset or config.calibration.dataset_repo_id or "unknown",
                dataset_name=where,
                metric_type="success_rate",
                metric_value=round(successes / trials, 4),
            )
        ]
    card.text = card.text.rstrip("\n") + "\n\n" + describe_calibration(config, rate_mean, dataset)
    return card


_GAMMA_METHODS = {
    "mean_plus_2std": "mean + 2 std of u over the calibration frames (the paper's rule)",
    "conformal": "split-conformal on the maximum u of {n} held-out dataset episodes at alpha = {alpha}",
    "conformal_rollouts": "split-conformal on the maximum u of {n} clean rollouts at alpha = {alpha}: at most "
    "that share of clean rollouts should stop",
    "time_band_rollouts": "a time-indexed band (one threshold per episode step) from {n} clean rollouts at "
    "alpha = {alpha}; gamma is its largest value",
    "std_band_rollouts": "a time-indexed band (mean + q standard deviations of u per episode step) from {n} "
    "clean rollouts at alpha = {alpha}; gamma is its largest value",
}


def measured_success(calibration) -> tuple[int, int, str] | None:
    """(trials, successes, what was run) of the clean rollouts a checkpoint's gamma was set on, if recorded."""
    c = calibration
    if c.rollout_successes is None or not c.rollout_seeds:
        return None
    seeds = f"seeds {min(c.rollout_seeds)}-{max(c.rollout_seeds)}"
    return len(c.rollout_seeds), c.rollout_successes, f"clean rollouts in simulation (lerobot-vib-eval, {seeds})"


def describe_calibration(config, rate_mean: float, training_data: str | None = None) -> str:
    """The model card's account of a VIB policy's uncertainty: its data, score, R_bar, gamma and how gamma was
    set, the stop's settings, and the success measured on the rollouts gamma was set on (with their command).
    `config`: a VIBConfig; `rate_mean`: the R_bar the policy uses."""
    c, safety = config.calibration, config.safety
    score = config.uncertainty_score or "rate"
    lines = ["## Uncertainty and the safety stop", ""]
    data = training_data or c.dataset_repo_id or "not recorded"
    lines.append(f"- Training data: `{data}`.")
    if c.dataset_repo_id:
        episodes = "all episodes" if c.episodes is None else f"episodes {c.episodes}"
        lines.append(f"- Calibrated on `{c.dataset_repo_id}` ({episodes}, {c.n_frames} frames).")
    else:
        lines.append("- Not calibrated: R_bar is the running mean kept during training (`lerobot-vib-calibrate`).")
    mean = c.score_means.get(score)
    normalizer = f"its training mean {mean:.4g}" if mean is not None else "its training mean"
    lines.append(f"- Score: `{score}`; u = the score over {normalizer}. R_bar (the rate's mean) = {rate_mean:.4g}.")
    if c.gamma is None:
        lines.append(
            "- Stop threshold gamma: not set on this policy's data or rollouts (the stop would use mean + 2 std)."
        )
    else:
        n = len(c.rollout_seeds or c.conformal_episodes or [])
        how = _GAMMA_METHODS.get(c.gamma_method or "", c.gamma_method or "unknown").format(n=n, alpha=c.conformal_alpha)
        lines.append(f"- Stop threshold gamma = {c.gamma:.4g} on `{c.gamma_score or 'rate'}`, set by {how}.")
        if c.rollout_episodes == "successes" and c.rollout_successes is not None:
            lines.append(
                f"- Only the {c.rollout_successes} successful ones among those rollouts set it (failure "
                "prediction's calibration: false alarms are bounded on episodes that would have succeeded)."
            )
        if c.and_gammas:
            partners = ", ".join(f"`{k}` above {g:.4g}" for k, g in c.and_gammas.items())
            lines.append(f"- The stop fires only when also {partners} (an AND of scores, each set as gamma was).")
        if c.or_gammas:
            over = "" if c.or_window == 1 else f" (its mean over {c.or_window} steps)"
            partners = ", ".join(f"`{k}`{over} above {g:.4g}" for k, g in c.or_gammas.items())
            lines.append(
                f"- The stop also fires when {partners} (an OR of scores; each threshold, gamma's included, set at "
                f"alpha / {len(c.or_gammas) + 1} so that the OR keeps alpha"
                + (f"; the OR's at {c.or_margin:g} times their conformal ones" if c.or_margin != 1 else "")
                + ")."
            )
        if c.window > 1:
            lines.append(
                f"- The stop reads u's {c.window_aggregate} over each env's last {c.window} steps, as gamma was set."
            )
    if m := c.monitor_metrics:

        def f(key: str, fmt: str = ".2f") -> str:
            return format(m[key], fmt) if m.get(key) is not None else "-"

        lines.append(
            f"- As a failure predictor (a failed episode alarmed is a true positive, a successful one a false alarm): "
            f"TPR {f('tpr')}, TNR {f('tnr')}, detection time {f('detection_time')} of the episode, median lead time "
            f"{f('median_lead_time', '.0f')} steps before the first missed grasp; {f('n_failed', '.0f')} failed and "
            f"{f('n_succeeded', '.0f')} successful rollouts that set nothing "
            f"({c.monitor_measured_on or 'not recorded'})."
        )
    lines.append(
        f"- Safety stop: {'on' if safety.enabled else 'off (enable with `--policy.safety.enabled=true`)'}; action "
        f"`{safety.action}`, resumes after {safety.resume_steps} calm steps, halts after {safety.max_hold_steps}."
    )
    if c.rollout_successes is not None and c.rollout_seeds:
        command = f" (`{c.rollout_command}`)" if c.rollout_command else ""
        lines.append(
            f"- Measured: {c.rollout_successes}/{len(c.rollout_seeds)} clean rollouts succeeded{command}, seeds "
            f"{min(c.rollout_seeds)}-{max(c.rollout_seeds)}."
        )
    else:
        lines.append(
            "- Measured: no evaluation is recorded in this checkpoint (`lerobot-vib-eval`, then "
            "`lerobot-vib-calibrate --rollouts=...` records one)."
        )
    return "\n".join(lines) + "\n"
