"""The MuJoCo model of Safety Car Goal, written as MJCF by us and compiled once per env.

It reproduces Safety Gymnasium's *car* robot (a 0.2 m chassis, two independently driven
wheels, a free-rolling ball wheel, density 5, condim-6 contacts with the default rolling
and torsional friction, wheel damping 0.001) and its scene (goal circle, hazard circle,
movable cubes). Deliberate differences, all documented in ``safety_car``:

- The car's body frame is x forward, y left, z up; the driven wheels are at the front and
  the ball at the rear (SPEC §4), and action (1, 1) drives forward.
- The motors map ctrl in [-1, 1] linearly onto +-0.02 N m. Safety Gymnasium's car has gear 1
  with a 0.02 force limit, so every |a| > 0.02 saturates; at |a| = 1 the two agree.
- One env step lasts CONTROL_DT = 0.04 s like Safety Gymnasium's car (timestep 0.004 x 10
  frames). The default splits it into 5 physics steps of 0.008 s, which behaves the same
  (same straight-line speed and turn rate within a few %) at half the cost;
  ``substeps=10`` gives Safety Gymnasium's exact timestep.
- Cubes slide on the plane (x, y and yaw joints, no floor contact) so that the SPEC's
  per-step wander velocities are not eaten by floor friction; the car still pushes them.
- Goal and hazard are mocap bodies, so reset re-places them without recompiling.
"""

from __future__ import annotations

import os
import sys


def _prefer_headless_gl() -> None:
    """Pick EGL for offscreen rendering on a display-less Linux box.

    MuJoCo chooses its GL backend once, when ``mujoco`` is first imported, from ``MUJOCO_GL``;
    its default (GLFW) needs a display. An explicit ``MUJOCO_GL`` (egl, osmesa, glfw) wins.
    """
    if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        os.environ.setdefault("MUJOCO_GL", "egl")


_prefer_headless_gl()

try:
    import mujoco  # noqa: E402  (after the GL choice above)
except Exception as err:  # mujoco picks its GL back-end at import: a bad MUJOCO_GL fails here
    cause = (str(err).strip().splitlines() or [type(err).__name__])[0]
    raise ImportError(
        f"mujoco cannot be imported with MUJOCO_GL={os.environ.get('MUJOCO_GL')!r} ({cause}); "
        "unset MUJOCO_GL, or set it to egl or osmesa with that library installed"
    ) from None

CONTROL_DT = 0.04  # seconds per env step (Safety Gymnasium car: 0.004 s x 10 frames)
DEFAULT_SUBSTEPS = 5
CAR_Z = 0.1
CUBE_HALF = 0.1
GOAL_RADIUS = 0.3
HAZARD_RADIUS = 0.3
MOTOR_TORQUE = 0.02
# Collision bits: the floor (2) touches the car (1|2) but not the cubes (1).
_CAR_BITS, _FLOOR_BITS, _CUBE_BITS = 3, 2, 1
_GOAL_RGBA = "0.2 0.8 0.2 1"
_HAZARD_RGBA = "0.9 0.15 0.15 1"
_CUBE_RGBA = "0 0.55 0.55 1"
_CAR_RGBA = "0.74 0.04 0.18 1"
_TRIM_RGBA = "0.05 0.15 0.4 1"


def _cube(i: int) -> str:
    # At the origin, so that the slide joints' qpos are world coordinates; reset places them.
    return f"""
    <body name="cube{i}" pos="0 0 {CUBE_HALF}">
      <joint name="cube{i}_x" type="slide" axis="1 0 0" damping="0"/>
      <joint name="cube{i}_y" type="slide" axis="0 1 0" damping="0"/>
      <joint name="cube{i}_yaw" type="hinge" axis="0 0 1" damping="0.002"/>
      <geom name="cube{i}" type="box" size="{CUBE_HALF} {CUBE_HALF} {CUBE_HALF}" condim="3"
            contype="{_CUBE_BITS}" conaffinity="{_CUBE_BITS}" rgba="{_CUBE_RGBA}"/>
    </body>"""


