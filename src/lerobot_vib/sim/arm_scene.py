"""The simulated 6-DoF arm with a parallel gripper, a table, a block and an occluder: one MJCF scene.

Kinematics (all lengths in metres, the base on the table at the origin, x forward, z up):

    joint 1 base yaw (z)  ->  joint 2 shoulder pitch (y), 0.16 above the table
    -> 0.30 upper arm -> joint 3 elbow pitch (y) -> 0.26 forearm -> joint 4 forearm roll (forearm axis)
    -> joint 5 wrist pitch (y) -> joint 6 wrist roll (tool axis) -> palm and two fingers

The fingers are two slide joints held together by a joint equality (one actuator drives both, as on a
real electric gripper). Every joint has a position actuator: `action` is the 6 joint targets (radians)
and the gripper opening in [0, 1] (0 closed, 1 open); `observation.state` is the same 7 numbers measured.
Links have gravity compensation, as a real arm's controller has, so targets are tracked without sag.

Cameras: `scene`, fixed in front of the arm and looking at the table at about 35 degrees (the block's distance
from the arm runs along the image's depth); `overhead`, fixed above the front edge of the table looking down
at 58 degrees with a narrower field of view, so both of the block's table coordinates move it across the image
(at 96x128, a block at the workspace's centre moves 1.8 px per cm along x and 2.0 along y there, against 1.1
and 1.6 in `scene`); `wrist`, on the hand.

The block is a free body; the occluder is a mocap body without collisions that the env moves between a fixed
camera and the workspace. Both are placed by the env, never here.
"""

from __future__ import annotations

import mujoco
import numpy as np

JOINTS = ("base_yaw", "shoulder_pitch", "elbow_pitch", "forearm_roll", "wrist_pitch", "wrist_roll")
STATE_NAMES = [*JOINTS, "gripper"]
CAMERAS = ("scene", "wrist", "overhead")
FIXED_CAMERAS = ("scene", "overhead")
FINGER_TRAVEL = 0.035  # each finger's opening at gripper = 1
BLOCK_HALF = 0.02  # the training block: a 4 cm red cube
BLOCK_RGBA = (0.85, 0.1, 0.1, 1.0)
OCCLUDER_PARKED = (0.0, 2.0, -1.0)  # out of every camera's view
# Joint targets of the start pose: the tool point 0.24 above the table at x = 0.33, pointing down.
HOME = np.array([0.0, 0.252, -0.057, 0.0, 1.375, 0.0])

