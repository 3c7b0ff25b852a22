"""Discovery shim: LeRobot imports installed distributions named `lerobot_policy_*`; this one registers
the VIB policy by importing `lerobot_vib`."""

import lerobot_vib  # noqa: F401
