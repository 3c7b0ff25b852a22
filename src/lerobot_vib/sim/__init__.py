"""ALOHA simulation: selective-rendering tasks and env, scripted demonstrations, the dataset recorder."""

import os

# MuJoCo picks its OpenGL back end when it is first imported, and every module here imports it. Without a
# display its default (GLFW) cannot render, and an evaluation would fail at its first frame: off-screen EGL
# renders on the CPU as well. A MUJOCO_GL set by the user is kept.
if not os.environ.get("DISPLAY"):
    os.environ.setdefault("MUJOCO_GL", "egl")
