"""The rows of the paper's Table I as policies that LeRobot's eval loop can run.

Two trained networks (a VIB and an ACT checkpoint, same data and budget) and one RND give every row; rows
that differ only at run time share a checkpoint:

    row          chunks from   executed by (runtime.py)          u (recorded every step)
    act          ACT           LeRobot's ACT, action queue        -
    act_te       ACT           LeRobot's ACT, its ensembling      -
    vib          VIB           Eq. 6                              VIB rate
    vib_queue    VIB           action queue                       VIB rate (not used)
    vib_wo_u     VIB           ACT's ensembling                   VIB rate (not used)
    act_u        ACT           Eq. 6                              VIB rate of the VIB checkpoint
    act_rnd      ACT           Eq. 6                              RND
    vib_rnd      VIB           Eq. 6                              RND

"ACT w/ Uncertainty" is not defined by the paper. Here it is ACT's chunks weighted by Eq. 6 with the u of
the VIB network trained on the same data: the uncertainty ACT lacks comes from the bottleneck, so that
`act_u` against `act_rnd` compares two scores driving the same actions, and `act_u` against `vib` separates
what the score does at run time from what the bottleneck does to the learned features.

The rows with a score are `ScoredChunkPolicy` (a chunk source, a score, and the shared `ChunkRuntime`) or
`VIBPolicy` itself; the safety stop is off in all of them (the benchmark judges thresholds offline on the
recorded u, so one rollout serves every threshold).

The comparison rows (`COMPARISON`) separate what the bottleneck buys from what VIB's other choices buy. Each
comes from its own network, trained on the same data, budget and recipe, and its run time (action queue, or
ACT's ensembling at some m) is chosen per trained network on validation episodes (`lerobot-vib-benchmark`):

    row            network        what it adds to the row above
    act_chosen     act            LeRobot's ACT as it is (frozen batch norm, ResNet to layer4, last weights)
    act_like_vib   act_like_vib   VIB's trunk (group norm, cut after layer2), weight average, normalization floor
    vib_beta0      vib_beta0      VIB's architecture (state tokens, posterior heads), no pressure on the rate
    vib_chosen     vib            the bottleneck: beta of the preset

The token comparison (`TOKEN_COMPARISON`, `--variants='[tokens]'`) puts the bottleneck on ACT's own token
memory instead (`--policy.encoder=tokens`, token_network.py), beside the same ACT rows and the pooled preset:

    vib_tokens_beta0  vib_tokens_beta0  the token network with beta = 0
    vib_tokens        vib_tokens        the token network with the preset's beta
    vib_tokens_narrow vib_tokens_narrow and with its posteriors starting narrow (`posterior_logvar_init`)
    vib_tokens_narrow_beta0  the narrow start with beta = 0: what the bottleneck's pressure buys the shipped start
    vib_tokens_narrow_act_trunk  the narrow start on ACT's trunk (frozen batch norm, ResNet to layer4): what
                      VIB's trunk costs the token network where `act_like_vib` lost to ACT (unseen block, colour)
    vib_tokens_narrow_act_trunk_l3  ACT's trunk cut after layer3: 48 image cells instead of 12, to see whether
                      its success and a map fine enough to place an occluder go together
    vib_tokens_narrow_act_trunk_l2  ACT's normalization (none, from scratch) at VIB's depth, layer2: with the
                      row below, which of the two differences between the trunks carries success and which the stop
    vib_tokens_narrow_l3  VIB's trunk (group norm) cut after layer3 instead of layer2: VIB's normalization at a
                      depth that kept ACT's success
    vib_tokens_narrow_act_trunk_l2_colour  the layer2 row trained on frames whose hue, saturation and brightness
                      are randomized (`COLOUR_AUGMENTATION`): whether the rows it trails ACT on, an unseen block
                      of another colour and colour jitter, are a matter of colour
    act_colour        act_colour        LeRobot's ACT trained on the same colour-randomized frames: the control
                      that says whether the colour row's gain is the bottleneck's or the augmentation's

and one control: `act_like_vib_nofloor`, ACT + VIB's trunk and weight average with the normalization floor
off, which says whether ACT loses anything to the floor that VIB's pooled network lost (the contact cue).
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch
from lerobot.configs.policies import PreTrainedConfig
from lerobot.policies.act.modeling_act import ACTPolicy
from lerobot.policies.pretrained import PreTrainedPolicy
from torch import Tensor

from .modeling_vib import VIBPolicy
from .rnd import RND
from .runtime import ChunkRuntime
from .safety import SafetyAction, SafetyMonitor
from .stop import UncertaintyStep

ENSEMBLE_COEFF = 0.01  # ACT's default m, for every ensembling row of Table I
NARROW_LOGVAR_INIT = -6.0  # vib_tokens_narrow's posterior_logvar_init: sigma ~ 0.05 at the start of training
# LeRobot's ACT trunk (ResNet-18 with frozen batch norm, cut after layer4), as VIBConfig flags
ACT_TRUNK = {"backbone_norm": "frozen_bn", "backbone_layer": "layer4"}
ACT_TRUNK_L3 = {**ACT_TRUNK, "backbone_layer": "layer3"}  # the same ResNet, one stage shorter: a 6x8 map at 96x128
ACT_TRUNK_L2 = {**ACT_TRUNK, "backbone_layer": "layer2"}  # and at VIB's depth: a 12x16 map, 192 cells
VIB_TRUNK_L3 = {"backbone_layer": "layer3"}  # VIB's trunk (group norm from the preset) one stage deeper
# LeRobot's `dataset.image_transforms` that randomize colour on every training frame: the hue over the whole
# circle, so the one red block is seen in every colour; saturation and brightness around the recording's.
COLOUR_AUGMENTATION = {
    "enable": True,
    "max_num_transforms": 3,
    "tfs": {
        "hue": {"weight": 1.0, "type": "ColorJitter", "kwargs": {"hue": [-0.5, 0.5]}},
        "saturation": {"weight": 1.0, "type": "ColorJitter", "kwargs": {"saturation": [0.5, 1.5]}},
        "brightness": {"weight": 1.0, "type": "ColorJitter", "kwargs": {"brightness": [0.7, 1.3]}},
    },
}

# The trained networks a row's chunks or u come from, with the policy class family that loads them.
NETWORKS: dict[str, str] = {
    "vib": "vib",  # the preset as it is
    "vib_beta0": "vib",  # the preset with beta = 0
    "act": "act",  # LeRobot's ACT with the preset's sizes and recipe
    "act_like_vib": "act",  # and VIB's trunk, weight average and normalization floor (baselines/)
    "vib_tokens": "vib",  # the preset on the token network (`--policy.encoder=tokens`)
    "vib_tokens_beta0": "vib",  # and with beta = 0
    "vib_tokens_narrow": "vib",  # and with its posteriors starting at sigma ~ 0.05 (NARROW_LOGVAR_INIT)
    "vib_tokens_narrow_beta0": "vib",  # and that start with beta = 0
    "vib_tokens_narrow_act_trunk": "vib",  # and that start on ACT's trunk (frozen batch norm, to layer4)
    "vib_tokens_narrow_act_trunk_l3": "vib",  # and on that trunk cut after layer3
    "vib_tokens_narrow_act_trunk_l2": "vib",  # and after layer2, VIB's depth
    "vib_tokens_narrow_l3": "vib",  # the narrow start on VIB's trunk cut after layer3
    "vib_tokens_narrow_act_trunk_l2_colour": "vib",  # the layer2 row trained on colour-randomized frames
    "act_like_vib_nofloor": "act",  # act_like_vib with the normalization floor off (a control)
    "act_colour": "act",  # ACT on the colour row's randomized frames (its control)
}
CHOSEN = "chosen"  # a row whose run time is chosen on validation episodes among the benchmark's `runtimes`


def queue_steps(chunk_size: int, n_action_steps: int, ensembles: bool) -> int:
    """Actions a queue row executes per chunk: the checkpoint's own queue, or half a chunk when the checkpoint
    was configured to ensemble (n_action_steps 1: the arm preset, whose queue was 10 of 20 before)."""
    return max(chunk_size // 2, 1) if ensembles and n_action_steps == 1 else n_action_steps


@dataclass(frozen=True)
class Variant:
    label: str  # as in the paper's Table I
    chunks: str  # the network (NETWORKS) that predicts the chunks
    ensemble: str  # runtime.py's mode, or CHOSEN
    score: str | None  # a VIB network of NETWORKS, "rnd" or None: the u recorded (and used by Eq. 6)

    def runtime(self) -> str:
        """The fixed run time of a Table I row as a `runtimes` entry (`parse_runtime`)."""
        if self.ensemble == CHOSEN:
            raise ValueError(f"{self.label}'s run time is chosen on validation episodes, not fixed.")
        return {"none": "queue", "act": f"act:{ENSEMBLE_COEFF}", "uncertainty": f"eq6:{ENSEMBLE_COEFF}"}[self.ensemble]


VARIANTS: dict[str, Variant] = {
    "act": Variant("ACT", "act", "none", None),
    "act_te": Variant("ACT (its temporal ensembling)", "act", "act", None),
    "vib": Variant("VIB (Eq. 6)", "vib", "uncertainty", "vib"),
    "vib_queue": Variant("VIB (action queue)", "vib", "none", "vib"),
    "act_u": Variant("ACT w/ Uncertainty", "act", "uncertainty", "vib"),
    "act_rnd": Variant("ACT w/ RND", "act", "uncertainty", "rnd"),
    "vib_wo_u": Variant("VIB wo/ Uncertainty", "vib", "act", "vib"),
    "vib_rnd": Variant("VIB r/RND", "vib", "uncertainty", "rnd"),
    "act_chosen": Variant("ACT (LeRobot's)", "act", CHOSEN, None),
    "act_like_vib": Variant("ACT + VIB's trunk, EMA, floor", "act_like_vib", CHOSEN, None),
    "act_like_vib_nofloor": Variant("ACT + VIB's trunk, EMA, no floor", "act_like_vib_nofloor", CHOSEN, None),
    "vib_beta0": Variant("VIB, beta = 0", "vib_beta0", CHOSEN, "vib_beta0"),
    "vib_chosen": Variant("VIB (arm preset)", "vib", CHOSEN, "vib"),
    "vib_tokens_beta0": Variant("VIB tokens, beta = 0", "vib_tokens_beta0", CHOSEN, "vib_tokens_beta0"),
    "vib_tokens": Variant("VIB tokens (the preset's beta)", "vib_tokens", CHOSEN, "vib_tokens"),
    "vib_tokens_narrow": Variant(
        "VIB tokens, posteriors start narrow", "vib_tokens_narrow", CHOSEN, "vib_tokens_narrow"
    ),
    "vib_tokens_narrow_beta0": Variant(
        "VIB tokens, narrow start, beta = 0", "vib_tokens_narrow_beta0", CHOSEN, "vib_tokens_narrow_beta0"
    ),
    "vib_tokens_narrow_act_trunk": Variant(
        "VIB tokens, narrow start, ACT's trunk",
        "vib_tokens_narrow_act_trunk",
        CHOSEN,
        "vib_tokens_narrow_act_trunk",
    ),
    "vib_tokens_narrow_act_trunk_l3": Variant(
        "VIB tokens, narrow start, ACT's trunk to layer3",
        "vib_tokens_narrow_act_trunk_l3",
        CHOSEN,
        "vib_tokens_narrow_act_trunk_l3",
    ),
    "vib_tokens_narrow_act_trunk_l2": Variant(
        "VIB tokens, narrow start, ACT's trunk to layer2",
        "vib_tokens_narrow_act_trunk_l2",
        CHOSEN,
        "vib_tokens_narrow_act_trunk_l2",
    ),
    "vib_tokens_narrow_l3": Variant(
        "VIB tokens, narrow start, VIB's trunk to layer3", "vib_tokens_narrow_l3", CHOSEN, "vib_tokens_narrow_l3"
    ),
    "vib_tokens_narrow_act_trunk_l2_colour": Variant(
        "VIB tokens, ACT's trunk to layer2, colour augmentation",
        "vib_tokens_narrow_act_trunk_l2_colour",
        CHOSEN,
        "vib_tokens_narrow_act_trunk_l2_colour",
    ),
    "act_colour": Variant("ACT (LeRobot's), colour augmentation", "act_colour", CHOSEN, None),
}
TABLE_I = ("act", "act_te", "vib", "vib_queue", "act_u", "act_rnd", "vib_wo_u", "vib_rnd")
COMPARISON = ("act_chosen", "act_like_vib", "vib_beta0", "vib_chosen")
TOKEN_COMPARISON = (
    "act_chosen", "act_like_vib", "act_like_vib_nofloor", "vib_tokens_beta0", "vib_tokens", "vib_tokens_narrow",
    "vib_tokens_narrow_beta0", "vib_tokens_narrow_act_trunk", "vib_tokens_narrow_act_trunk_l3",
    "vib_tokens_narrow_act_trunk_l2", "vib_tokens_narrow_l3", "vib_tokens_narrow_act_trunk_l2_colour", "act_colour",
    "vib_chosen",
)  # fmt: skip
_RUNTIME_MODES = {"queue": "none", "act": "act", "eq6": "uncertainty"}


SAMPLE = "+sample"  # a run time's suffix: a VIB network decodes a posterior sample, not the posterior mean


def split_runtime(spec: str) -> tuple[str, bool]:
    """ "act:0.3+sample" -> ("act:0.3", True): the run time proper, and whether a VIB network decodes a posterior
    sample at every step (its training input) instead of the posterior mean (config.sample_latent_at_inference).
    """
    if spec.endswith(SAMPLE):
        return spec.removesuffix(SAMPLE), True
    return spec, False


def samples(spec: str) -> bool:
    """Whether run time `spec` decodes posterior samples (`split_runtime`)."""
    return split_runtime(spec)[1]


def parse_runtime(spec: str) -> tuple[str, float]:
    """ "queue", "act:<m>" (ACT's ensembling) or "eq6:<m>", each with an optional "+sample" (`split_runtime`)
    -> (runtime.py's mode, m)."""
    mode, _, coeff = split_runtime(spec)[0].partition(":")
    if mode not in _RUNTIME_MODES or (mode == "queue") != (coeff == ""):
        raise ValueError(
            f"A run time is 'queue', 'act:<m>' or 'eq6:<m>' (m >= 0), each optionally with '{SAMPLE}', got {spec!r}."
        )
    if mode == "queue":
        return "none", ENSEMBLE_COEFF
    try:
        m = float(coeff)
    except ValueError:
        m = math.nan
    if not (math.isfinite(m) and m >= 0):
        raise ValueError(f"The m of run time {spec!r} must be a number >= 0.")
    return _RUNTIME_MODES[mode], m


def _known_mean(mean: float, problem: str) -> float:
    # An unknown mean would make u NaN at every step: every rollout would stop without saying why.
    if not (math.isfinite(mean) and mean > 0):
        raise RuntimeError(f"{problem}, so its u is unknown: train it first (lerobot-train, train_rnd).")
    return mean


def vib_score(vib: VIBPolicy) -> Callable[[dict[str, Tensor]], tuple[Tensor, Tensor]]:
    """batch -> (rate, u = rate / R_bar) of a VIB network."""

    r_bar = _known_mean(vib.rate_mean(), "This VIB network has no rate statistics (R_bar)")

    @torch.no_grad()
    def score(batch: dict[str, Tensor]) -> tuple[Tensor, Tensor]:
        vib.eval()
        _, rate = vib._encode(batch)
        return rate, rate / r_bar

    return score


def rnd_score(rnd: RND) -> Callable[[dict[str, Tensor]], tuple[Tensor, Tensor]]:
    """batch -> (e, u_RND = e / e_bar)."""

    e_bar = _known_mean(float(rnd.error_mean), "This RND has no training statistics (e_bar)")

    @torch.no_grad()
    def score(batch: dict[str, Tensor]) -> tuple[Tensor, Tensor]:
        error = rnd.error(batch)
        return error, error / e_bar

    return score


class ScoredChunkPolicy(PreTrainedPolicy):
    """Chunks from one policy, u from any score, and the shared run-time layer between them.

    `last_step` holds the step's score and u like VIBPolicy's, so the same traces come out of both.
    A non-finite u, observation or action stops the env (the last command is held).
    """

    config_class = PreTrainedConfig
    name = "vib_scored_chunks"

    def __init__(
        self,
        chunk_policy: PreTrainedPolicy,
        score: Callable[[dict[str, Tensor]], tuple[Tensor, Tensor]],
        ensemble: str = "uncertainty",
        coeff: float = ENSEMBLE_COEFF,
    ):
        super().__init__(chunk_policy.config)
        self.chunk_policy = chunk_policy
        self.score = score
        cfg = chunk_policy.config
        n_action_steps = cfg.n_action_steps if ensemble == "none" else 1
        self.runtime = ChunkRuntime(ensemble, cfg.chunk_size, n_action_steps, coeff)
        self._hold = SafetyAction("hold")
        self.last_step: UncertaintyStep | None = None
        self.reset()

    def reset(self) -> None:
        self.runtime.reset(SafetyMonitor(gamma=None))
        self.last_step = None

    def get_optim_params(self) -> dict:
        raise NotImplementedError("A ScoredChunkPolicy runs trained networks; train them separately.")

    def forward(self, batch: dict[str, Tensor]) -> tuple[Tensor, dict | None]:
        raise NotImplementedError("A ScoredChunkPolicy runs trained networks; train them separately.")

    @torch.no_grad()
    def predict_action_chunk(self, batch: dict[str, Tensor], **kwargs: Any) -> Tensor:
        return self.chunk_policy.predict_action_chunk(batch)

    @torch.no_grad()
    def select_action(self, batch: dict[str, Tensor], **kwargs: Any) -> Tensor:
        images_and_state = [v for k, v in batch.items() if k.startswith("observation.") and isinstance(v, Tensor)]
        finite = torch.stack([torch.isfinite(v).flatten(1).all(1) for v in images_and_state]).all(0)
        raw, u = self.score(batch)
        action, decision = self.runtime.step(
            u,
            lambda: self.chunk_policy.predict_action_chunk(batch),
            lambda last: self._hold(last, batch_size=u.shape[0]),
            unknown=~finite,
        )
        self.last_step = UncertaintyStep(
            rate=raw,
            u=u,
            gamma=math.nan,
            threshold_active=False,
            stopped=decision.stopped,
            just_stopped=decision.just_stopped,
            resumed=decision.resumed,
            halted=decision.halted,
        )
        return action


def vib_with(vib: VIBPolicy, ensemble: str, coeff: float = ENSEMBLE_COEFF, sample: bool = False) -> VIBPolicy:
    """The VIB checkpoint run with another ensembling mode and m (its own `select_action`), the stop off;
    `sample`: it decodes a posterior sample at every step instead of the posterior mean."""
    config = copy.deepcopy(vib.config)
    config.sample_latent_at_inference = sample
    if ensemble == "none":
        ensembles = config.temporal_ensemble != "none"
        config.n_action_steps = queue_steps(config.chunk_size, config.n_action_steps, ensembles)
    else:
        config.n_action_steps = 1
    config.temporal_ensemble = ensemble
    config.temporal_ensemble_coeff = coeff
    config.safety.enabled = False
    config.uncertainty_every_step = True  # the u trace needs every step, also under the queue
    policy = VIBPolicy(config)
    policy.load_state_dict(vib.state_dict())
    return policy.eval()


def act_with(act: ACTPolicy, ensemble: str, coeff: float = ENSEMBLE_COEFF) -> ACTPolicy:
    """LeRobot's ACT (or a subclass, such as ACT like VIB) with its queue ("none") or its temporal ensembling
    ("act") at m = `coeff`."""
    if ensemble not in ("none", "act"):
        raise ValueError(f"ACT runs its queue or its own ensembling, not {ensemble!r}.")
    config = copy.deepcopy(act.config)
    if ensemble == "act":
        config.temporal_ensemble_coeff, config.n_action_steps = coeff, 1
    else:
        config.temporal_ensemble_coeff = None
    policy = type(act)(config)
    policy.load_state_dict(act.state_dict())
    return policy.eval()


def build_variant(
    name: str,
    networks: dict[str, PreTrainedPolicy | None],
    rnd: RND | None = None,
    runtime: str | None = None,
) -> PreTrainedPolicy:
    """The policy of one row from the trained networks it needs (module docstring), `networks` keyed as
    NETWORKS. `runtime` (`parse_runtime`) is the row's run time: required for a row whose run time is chosen,
    the row's own when None."""
    if name not in VARIANTS:
        raise ValueError(f"Unknown variant {name!r}; choose from {sorted(VARIANTS)}.")
    v = VARIANTS[name]
    if runtime is None:
        runtime = v.runtime()
    ensemble, coeff = parse_runtime(runtime)
    sample = samples(runtime)
    if sample and NETWORKS[v.chunks] != "vib":
        raise ValueError(f"Run time {runtime!r} samples a VIB posterior; {v.label}'s chunks come from ACT.")
    needs = {**networks, "rnd": rnd}
    for model in {v.chunks, *([v.score] if v.score else [])}:
        if needs.get(model) is None:
            raise ValueError(f"Variant {name!r} ({v.label}) needs the {model.upper()} network.")
    chunk_net = networks[v.chunks]
    if v.score is None:
        return act_with(chunk_net, ensemble, coeff)
    if v.score == v.chunks:
        return vib_with(chunk_net, ensemble, coeff, sample)
    if NETWORKS[v.chunks] == "vib":
        chunk_policy = vib_with(chunk_net, "none", sample=sample)
    else:
        chunk_policy = act_with(chunk_net, "none")
    score = rnd_score(rnd) if v.score == "rnd" else vib_score(networks[v.score])
    return ScoredChunkPolicy(chunk_policy, score, ensemble, coeff)
