"""Configuration of the VIB policy (`--policy.type=vib`)."""

from __future__ import annotations

from dataclasses import dataclass, field

from lerobot.configs import FeatureType, NormalizationMode, PreTrainedConfig
from lerobot.optim import AdamWConfig
from lerobot.utils.constants import ACTION, OBS_STATE

IMAGE_POOLINGS = ("spatial_softmax", "avg")
POSITION_EMBEDDINGS = ("learned", "sinusoidal")


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
        vision_backbone: torchvision ResNet used for every camera (one shared trunk), as in ACT.
        pretrained_backbone_weights: torchvision weights for the backbone, ACT's semantics:
            "ResNet18_Weights.IMAGENET1K_V1" by default, `None` (`null` on the command line) to train the
            trunk from scratch. Loading needs the weights in the torch hub cache or a network connection.
        replace_final_stride_with_dilation: Replace the ResNet's final stride with a dilation (ACT's option);
            doubles the feature map size.
        image_pooling: How a camera's ResNet feature map becomes a feature vector.
            "spatial_softmax" (default): expected image coordinates of `spatial_softmax_num_keypoints`
            learned keypoints (LeRobot's Diffusion Policy layer), which keeps *where* things are;
            "avg": global average pooling, which discards it.
        spatial_softmax_num_keypoints: Number of keypoints for "spatial_softmax" pooling.
        mlp_hidden_dim: Hidden width of the two-layer MLPs that project each camera's pooled feature,
            `observation.state` and `observation.environment_state` to the fused feature.
        n_state_tokens: Number K of state tokens the fused feature is split into (paper Table V: 32 best).
        d_token: Size of one state token. The fused feature has `n_state_tokens * d_token` elements.
        latent_dim: Size D of each token's Gaussian latent z_k; the rate sums the KL over these dims.
        sample_latent_at_inference: If True, inference decodes a posterior sample instead of the posterior
            mean. Training always samples (reparameterization trick).
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
        optimizer_lr: AdamW learning rate (ACT's preset).
        optimizer_weight_decay: AdamW weight decay (ACT's preset).
        optimizer_lr_backbone: Learning rate of the ResNet trunk (ACT's preset).
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

    # Encoder p(z|s).
    vision_backbone: str = "resnet18"
    pretrained_backbone_weights: str | None = "ResNet18_Weights.IMAGENET1K_V1"
    replace_final_stride_with_dilation: bool = False
    image_pooling: str = "spatial_softmax"
    spatial_softmax_num_keypoints: int = 32
    mlp_hidden_dim: int = 512
    n_state_tokens: int = 32
    d_token: int = 64
    latent_dim: int = 32
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

    # Training preset (ACT's).
    optimizer_lr: float = 1e-5
    optimizer_weight_decay: float = 1e-4
    optimizer_lr_backbone: float = 1e-5

    def __post_init__(self):
        super().__post_init__()
        if not self.vision_backbone.startswith("resnet"):
            raise ValueError(f"`vision_backbone` must be a torchvision ResNet, got {self.vision_backbone!r}.")
        if self.image_pooling not in IMAGE_POOLINGS:
            raise ValueError(f"`image_pooling` must be one of {IMAGE_POOLINGS}, got {self.image_pooling!r}.")
        if self.position_embedding not in POSITION_EMBEDDINGS:
            raise ValueError(
                f"`position_embedding` must be one of {POSITION_EMBEDDINGS}, got {self.position_embedding!r}."
            )
        if self.n_obs_steps != 1:
            raise ValueError(f"Only `n_obs_steps=1` is supported, got {self.n_obs_steps}.")
        for name in ("chunk_size", "n_action_steps", "n_state_tokens", "d_token", "latent_dim", "n_layers"):
            if getattr(self, name) < 1:
                raise ValueError(f"`{name}` must be >= 1, got {getattr(self, name)}.")
        if self.n_action_steps > self.chunk_size:
            raise ValueError(
                f"`n_action_steps` ({self.n_action_steps}) cannot exceed `chunk_size` ({self.chunk_size}): "
                "a forward pass only predicts `chunk_size` actions."
            )
        if self.dim_model % self.n_heads != 0:
            raise ValueError(f"`dim_model` ({self.dim_model}) must be divisible by `n_heads` ({self.n_heads}).")
        if self.beta < 0:
            raise ValueError(f"`beta` must be >= 0, got {self.beta}.")

    def get_optimizer_preset(self) -> AdamWConfig:
        return AdamWConfig(lr=self.optimizer_lr, weight_decay=self.optimizer_weight_decay)

    def get_scheduler_preset(self) -> None:
        return None

    def validate_features(self) -> None:
        """Fail early on feature sets the model cannot encode or decode."""
        if not self.output_features or ACTION not in self.output_features:
            raise ValueError(f"VIB needs an `{ACTION}` output feature; got outputs {list(self.output_features or {})}.")
        if len(self.action_feature.shape) != 1:
            raise ValueError(f"`{ACTION}` must be a vector, got shape {tuple(self.action_feature.shape)}.")
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