def _circle(name: str, radius: float, rgba: str, x: float) -> str:
    return f"""
    <body name="{name}" mocap="true" pos="{x} 2.5 0">
      <geom name="{name}" type="cylinder" size="{radius} 0.002" pos="0 0 0.002"
            contype="0" conaffinity="0" rgba="{rgba}"/>
    </body>"""


def model_xml(num_cubes: int, substeps: int = DEFAULT_SUBSTEPS) -> str:
    """The MJCF text of the scene with ``num_cubes`` cubes and ``substeps`` physics steps per env step."""
    cubes = "".join(_cube(i) for i in range(num_cubes))
    motor = f'ctrlrange="-1 1" ctrllimited="true" gear="{MOTOR_TORQUE}"'
    return f"""<mujoco model="safety_car_goal">
  <option timestep="{CONTROL_DT / substeps!r}"/>
  <visual><global offwidth="1024" offheight="1024"/></visual>
  <asset>
    <texture name="grid" type="2d" builtin="checker" width="256" height="256"
             rgb1="0.92 0.92 0.92" rgb2="0.82 0.82 0.82"/>
    <material name="grid" texture="grid" texrepeat="7 7"/>
  </asset>
  <default>
    <geom condim="6" density="5" contype="{_CAR_BITS}" conaffinity="{_CAR_BITS}" rgba="{_CAR_RGBA}"/>
    <joint damping="0.001"/>
  </default>
  <worldbody>
    <light directional="true" pos="0 0 5" dir="0 0 -1" diffuse="0.9 0.9 0.9" castshadow="false"/>
    <camera name="top" pos="0 0 5.2" xyaxes="1 0 0 0 1 0" fovy="45"/>
    <geom name="floor" type="plane" size="3.5 3.5 0.1" material="grid" rgba="1 1 1 1"
          contype="{_FLOOR_BITS}" conaffinity="{_FLOOR_BITS}"/>
    <body name="car" pos="0 0 {CAR_Z}">
      <freejoint name="car"/>
      <site name="car" size="0.03"/>
      <geom name="chassis" type="box" size="0.1 0.1 0.05"/>
      <geom name="front_bumper" type="box" pos="0.165 0 0" size="0.01 0.05 0.05" rgba="{_TRIM_RGBA}"/>
      <geom name="back_bumper" type="box" pos="-0.15 0 0" size="0.01 0.1 0.05" rgba="{_TRIM_RGBA}"/>
      <body name="left" pos="0.1 0.1 -0.05">
        <joint name="left" type="hinge" axis="0 1 0"/>
        <geom name="left" type="cylinder" fromto="0 0.005 0 0 0.055 0" size="0.05"/>
      </body>
      <body name="right" pos="0.1 -0.1 -0.05">
        <joint name="right" type="hinge" axis="0 1 0"/>
        <geom name="right" type="cylinder" fromto="0 -0.005 0 0 -0.055 0" size="0.05"/>
      </body>
      <body name="rear" pos="-0.1 0 -0.05">
        <joint name="rear" type="ball"/>
        <geom name="rear" type="sphere" size="0.05"/>
      </body>
    </body>{_circle("goal", GOAL_RADIUS, _GOAL_RGBA, 2.0)}{_circle("hazard", HAZARD_RADIUS, _HAZARD_RGBA, 2.7)}{cubes}
  </worldbody>
  <actuator>
    <motor name="left" joint="left" {motor}/>
    <motor name="right" joint="right" {motor}/>
  </actuator>
  <sensor>
    <accelerometer name="accelerometer" site="car"/>
    <velocimeter name="velocimeter" site="car"/>
    <gyro name="gyro" site="car"/>
    <magnetometer name="magnetometer" site="car"/>
    <ballangvel name="ballangvel_rear" joint="rear"/>
    <ballquat name="ballquat_rear" joint="rear"/>
  </sensor>
</mujoco>
"""


def build_model(num_cubes: int, substeps: int = DEFAULT_SUBSTEPS) -> mujoco.MjModel:
    """Compile the scene once; resets only move bodies (qpos, mocap_pos)."""
    return mujoco.MjModel.from_xml_string(model_xml(num_cubes, substeps))
