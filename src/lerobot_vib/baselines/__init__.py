"""Baselines for like-for-like comparisons: LeRobot's policies with one of VIB's treatments, by subclassing,
not by copying them. Importing this package registers their `--policy.type`s."""

from .configuration_act_like_vib import ACTLikeVIBConfig

__all__ = ["ACTLikeVIBConfig"]