_XML = """
<mujoco model="vib_arm_grasp">
  <compiler angle="radian" autolimits="true"/>
  <option timestep="0.002" cone="elliptic" impratio="10" integrator="implicitfast"/>
  <visual>
    <headlight ambient="0.3 0.3 0.3" diffuse="0.35 0.35 0.35" specular="0 0 0"/>
    <quality shadowsize="1024"/>
    <global offwidth="1280" offheight="960"/>
  </visual>
  <default>
    <joint damping="2" armature="0.05"/>
    <position kp="400" dampratio="1" forcerange="-80 80"/>
    <geom rgba="0.75 0.75 0.78 1" friction="1 0.01 0.001"/>
    <default class="finger">
      <geom type="box" size="0.03 0.006 0.012" rgba="0.2 0.2 0.22 1" friction="1.5 0.01 0.001" condim="4"
            solref="0.004 1"/>
    </default>
  </default>
  <asset>
    <texture name="floor" type="2d" builtin="checker" rgb1="0.32 0.34 0.36" rgb2="0.28 0.3 0.32"
             width="256" height="256"/>
    <material name="floor" texture="floor" texrepeat="8 8"/>
    <material name="table" rgba="0.62 0.56 0.48 1"/>
  </asset>
  <worldbody>
    <light name="key" pos="0.3 -0.4 1.4" dir="-0.1 0.3 -1" diffuse="0.45 0.45 0.45" castshadow="true"/>
    <geom name="floor" type="plane" size="2 2 0.05" pos="0 0 -0.75" material="floor"/>
    <geom name="table" type="box" size="0.45 0.45 0.02" pos="0.35 0 -0.02" material="table"/>
    <camera name="scene" pos="0.95 0 0.55" xyaxes="0 1 0 -0.57 0 0.822" fovy="45"/>
    <camera name="overhead" pos="0.8 0 0.8" xyaxes="0 1 0 -0.848 0 0.530" fovy="30"/>
    <body name="base" pos="0 0 0">
      <geom type="cylinder" size="0.07 0.04" pos="0 0 0.04" rgba="0.25 0.25 0.28 1"/>
      <body name="link1" pos="0 0 0.08" gravcomp="1">
        <joint name="base_yaw" axis="0 0 1" range="-2.6 2.6"/>
        <geom type="cylinder" size="0.055 0.04" pos="0 0 0.04" rgba="0.9 0.9 0.92 1"/>
        <body name="upper_arm" pos="0 0 0.08" gravcomp="1">
          <joint name="shoulder_pitch" axis="0 1 0" range="-1.8 1.8"/>
          <geom type="capsule" fromto="0 0 0 0 0 0.3" size="0.04" rgba="0.9 0.9 0.92 1"/>
          <body name="forearm" pos="0 0 0.3" gravcomp="1">
            <joint name="elbow_pitch" axis="0 1 0" range="-2.2 1.2"/>
            <geom type="capsule" fromto="0 0 0 0.26 0 0" size="0.032" rgba="0.9 0.9 0.92 1"/>
            <body name="forearm_roll" pos="0.16 0 0" gravcomp="1">
              <joint name="forearm_roll" axis="1 0 0" range="-2.6 2.6"/>
              <geom type="cylinder" fromto="0 0 0 0.1 0 0" size="0.03" rgba="0.9 0.9 0.92 1"/>
              <body name="wrist" pos="0.1 0 0" gravcomp="1">
                <joint name="wrist_pitch" axis="0 1 0" range="-2.2 2.2"/>
                <geom type="capsule" fromto="0 0 0 0.06 0 0" size="0.028" rgba="0.25 0.25 0.28 1"/>
                <body name="hand" pos="0.07 0 0" gravcomp="1">
                  <joint name="wrist_roll" axis="1 0 0" range="-3.1 3.1"/>
                  <geom type="box" size="0.015 0.05 0.02" pos="0.015 0 0" rgba="0.25 0.25 0.28 1"/>
                  <camera name="wrist" pos="-0.01 0 0.06" xyaxes="0 -1 0 0.55 0 0.83" fovy="70"/>
                  <site name="grip" pos="0.09 0 0" size="0.005" rgba="0 1 0 0"/>
                  <body name="finger_left" pos="0.06 0 0" gravcomp="1">
                    <joint name="finger_left" type="slide" axis="0 1 0" range="0 0.035" damping="5" armature="0.01"/>
                    <geom class="finger" pos="0.03 0.006 0"/>
                  </body>
                  <body name="finger_right" pos="0.06 0 0" gravcomp="1">
                    <joint name="finger_right" type="slide" axis="0 -1 0" range="0 0.035" damping="5" armature="0.01"/>
                    <geom class="finger" pos="0.03 -0.006 0"/>
                  </body>
                </body>
              </body>
            </body>
          </body>
        </body>
      </body>
    </body>
    <body name="block" pos="0.4 0 0.02">
      <freejoint name="block"/>
      <geom name="block" type="box" size="0.02 0.02 0.02" mass="0.05" rgba="0.85 0.1 0.1 1" condim="4"
            friction="1.5 0.01 0.001"/>
    </body>
    <body name="occluder" mocap="true" pos="0 2 -1">
      <geom name="occluder" type="box" size="0.01 0.1 0.08" contype="0" conaffinity="0" rgba="0.45 0.42 0.4 1"/>
    </body>
  </worldbody>
  <equality>
    <joint joint1="finger_left" joint2="finger_right" polycoef="0 1 0 0 0" solref="0.005 1"/>
  </equality>
  <contact>
    <exclude body1="hand" body2="finger_left"/>
    <exclude body1="hand" body2="finger_right"/>
    <exclude body1="finger_left" body2="finger_right"/>
  </contact>
  <actuator>
    <position name="base_yaw" joint="base_yaw" ctrlrange="-2.6 2.6"/>
    <position name="shoulder_pitch" joint="shoulder_pitch" ctrlrange="-1.8 1.8"/>
    <position name="elbow_pitch" joint="elbow_pitch" ctrlrange="-2.2 1.2"/>
    <position name="forearm_roll" joint="forearm_roll" ctrlrange="-2.6 2.6" kp="150"/>
    <position name="wrist_pitch" joint="wrist_pitch" ctrlrange="-2.2 2.2" kp="150"/>
    <position name="wrist_roll" joint="wrist_roll" ctrlrange="-3.1 3.1" kp="100"/>
    <position name="gripper" joint="finger_left" ctrlrange="0 0.035" kp="300" forcerange="-15 15"/>
  </actuator>
</mujoco>
"""


def load_model() -> mujoco.MjModel:
    """A fresh model: the env edits camera poses and block colour / size in place, per episode."""
    return mujoco.MjModel.from_xml_string(_XML)
