"""Configuration of the VIB policy (`--policy.type=vib`)."""

from __future__ import annotations

import json
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path

import huggingface_hub
from draccus.utils import ParsingError
from lerobot.configs import FeatureType, NormalizationMode, PreTrainedConfig, parser
from lerobot.optim import AdamWConfig
from lerobot.optim.schedulers import CosineAnnealingWithWarmupSchedulerConfig
from lerobot.utils.constants import ACTION, OBS_STATE

from .backbone import BACKBONE_LAYERS, BACKBONE_NORMS
from .bottleneck import LOGVAR_MAX, LOGVAR_MIN
from .scores import MAP_SCORES, RND_INPUTS, SCORES, TOKEN_SCORES

IMAGE_POOLINGS = ("spatial_softmax", "spatial_softmax_avg", "avg")
POSITION_EMBEDDINGS = ("learned", "sinusoidal")
TEMPORAL_ENSEMBLES = ("none", "act", "uncertainty")
SAFETY_ACTIONS = ("hold", "home")
BAND_INDICES = ("progress", "episode_step")
# Which features `normalization_floor` applies to, by `normalization_floor_features`.
FLOORED_TYPES = {
    "all": (FeatureType.VISUAL, FeatureType.STATE, FeatureType.ENV, FeatureType.ACTION),
    "state": (FeatureType.STATE, FeatureType.ENV),
    "action": (FeatureType.ACTION,),
}
ENCODERS = ("pooled", "tokens")
TOKEN_MARGINALS = ("type", "cell")


class VIBConfigError(ParsingError):
    """A bad configuration value, named with its allowed values.

    A draccus `ParsingError` rather than a `ValueError`: draccus replaces the message of a `ValueError` raised
    while it builds a config with "Couldn't instantiate class VIBConfig", so the command line would not say
    which field is wrong; the text of a `ParsingError` reaches the user.
    """


# The score u is read from when the config leaves it open and the policy has a camera: the best measured on the
# simulated arm (benchmarks/results/uncertainty_scores_*/report.md).
DEFAULT_SCORE = "low_image_rate"

# The trunk's normalization when it is trained from scratch: the best of `benchmarks/backbone_norm.py`.
SCRATCH_BACKBONE_NORM = "group_norm"


def cli_dataset_action_dim() -> int | None:
    """The action size of the local dataset that `--dataset.root` names on the command line, if it names one."""
    root = parser.parse_arg("dataset.root")
    info = Path(root) / "meta" / "info.json" if root else None
    if info is None or not info.is_file():
        return None
    try:
        shape = json.loads(info.read_text())["features"][ACTION]["shape"]
    except (KeyError, TypeError, json.JSONDecodeError):
        return None  # LeRobot reports a malformed dataset when it loads it
    return int(shape[0]) if len(shape) == 1 else None


@dataclass
class SafetyConfig:
    """The safety stop (paper Sec. III-E, Fig. 3c), run inside `select_action`.

    RUN -> STOP when u > gamma (only if `enabled`) or, always, when u, the observation or the predicted
    action is not finite: unknown means stop. STOP -> RUN once u < `resume_threshold` for `resume_steps`
    consecutive steps; the env's action queue and ensemble are then cleared. While stopped the policy emits
    the safety action. A stop that has held `max_hold_steps` steps becomes terminal (halted): holding keeps
    the image and the pose, hence u, unchanged, so a stop caused by what the hold keeps in view would
    otherwise never end. A halted env goes home if `home_pose` is set (else it keeps holding), reports
    `last_step.halted`, and runs again only after an explicit `policy.resume()`.

    Args:
        enabled: Stop when u exceeds gamma. Non-finite values stop the policy even when this is false.
        gamma: Stop threshold on u = R / R_bar. None: the calibrated threshold (`lerobot-vib-calibrate`),
            else 1 + 2 * std(R) / mean(R) from the running statistics kept during training (paper: mean(u)
            + 2 std(u); mean(u) = 1 by construction).
        resume_threshold: u must stay below this to resume (hysteresis). None: gamma.
        resume_steps: Consecutive steps below `resume_threshold` needed to resume.
        action: "hold": repeat the last commanded action; "home": move to `home_pose`, changing each action
            dimension by at most `home_max_step` per step.
        home_pose: The home action in robot units (what the robot receives, after unnormalization).
            Required for "home"; with "hold", used if the very first step is already stopped.
        home_max_step: Largest change per step and action dimension on the way home, in robot units
            (e.g. radians per step), so that going home is never a jump.
        max_hold_steps: Consecutive stopped steps after which the stop is terminal (halted). 100 steps is
            5 s on the simulated arm (20 Hz) and 2 s in ALOHA (50 Hz); longer than any pause-and-resume
            there (an occluder for at most 40 steps, then `resume_steps`).
        band_index: How a time-indexed threshold (`calibration.gamma_band`) is read. "progress": at the
            number of steps the env has run, not counting stopped ones, so the band stands still while the arm
            holds and a stop ends when u falls, not because the clock moved the band above a u that never
            changed. "episode_step": at the episode's step, stopped ones included (the band as calibrated on
            rollouts without stops).
    """

    enabled: bool = False
    gamma: float | None = None
    resume_threshold: float | None = None
    resume_steps: int = 10
    action: str = "hold"
    home_pose: list[float] | None = None
    home_max_step: float = 0.01
    max_hold_steps: int = 100
    band_index: str = "progress"

    def __post_init__(self):
        if self.action not in SAFETY_ACTIONS:
            raise VIBConfigError(f"`safety.action` must be one of {SAFETY_ACTIONS}, got {self.action!r}.")
        if self.action == "home" and self.home_pose is None:
            raise VIBConfigError("`safety.action=home` needs `safety.home_pose` (the home action in robot units).")
        if self.resume_steps < 1:
            raise VIBConfigError(f"`safety.resume_steps` must be >= 1, got {self.resume_steps}.")
        if self.band_index not in BAND_INDICES:
            raise VIBConfigError(f"`safety.band_index` must be one of {BAND_INDICES}, got {self.band_index!r}.")
        if self.max_hold_steps is None or self.max_hold_steps < 1:
            raise VIBConfigError(
                f"`safety.max_hold_steps` must be >= 1 (a stop must be able to end), got {self.max_hold_steps}."
            )
        if not self.home_max_step > 0:
            raise VIBConfigError(f"`safety.home_max_step` must be > 0, got {self.home_max_step}.")
        for name in ("gamma", "resume_threshold"):
            value = getattr(self, name)
            if value is not None and not (math.isfinite(value) and value > 0):
                raise VIBConfigError(f"`safety.{name}` must be a positive finite number, got {value}.")
        if self.gamma is not None and self.resume_threshold is not None and self.resume_threshold > self.gamma:
            raise VIBConfigError(
                f"`safety.resume_threshold` ({self.resume_threshold}) must not exceed `safety.gamma` ({self.gamma}): "
                "a u between them would resume and stop again at once."
            )

    def check_action_dim(self, action_dim: int) -> None:
        """The home pose has one value per action dimension (known once the features are)."""
        if self.home_pose is not None and len(self.home_pose) != action_dim:
            raise VIBConfigError(
                f"`safety.home_pose` has {len(self.home_pose)} values, the action has {action_dim}: give one value "
                "per action dimension, in robot units."
            )


