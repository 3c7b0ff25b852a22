"""lerobot-vib: uncertainty-aware imitation learning for LeRobot through a Variational Information
Bottleneck. Importing this package registers `--policy.type=vib` (and the baseline `act_like_vib`) with LeRobot."""

from . import baselines as _baselines  # noqa: F401  (registers --policy.type=act_like_vib)
from . import cli_errors as _cli_errors
from .configuration_vib import VIBConfig
from .sim import env_config as _env_config  # noqa: F401  (registers --env.type=aloha_fast)

__all__ = ["VIBConfig", "VIBPolicy", "make_vib_pre_post_processors"]

_cli_errors.install()  # inside lerobot-train / lerobot-eval / lerobot-rollout: a refusal prints as one line
__version__ = "0.1.0"


def __getattr__(name: str):
    # The model and processors import torchvision and LeRobot's policy stack: load them on first use so that
    # registering the config (what LeRobot's plugin discovery needs) stays cheap.
    if name == "VIBPolicy":
        from .modeling_vib import VIBPolicy

        return VIBPolicy
    if name == "make_vib_pre_post_processors":
        from .processor_vib import make_vib_pre_post_processors

        return make_vib_pre_post_processors
    raise AttributeError(name)