@dataclass
class CalibrationConfig:
    """Rate statistics over a dataset, written by `lerobot-vib-calibrate` (empty after training, when the
    running statistics kept during training are used instead).

    Args:
        dataset_repo_id: The dataset the statistics were computed on.
        episodes: Its episodes used for R_bar (all if None).
        n_frames: Number of frames they hold.
        rate_mean: R_bar, the mean rate: u = R / R_bar.
        rate_std: Standard deviation of the rate over those frames.
        rate_quantiles: Quantiles of the rate, keyed by level ("0.5", "0.9", ...).
        gamma: The calibrated stop threshold on u.
        gamma_method: "mean_plus_2std" (paper), "conformal" (held-out dataset episodes), "conformal_rollouts"
            (clean rollouts of the policy, `lerobot-vib-calibrate --rollouts`), or "time_band_rollouts" /
            "std_band_rollouts" (a time-indexed band from such rollouts, `gamma_band`).
        conformal_alpha: Target per-episode false-stop rate of the conformal threshold.
        conformal_episodes: The held-out episodes the conformal threshold was computed on.
        rollout_seeds: The env seeds of the rollouts a "conformal_rollouts" gamma was computed on.
        rollout_successes: How many of those rollouts succeeded (what the model card reports as measured).
        rollout_command: The `lerobot-vib-eval` command that made them, as it was typed.
        rollout_episodes: Which of those rollouts set gamma: "all" (every clean rollout: the stop bounds how
            often it interrupts the policy in the env it was trained for) or "successes" (the successful ones
            only, as failure prediction calibrates: it bounds false alarms on episodes that would have
            succeeded, and lets a failing episode's u stand out). None: "all" (calibrations before this field).
        score_means: Mean over the calibration frames of every other score (`scores.py`), by name: each
            normalizes its u as R_bar does the rate's.
        score_stds: Their standard deviations over the same frames.
        gamma_score: The score `gamma` was set on (None: "rate", as every calibration before scores existed).
        gamma_band: A time-indexed threshold, one value per episode step (the last one holds after it): at step
            t the stop threshold is gamma_band[t] instead of `gamma` (`lerobot-vib-calibrate --rollouts=...
            --threshold=time_band` or `std_band`; `gamma` then holds its largest value). u is not equally high at every
            phase of a task, so one threshold for all steps is either late where u is low or trips where it
            is high.
        frames_above_gamma: Fraction of the calibration frames with u > gamma (None for a gamma from rollouts).
        episodes_above_gamma: Fraction of the calibration episodes (or rollouts) with u > gamma at some frame:
            the in-sample rate of episodes the threshold stop would interrupt.
        window: The stop reads m_t, u aggregated over each env's last `window` steps (failure.windowed), and
            gamma (or the band) is a threshold on m: a score that stays up for several steps rather than one
            frame's spike. 1: u itself. Set with gamma by `lerobot-vib-calibrate --rollouts=... --window=w`,
            since a threshold only means something on the quantity it was calibrated on; Eq. 6 reads u as it is.
        window_aggregate: "mean" or "sum" of the window's u (they differ only in the first `window` steps).
        and_gammas: Other scores that must also be above their own threshold, each on its u over the same
            window, for the stop to fire (an AND of scores, FIPER's combination): {score: threshold}. Empty: the
            stop reads one score. The stop compares gamma_t * min(m_t / gamma_t, m_k / gamma_k, ...) with gamma_t,
            which is above it exactly when every member is above its own threshold, and falls below the resume
            threshold when any member falls. Set by `lerobot-vib-calibrate --rollouts=... --and_scores=[...]`.
        or_gammas: Other scores any of which, above its own constant threshold, also stops: {score: threshold},
            each on its u's `window_aggregate` over `or_window` steps (an OR: a novel scene and an arm gone
            astray show at different times, failure.AnyOf). The stop compares gamma_t * max(m_t / gamma_t,
            m_k / gamma_k, ...) with gamma_t. Every member's threshold, gamma's included, is conformal at alpha / k
            for k members, so that the OR stops a clean rollout with probability at most alpha. Set by
            `lerobot-vib-calibrate --rollouts=... --or_scores=[...] --or_window=w`; not with `and_gammas`.
        or_window: The window of the `or_gammas` scores, in steps (1: their u itself).
        or_margin: How many times their conformal thresholds the `or_gammas` are (>= 1, which keeps alpha: a
            partner then fires only far outside the clean rollouts). Set by `lerobot-vib-calibrate --or_margin`;
            already applied to `or_gammas`, kept to say how they were set.
        monitor_metrics: What the stop, as calibrated here, measured as a failure predictor on rollouts that set
            nothing (failure.py): "tpr", "tnr", "detection_time", "median_lead_time", "n_failed", "n_succeeded",
            "alpha". Empty: not measured. `lerobot-vib-benchmark` writes it into the checkpoints it ships.
        monitor_measured_on: Which rollouts those are (seeds, conditions, the command), as the model card says.
    """

    dataset_repo_id: str | None = None
    episodes: list[int] | None = None
    n_frames: int = 0
    rate_mean: float | None = None
    rate_std: float | None = None
    rate_quantiles: dict[str, float] = field(default_factory=dict)
    gamma: float | None = None
    gamma_method: str | None = None
    conformal_alpha: float | None = None
    conformal_episodes: list[int] | None = None
    rollout_seeds: list[int] | None = None
    rollout_successes: int | None = None
    rollout_command: str | None = None
    rollout_episodes: str | None = None
    score_means: dict[str, float] = field(default_factory=dict)
    score_stds: dict[str, float] = field(default_factory=dict)
    gamma_score: str | None = None
    gamma_band: list[float] | None = None
    frames_above_gamma: float | None = None
    episodes_above_gamma: float | None = None
    window: int = 1
    window_aggregate: str = "mean"
    and_gammas: dict[str, float] = field(default_factory=dict)
    or_gammas: dict[str, float] = field(default_factory=dict)
    or_window: int = 1
    or_margin: float = 1.0
    monitor_metrics: dict[str, float] = field(default_factory=dict)
    monitor_measured_on: str | None = None

    def __post_init__(self):
        for name, value in self.and_gammas.items():
            if name not in SCORES or not (math.isfinite(value) and value > 0):
                raise VIBConfigError(
                    f"`calibration.and_gammas` must map scores {SCORES} to positive finite thresholds, got "
                    f"{name}={value}."
                )
        for name, value in self.or_gammas.items():
            if name not in SCORES or not (math.isfinite(value) and value > 0):
                raise VIBConfigError(
                    f"`calibration.or_gammas` must map scores {SCORES} to positive finite thresholds, got "
                    f"{name}={value}."
                )
        if self.and_gammas and self.or_gammas:
            raise VIBConfigError(
                "`calibration.and_gammas` and `calibration.or_gammas` are both set: the stop runs an AND or an OR "
                "of scores, not both. Calibrate one of them (lerobot-vib-calibrate --and_scores or --or_scores)."
            )
        if not (math.isfinite(self.or_margin) and self.or_margin >= 1):
            raise VIBConfigError(f"`calibration.or_margin` must be >= 1, got {self.or_margin}.")
        for name in ("window", "or_window"):
            value = getattr(self, name)
            if not (isinstance(value, int) and value >= 1):
                raise VIBConfigError(f"`calibration.{name}` must be a whole number of steps >= 1, got {value}.")
        if self.window_aggregate not in ("mean", "sum"):
            raise VIBConfigError(
                f"`calibration.window_aggregate` must be 'mean' or 'sum', got {self.window_aggregate!r}."
            )
        for name in ("rate_mean", "gamma"):
            value = getattr(self, name)
            if value is not None and not (math.isfinite(value) and value > 0):
                raise VIBConfigError(f"`calibration.{name}` must be a positive finite number, got {value}.")
        if self.rate_std is not None and not (math.isfinite(self.rate_std) and self.rate_std >= 0):
            raise VIBConfigError(f"`calibration.rate_std` must be a finite number >= 0, got {self.rate_std}.")
        for name, value in self.score_means.items():
            if name not in SCORES or not (math.isfinite(value) and value > 0):
                raise VIBConfigError(
                    f"`calibration.score_means` must map scores {SCORES} to positive finite means, got {name}={value}."
                )
        if self.gamma_band is not None and (
            not self.gamma_band or not all(math.isfinite(g) and g > 0 for g in self.gamma_band)
        ):
            raise VIBConfigError("`calibration.gamma_band` must be a non-empty list of positive finite thresholds.")
        if self.gamma_score is not None and self.gamma_score not in SCORES:
            raise VIBConfigError(f"`calibration.gamma_score` must be one of {SCORES}, got {self.gamma_score!r}.")


@PreTrainedConfig.register_subclass("vib")
@dataclass
class VIBConfig(PreTrainedConfig):
    """Configuration of VIBPolicy: ACT-style action chunking through a Variational Information Bottleneck.

    The encoder p(z|s) maps the observation (one or more camera images and/or the robot state) to
    `n_state_tokens` Gaussian state tokens; a learnable Gaussian marginal m(z) gives the *rate*
    R = KL(p(z|s) || m(z)), an epistemic-uncertainty score. An encoder-only transformer over
    [state tokens; `chunk_size` learnable action queries] decodes a chunk of actions. The loss is
    L1(actions) + beta * R. Defaults follow the paper (Sec. IV) and LeRobot's ACT where the paper is silent.

    Inputs and outputs:
        - At least one camera (`observation.images.*`), `observation.state` or
          `observation.environment_state` is required. All cameras must share one shape (one ResNet trunk
          and one pooling layer serve them all).
        - `action` is required as the output.

    Args:
        n_obs_steps: Number of observation steps given to the policy. Only 1 is supported.
        chunk_size: Number of future actions predicted by one forward pass (the paper's horizon T).
        n_action_steps: Number of actions of a chunk executed before the policy is queried again
            (ACT's action queue). At most `chunk_size`.
        normalization_mapping: Normalization mode per feature type (LeRobot's normalizer processor).
        normalization_floor: Floor under every normalization scale, relative to the median scale of the
            feature's dimensions (`normalization.py`): a joint the demonstrations never move would otherwise
            turn any deviation into a huge z-score that dominates the inputs and the rate. Applied when the
            processors are built from dataset statistics (training); a checkpoint keeps the statistics it
            saved. None: LeRobot's statistics as they are (checkpoints trained before the floor existed).
        normalization_floor_features: Which features the floor applies to: "all" (cameras, state, environment
            state and action), "state" (the state vectors only) or "action" (the action only). The floor keeps a
            never-moved joint from dominating u, and also flattens what the network may read from it (on the
            arm, a joint's twitch at contact): which scope costs least success is a question for the
            validation seeds.
        encoder: The network (docs/model.md). "pooled" (the paper's Fig. 2 as drawn): each
            camera's trunk feature pooled to keypoints, summed with the state path into `n_state_tokens` state
            tokens, each with a posterior, decoded by an encoder-only transformer. "tokens" (`token_network.py`):
            ACT's own memory, one token per cell of each camera's feature map (a 1x1 projection, ACT's 2D
            sinusoidal embedding) and one per state vector, each with a posterior before ACT's encoder, and
            ACT's decoder with action queries; its image rates form `last_step.rate_map`. "tokens" ignores
            `image_pooling`, `spatial_softmax_num_keypoints`, `mlp_hidden_dim`, `n_state_tokens`, `d_token` and
            `position_embedding`.
        token_marginal: "tokens" only: "type" (one learnable marginal per token type: image, state,
            environment state) or "cell" (one per image cell, so each cell is judged against what it usually
            shows).
        n_decoder_layers: "tokens" only: layers of ACT's decoder (ACT's default 1); `n_layers` sets its encoder.
        map_top_k: "tokens" only: the "map_score" reduces the per-cell z-scores of the rate map by the mean of
            its k largest (1: the maximum), "low_map_score" the negated z-scores likewise and "abs_map_score"
            their absolute values.
        vision_backbone: torchvision ResNet used for every camera (one shared trunk), as in ACT.
        pretrained_backbone_weights: Initial weights of the backbone: a torchvision weights name
            ("ResNet18_Weights.IMAGENET1K_V1", the default, as ACT; needs the torch hub cache or a network
            connection), a local file holding a torchvision ResNet state dict (`.pth`, `.pt`, `.safetensors`;
            for offline machines), or `None` (`null` on the command line) to train the trunk from scratch.
            A checkpoint never reloads them: its own weights replace them.
        backbone_norm: Normalization layers of the trunk (`backbone.py`): "frozen_bn" (ACT's frozen batch
            norm, which keeps pretrained statistics and is the identity from scratch), "batch_norm" (trained
            batch norm) or "group_norm" (Diffusion Policy's choice from scratch). None: "frozen_bn" with
            pretrained weights, else the best measured from scratch (`SCRATCH_BACKBONE_NORM`). The resolved
            value is saved with the checkpoint, so loading builds the same layers.
        replace_final_stride_with_dilation: Replace the ResNet's final stride with a dilation (ACT's option);
            doubles the feature map size. Only ResNets of bottleneck blocks (resnet50 and up) can dilate.
        backbone_layer: The ResNet stage whose feature map is pooled: "layer4" (ACT's, stride 32), "layer3"
            (stride 16: twice the map's height and width, and for resnet18 a quarter of the trunk's weights;
            faster to train, `benchmarks/results/trunk_layer_cpu_2core/`) or "layer2" (stride 8, a sixteenth
            of the weights, a receptive field of about 100 pixels). At small images layer4's map is a few cells
            (3x4 at 96x128), coarse for placing a gripper within a centimetre; layer3 and layer2 keep finer
            grids (6x8 and 12x16).
        image_pooling: How a camera's ResNet feature map becomes a feature vector.
            "spatial_softmax" (default): expected image coordinates of `spatial_softmax_num_keypoints`
            learned keypoints (LeRobot's Diffusion Policy layer), which keeps *where* things are;
            "avg": global average pooling, which discards it; "spatial_softmax_avg": the keypoints and the
            feature map's channel means side by side (keypoints are blind to the map's overall level, so a
            black image gives ordinary-looking keypoints; the means are not).
        spatial_softmax_num_keypoints: Number of keypoints for "spatial_softmax" pooling.
        mlp_hidden_dim: Hidden width of the two-layer MLPs that project each camera's pooled feature,
            `observation.state` and `observation.environment_state` to the fused feature.
        n_state_tokens: Number K of state tokens the fused feature is split into (paper Table V: 32 best).
        d_token: Size of one state token. The fused feature has `n_state_tokens * d_token` elements.
        latent_dim: Size D of each token's Gaussian latent z_k; the rate sums the KL over these dims.
        posterior_logvar_init: None: every posterior head starts as a default linear layer, at sigma ~ 1 (the
            paper's, and every checkpoint saved before this field). A number: the heads' log-variance starts there
            (-6: sigma ~ 0.05), so the decoder first sees the camera's tokens with little noise and the rate's
            pressure adds noise where the loss allows (bottleneck.py). Affects training only; a loaded
            checkpoint acts with its own weights.
        sample_latent_at_inference: If True, inference decodes a posterior sample instead of the posterior
            mean. Training always samples (reparameterization trick), so where the posterior stays wide (the
            token network's image cells) the mean is an input the decoder never saw; choose on validation
            episodes (docs/model.md).
        dim_model: Width of the action transformer.
        n_heads: Attention heads of the action transformer.
        dim_feedforward: Feed-forward width of the action transformer.
        feedforward_activation: "relu", "gelu" or "glu".
        n_layers: Number of (encoder-only) transformer layers in the decoder q(a|z).
        pre_norm: Pre-norm transformer layers instead of post-norm.
        position_embedding: "learned" or "sinusoidal" position embeddings over
            [state tokens; action queries].
        dropout: Dropout in the transformer layers.
        beta: Weight of the rate in the loss, L = L1 + beta * mean(R) (paper Eq. 5; Table II: 1e-4 best).
        rate_momentum: Momentum of the running mean and second moment of the rate kept during training
            (buffers saved with the model), which give R_bar until `lerobot-vib-calibrate` replaces it.
        uncertainty_score: The score u is read from (`scores.py`; each is normalized by its mean over the
            calibration frames, u = s / s_bar). None: the best measured on the simulated arm
            (`DEFAULT_SCORE`, docs/uncertainty.md) for a policy with a camera, else "rate"; resolved when the
            policy is built and saved resolved. "rate": the paper's rate over the fused state tokens;
            "image_rate": the rate with the state path held at its training mean, so only the camera moves it;
            "low_image_rate": its inverse, high when the camera path carries less information than in training
            (a dark, covered or featureless view lowers the rate);
            "embedding_rnd": random network distillation on the policy's observation embedding;
            "chunk_disagreement": the spread of the overlapping chunks' candidates for the current step (decodes
            a chunk every step); the token network's "state_rate" (its state tokens' rate), "map_score" (the
            rate map's largest cell z-score against each cell's training statistics), "low_map_score" (the
            largest fall below them) and "abs_map_score" (the largest move either way). All but "rate" need
            `lerobot-vib-calibrate`, which computes their statistics and fits the RND. The safety stop and Eq. 6
            use this u; every available score is traced in `last_step.scores`.
        rnd_input: The embedding "embedding_rnd" reads: "fused" (the fused feature the bottleneck sees, as
            FIPER's RND-OE) or "pooled" (the cameras' pooled trunk features and the normalized state).
        temporal_ensemble: How `select_action` turns chunks into one action. "none": ACT's action queue
            of `n_action_steps`; "act": ACT's temporal ensembling, w_j ∝ exp(-m * j); "uncertainty": the
            paper's Eq. 6, w_j ∝ exp(-m * u_j * j), j = 0 the oldest chunk's candidate and u_j the normalized
            rate of the pass that produced it. Ensembling needs `n_action_steps=1`.
        temporal_ensemble_coeff: m in the ensembling weights (ACT's 0.01).
        uncertainty_every_step: Encode every step's observation for its rate, even while actions come from
            the queue (what the safety stop and per-step traces need). False: with the action queue, encode
            only when a chunk is planned, as ACT (much cheaper per step); u and the threshold stop then
            update only at those steps. Non-finite observations stop the policy either way.
        safety: The safety stop (see `SafetyConfig`), e.g. `--policy.safety.enabled=true`.
        calibration: Rate statistics written by `lerobot-vib-calibrate` (see `CalibrationConfig`).
        optimizer_lr: AdamW learning rate (ACT's preset).
        optimizer_weight_decay: AdamW weight decay (ACT's preset).
        optimizer_lr_backbone: Learning rate of the ResNet trunk (ACT's preset).
        scheduler_warmup_steps: None (ACT's preset): a constant learning rate. An integer: LeRobot's
            `cosine_annealing_with_warmup`, a linear warmup over this many steps and then a cosine decay to zero
            at the run's last step, so the last checkpoint is the settled one (from-scratch recipes).
        ema_decay: None (ACT's way): the policy acts with the last trained weights. A number in (0, 1): it
            keeps an exponential moving average of the weights (`ema.py`; about the last tenth of training
            early on, at most `1 / (1 - ema_decay)` steps later) and acts, calibrates and saves with it in eval
            mode; training still updates the raw weights. Checkpoints then hold both. The running R_bar from
            training is the raw weights' rate: run `lerobot-vib-calibrate` before trusting u or gamma.
    """

    # Input / output structure.
    n_obs_steps: int = 1
    chunk_size: int = 100
    n_action_steps: int = 100

    normalization_mapping: dict[str, NormalizationMode] = field(
        default_factory=lambda: {
            "VISUAL": NormalizationMode.MEAN_STD,
            "STATE": NormalizationMode.MEAN_STD,
            "ENV": NormalizationMode.MEAN_STD,
            "ACTION": NormalizationMode.MEAN_STD,
        }
    )

    normalization_floor: float | None = 0.1
    normalization_floor_features: str = "all"

    # Which network (DESIGN 1): the paper's pooled state tokens, or ACT's token memory with a bottleneck.
    encoder: str = "pooled"
    token_marginal: str = "type"
    n_decoder_layers: int = 1
    map_top_k: int = 1

    # Encoder p(z|s).
    vision_backbone: str = "resnet18"
    pretrained_backbone_weights: str | None = "ResNet18_Weights.IMAGENET1K_V1"
    backbone_norm: str | None = None
    replace_final_stride_with_dilation: bool = False
    backbone_layer: str = "layer4"
    image_pooling: str = "spatial_softmax"
    spatial_softmax_num_keypoints: int = 32
    mlp_hidden_dim: int = 512
    n_state_tokens: int = 32
    d_token: int = 64
    latent_dim: int = 32
    posterior_logvar_init: float | None = None
    sample_latent_at_inference: bool = False

    # Decoder q(a|z): encoder-only transformer with learnable action queries.
    dim_model: int = 512
    n_heads: int = 8
    dim_feedforward: int = 3200
    feedforward_activation: str = "relu"
    n_layers: int = 4
    pre_norm: bool = False
    position_embedding: str = "learned"
    dropout: float = 0.1

    # Loss.
    beta: float = 1e-4
    rate_momentum: float = 0.01

    # Run time: the uncertainty score, ensembling, safety stop, calibration.
    uncertainty_score: str | None = None
    rnd_input: str = "fused"
    temporal_ensemble: str = "none"
    temporal_ensemble_coeff: float = 0.01
    uncertainty_every_step: bool = True
    safety: SafetyConfig = field(default_factory=SafetyConfig)
    calibration: CalibrationConfig = field(default_factory=CalibrationConfig)

    # Training preset (ACT's).
    optimizer_lr: float = 1e-5
    optimizer_weight_decay: float = 1e-4
    optimizer_lr_backbone: float = 1e-5
    scheduler_warmup_steps: int | None = None
    ema_decay: float | None = None

    def __post_init__(self):
        super().__post_init__()
        if not self.vision_backbone.startswith("resnet"):
            raise VIBConfigError(f"`vision_backbone` must be a torchvision ResNet, got {self.vision_backbone!r}.")
        if self.replace_final_stride_with_dilation and self.vision_backbone in ("resnet18", "resnet34"):
            # torchvision's BasicBlock has no dilation; it would fail later with a bare NotImplementedError.
            raise VIBConfigError(
                f"`replace_final_stride_with_dilation=true` needs a ResNet of bottleneck blocks (resnet50 and "
                f"larger); {self.vision_backbone} has none. Set it to false, or change `vision_backbone`."
            )
        if self.backbone_layer not in BACKBONE_LAYERS:
            raise VIBConfigError(f"`backbone_layer` must be one of {BACKBONE_LAYERS}, got {self.backbone_layer!r}.")
        if self.replace_final_stride_with_dilation and self.backbone_layer != "layer4":
            raise VIBConfigError(
                "`replace_final_stride_with_dilation=true` dilates layer4, which "
                f"`backbone_layer={self.backbone_layer}` leaves out. Set one of them back."
            )
        if self.backbone_norm is None:
            self.backbone_norm = "frozen_bn" if self.pretrained_backbone_weights else SCRATCH_BACKBONE_NORM
        if self.backbone_norm not in BACKBONE_NORMS:
            raise VIBConfigError(f"`backbone_norm` must be one of {BACKBONE_NORMS}, got {self.backbone_norm!r}.")
        if self.backbone_norm == "group_norm" and self.pretrained_backbone_weights:
            raise VIBConfigError(
                "`backbone_norm=group_norm` cannot use `pretrained_backbone_weights` "
                f"({self.pretrained_backbone_weights!r}): they were trained with batch norm. Use frozen_bn or "
                "batch_norm with pretrained weights, or `--policy.pretrained_backbone_weights=null`."
            )
        if self.image_pooling not in IMAGE_POOLINGS:
            raise VIBConfigError(f"`image_pooling` must be one of {IMAGE_POOLINGS}, got {self.image_pooling!r}.")
        if self.position_embedding not in POSITION_EMBEDDINGS:
            raise VIBConfigError(
                f"`position_embedding` must be one of {POSITION_EMBEDDINGS}, got {self.position_embedding!r}."
            )
        if self.normalization_floor is not None and not (
            math.isfinite(self.normalization_floor) and 0 < self.normalization_floor <= 1
        ):
            raise VIBConfigError(f"`normalization_floor` must be in (0, 1] or null, got {self.normalization_floor}.")
        if self.normalization_floor_features not in FLOORED_TYPES:
            raise VIBConfigError(
                f"`normalization_floor_features` must be one of {tuple(FLOORED_TYPES)}, got "
                f"{self.normalization_floor_features!r}."
            )
        if self.n_obs_steps != 1:
            raise VIBConfigError(f"Only `n_obs_steps=1` is supported, got {self.n_obs_steps}.")
        for name in ("chunk_size", "n_action_steps", "n_state_tokens", "d_token", "latent_dim", "n_layers"):
            if getattr(self, name) < 1:
                raise VIBConfigError(f"`{name}` must be >= 1, got {getattr(self, name)}.")
        if self.n_action_steps > self.chunk_size:
            raise VIBConfigError(
                f"`n_action_steps` ({self.n_action_steps}) cannot exceed `chunk_size` ({self.chunk_size}): "
                "a forward pass only predicts `chunk_size` actions."
            )
        if self.dim_model % self.n_heads != 0:
            raise VIBConfigError(f"`dim_model` ({self.dim_model}) must be divisible by `n_heads` ({self.n_heads}).")
        if self.ema_decay is not None and not 0.0 < self.ema_decay < 1.0:
            raise VIBConfigError(f"`ema_decay` must be in (0, 1) or null, got {self.ema_decay}.")
        if self.scheduler_warmup_steps is not None and self.scheduler_warmup_steps < 0:
            raise VIBConfigError(f"`scheduler_warmup_steps` must be >= 0 or null, got {self.scheduler_warmup_steps}.")
        if self.beta < 0:
            raise VIBConfigError(f"`beta` must be >= 0, got {self.beta}.")
        if self.posterior_logvar_init is not None and not LOGVAR_MIN <= self.posterior_logvar_init <= LOGVAR_MAX:
            raise VIBConfigError(
                f"`posterior_logvar_init` must be null or in [{LOGVAR_MIN}, {LOGVAR_MAX}] (the log-variance's "
                f"clamp), got {self.posterior_logvar_init}."
            )
        if not 0 < self.rate_momentum <= 1:
            raise VIBConfigError(f"`rate_momentum` must be in (0, 1], got {self.rate_momentum}.")
        if self.uncertainty_score is not None and self.uncertainty_score not in SCORES:
            raise VIBConfigError(f"`uncertainty_score` must be one of {SCORES}, got {self.uncertainty_score!r}.")
        if self.rnd_input not in RND_INPUTS:
            raise VIBConfigError(f"`rnd_input` must be one of {RND_INPUTS}, got {self.rnd_input!r}.")
        if self.temporal_ensemble not in TEMPORAL_ENSEMBLES:
            raise VIBConfigError(
                f"`temporal_ensemble` must be one of {TEMPORAL_ENSEMBLES}, got {self.temporal_ensemble!r}."
            )
        if self.encoder not in ENCODERS:
            raise VIBConfigError(f"`encoder` must be one of {ENCODERS}, got {self.encoder!r}.")
        if self.token_marginal not in TOKEN_MARGINALS:
            raise VIBConfigError(f"`token_marginal` must be one of {TOKEN_MARGINALS}, got {self.token_marginal!r}.")
        if self.n_decoder_layers < 1 or self.map_top_k < 1:
            raise VIBConfigError(
                f"`n_decoder_layers` and `map_top_k` must be >= 1, got {self.n_decoder_layers} and {self.map_top_k}."
            )
        if self.encoder == "tokens" and self.rnd_input == "pooled":
            raise VIBConfigError(
                "`rnd_input=pooled` reads the pooled network's keypoints; the token network has none: use `fused` "
                "(its tokens' posterior means)."
            )
        if self.temporal_ensemble != "none" and self.n_action_steps != 1:
            raise VIBConfigError(
                f"`temporal_ensemble={self.temporal_ensemble}` needs `n_action_steps=1`: the policy must be "
                f"queried every step to ensemble (got n_action_steps={self.n_action_steps})."
            )
        self._check_safety_against_known_values()
        self._check_hub_push_can_happen()

    def _check_hub_push_can_happen(self) -> None:
        """`lerobot-train` pushes to the Hub after the last step: offline, refuse before the first one."""
        training = Path(sys.argv[0]).name == "lerobot-train" if sys.argv else False
        if training and self.push_to_hub and self.repo_id and huggingface_hub.constants.HF_HUB_OFFLINE:
            raise VIBConfigError(
                f"`push_to_hub=true` with `repo_id={self.repo_id}` would push after training, but the Hub is "
                "offline (HF_HUB_OFFLINE): set `--policy.push_to_hub=false` and push the calibrated checkpoint "
                "later, or go online."
            )

    def _check_safety_against_known_values(self) -> None:
        """What the stop's settings can be checked against before any data loads or episode runs: the calibrated
        gamma, the action size of a loaded config, or of the local dataset named on the command line (so that
        `lerobot-train` refuses a home pose of the wrong length before it loads the dataset)."""
        safety, calibration = self.safety, self.calibration
        if (
            safety.gamma is None
            and safety.resume_threshold is not None
            and calibration.gamma is not None
            and not calibration.gamma_band  # a band moves gamma every step; the hysteresis is kept below it
            and safety.resume_threshold > calibration.gamma
        ):
            raise VIBConfigError(
                f"`safety.resume_threshold` ({safety.resume_threshold}) must not exceed the calibrated gamma "
                f"({calibration.gamma}): a u between them would resume and stop again at once."
            )
        if safety.home_pose is None:
            return
        if self.output_features and ACTION in self.output_features:
            action_dim, source = self.output_features[ACTION].shape[0], "the policy's action"
        elif (action_dim := cli_dataset_action_dim()) is not None:
            source = f"the action of the dataset at --dataset.root={parser.parse_arg('dataset.root')}"
        else:
            return
        if len(safety.home_pose) != action_dim:
            raise VIBConfigError(
                f"`safety.home_pose` has {len(safety.home_pose)} values, {source} has {action_dim}: give one "
                "value per action dimension, in robot units."
            )

    def get_optimizer_preset(self) -> AdamWConfig:
        return AdamWConfig(lr=self.optimizer_lr, weight_decay=self.optimizer_weight_decay)

    def get_scheduler_preset(self) -> CosineAnnealingWithWarmupSchedulerConfig | None:
        if self.scheduler_warmup_steps is None:
            return None
        return CosineAnnealingWithWarmupSchedulerConfig(num_warmup_steps=self.scheduler_warmup_steps)

    def validate_features(self) -> None:
        """Fail early on feature sets the model cannot encode or decode."""
        if not self.output_features or ACTION not in self.output_features:
            raise ValueError(f"VIB needs an `{ACTION}` output feature; got outputs {list(self.output_features or {})}.")
        if len(self.action_feature.shape) != 1:
            raise ValueError(f"`{ACTION}` must be a vector, got shape {tuple(self.action_feature.shape)}.")
        if self.uncertainty_score is None:
            self.uncertainty_score = DEFAULT_SCORE if self.image_features else "rate"
        if self.uncertainty_score in TOKEN_SCORES and self.encoder != "tokens":
            raise ValueError(
                f"`uncertainty_score={self.uncertainty_score}` reads per-token rates, which only the token network "
                "has: set `encoder=tokens`, or use another score."
            )
        camera_scores = ("image_rate", "low_image_rate", *MAP_SCORES)
        if self.uncertainty_score in camera_scores and not self.image_features:
            raise ValueError(
                f"`uncertainty_score={self.uncertainty_score}` reads the camera path, and this policy has no camera: "
                "use `rate` (or `embedding_rnd`, `chunk_disagreement`)."
            )
        self.safety.check_action_dim(self.action_feature.shape[0])
        state_keys = [
            k for k, ft in (self.input_features or {}).items() if ft.type is FeatureType.STATE and k != OBS_STATE
        ]
        if state_keys and not self.robot_state_feature:
            raise ValueError(
                f"VIB reads the robot state from `{OBS_STATE}`, but the inputs name it {state_keys}; "
                f'rename it with `--rename_map=\'{{"{state_keys[0]}": "{OBS_STATE}"}}\'`.'
            )
        if not (self.image_features or self.robot_state_feature or self.env_state_feature):
            raise ValueError(
                "VIB needs at least one camera (`observation.images.*`), `observation.state` or "
                f"`observation.environment_state` among its inputs; got {list(self.input_features or {})}."
            )
        shapes = {key: tuple(ft.shape) for key, ft in self.image_features.items()}
        for key, shape in shapes.items():
            if len(shape) != 3:
                raise ValueError(f"Camera `{key}` must have a (C, H, W) shape, got {shape}.")
        if len(set(shapes.values())) > 1:
            raise ValueError(
                "All cameras must have the same (C, H, W) shape because they share one ResNet trunk; got "
                + ", ".join(f"{k}: {s}" for k, s in shapes.items())
                + ". Resize them when recording or with a rename/resize processor."
            )
        for key, ft in (self.input_features or {}).items():
            if ft.type in (FeatureType.STATE, FeatureType.ENV) and len(ft.shape) != 1:
                raise ValueError(f"`{key}` must be a vector, got shape {tuple(ft.shape)}.")

    @property
    def observation_delta_indices(self) -> None:
        return None

    @property
    def action_delta_indices(self) -> list[int]:
        return list(range(self.chunk_size))

    @property
    def reward_delta_indices(self) -> None:
        return None
