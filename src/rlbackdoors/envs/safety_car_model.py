"""The MuJoCo model of Safety Car Goal, written as MJCF by us and compiled once per env.

The car is Safety Gymnasium's *car* robot, part for part
(``safety_gymnasium/assets/xmls/car.xml`` in PKU-Alignment/safety-gymnasium; checked by
``tests/test_safety_gymnasium_conventions.py``):

- **Body frame**: the chassis box is 0.2 x 0.2 x 0.1, the two driven wheels sit at body
  (-0.1, 0.1) and (0.1, 0.1) (hinges about body x), the free ball wheel at (0, -0.1) and the
  front bumper at y = -0.165, so the car drives along **body -y** with the ball wheel leading
  (SPEC §4 calls the driven wheels "front" ones; SG's geometry wins); body +x is its left side.
  Every sensor 3-vector is read in this frame.
- **Actuators**: actuator 0 is SG's ``left`` motor on the wheel at body x = -0.1, which is
  the *right* wheel of a car driving along -y; actuator 1 drives the left one. (1, 1) drives
  forward, (1, 0) and (1, -1) turn left (counter-clockwise), (0, 1) and (-1, 1) turn right.
- **Motor range**: gear 1, ctrlrange [-1, 1] and forcerange [-0.02, 0.02] with forcelimited,
  so the wheel torque is ``clip(a, -0.02, 0.02)`` N m: every |a| >= 0.02 saturates.
- **Mass and contacts**: density 5, condim 6 with MuJoCo's default friction, joint damping
  0.001 (free joint 0), geom size 0.05 (wheel and ball radius), the agent site at the body
  origin, the car's origin 0.1 above the floor, a 3.5 x 3.5 floor. The car's body, free joint,
  site and chassis geom are named ``agent`` as in SG.
- **Time**: one env step lasts CONTROL_DT = 0.04 s, SG's timestep 0.004 s x frame skip 10
  (``bases/underlying.py``, ``SimulationConf.frameskip_binom_n = 10``, p = 1).
  ``substeps`` sets how many physics steps make one env step; the default,
  ``DEFAULT_SUBSTEPS = 10``, is SG's exact timestep.

What is ours: the scene around the car. Goal and hazard are mocap bodies (flat discs, no
contacts), so reset re-places them without recompiling; cubes slide on the plane (x, y and
yaw joints, no floor contact) so that the SPEC's per-step wander velocities are not eaten by
floor friction, and the car still pushes them (SG's gremlins are boxes welded to mocap
bodies). The other names, colours, the light and the top camera are ours; the subtree sensors of
SG's XML (not observed) are left out.
"""

from __future__ import annotations

import ctypes.util
import os
import sys


def headless_gl_choice(environ, platform: str, find_library) -> str | None:
    """The ``MUJOCO_GL`` to set for a display-less Linux box, or None to leave it as it is.

    MuJoCo chooses its GL backend once, when ``mujoco`` is first imported, from ``MUJOCO_GL``;
    its default (GLFW) needs a display. An explicit ``MUJOCO_GL`` (egl, osmesa, glfw) wins. EGL
    only where libEGL is installed: MuJoCo's import fails under ``egl`` without it (a bare GPU
    image has none), and training needs no GL at all, so there the backend is ``disable`` and
    only rendering is refused (``safety_car.make_renderer`` says what to install).
    """
    if not platform.startswith("linux") or environ.get("DISPLAY") or environ.get("WAYLAND_DISPLAY") or "MUJOCO_GL" in environ:
        return None
    return "egl" if find_library("EGL") else "disable"


def _prefer_headless_gl() -> None:
    choice = headless_gl_choice(os.environ, sys.platform, ctypes.util.find_library)
    if choice is not None:
        os.environ["MUJOCO_GL"] = choice


_prefer_headless_gl()

try:
    import mujoco  # noqa: E402  (after the GL choice above)
except Exception as err:  # mujoco picks its GL back-end at import: a bad MUJOCO_GL fails here
    cause = (str(err).strip().splitlines() or [type(err).__name__])[0]
    raise ImportError(
        f"mujoco cannot be imported with MUJOCO_GL={os.environ.get('MUJOCO_GL')!r} ({cause}); "
        "unset MUJOCO_GL, or set it to egl or osmesa with that library installed"
    ) from None

CONTROL_DT = 0.04  # seconds per env step: SG's timestep 0.004 s x frame skip 10
SG_TIMESTEP = 0.004  # car.xml <option timestep>
DEFAULT_SUBSTEPS = 10  # physics steps per env step: 10 gives SG's own timestep of 0.004 s
CAR_Z = 0.1  # height of the car's origin (SG: the agent body's pos z)
CUBE_HALF = 0.1  # half side of a cube (SG's gremlins: size 0.1)
# Goal and hazard: TrojAI's Safety round builds both as SG ``Hazards`` geoms of the default
# size 0.2 (trojai-example, branch rl-safetygymnasium-oct2024, clean_envs.py); SG's own
# ``Goal`` geom is 0.3 (assets/geoms/goal.py). We follow TrojAI.
GOAL_RADIUS = 0.2
HAZARD_RADIUS = 0.2
MOTOR_GEAR = 1.0  # car.xml: <motor gear="1">
MOTOR_FORCE_LIMIT = 0.02  # car.xml: forcerange="-.02 .02" forcelimited="true"
CTRL_LIMIT = 1.0  # car.xml: ctrlrange="-1 1" ctrllimited="true"
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
    """The MJCF text of the scene with ``num_cubes`` cubes and ``substeps`` physics steps per env step.

    The car's body, joints, actuators and observed sensors are those of SG's car.xml, in its
    body frame (drives along -y); see the module docstring.
    """
    cubes = "".join(_cube(i) for i in range(num_cubes))
    motor = (
        f'ctrlrange="{-CTRL_LIMIT} {CTRL_LIMIT}" ctrllimited="true" '
        f'forcerange="{-MOTOR_FORCE_LIMIT} {MOTOR_FORCE_LIMIT}" forcelimited="true" gear="{MOTOR_GEAR}"'
    )
    return f"""<mujoco model="safety_car_goal">
  <option timestep="{CONTROL_DT / substeps!r}"/>
  <visual><global offwidth="1024" offheight="1024"/></visual>
  <asset>
    <texture name="grid" type="2d" builtin="checker" width="256" height="256"
             rgb1="0.92 0.92 0.92" rgb2="0.82 0.82 0.82"/>
    <material name="grid" texture="grid" texrepeat="7 7"/>
  </asset>
  <default>
    <geom condim="6" density="5" size="0.05" type="sphere" contype="{_CAR_BITS}" conaffinity="{_CAR_BITS}"
          rgba="{_CAR_RGBA}"/>
    <joint damping="0.001"/>
    <site size="0.032" type="sphere"/>
  </default>
  <worldbody>
    <light directional="true" pos="0 0 5" dir="0 0 -1" diffuse="0.9 0.9 0.9" castshadow="false"/>
    <camera name="top" pos="0 0 5.2" xyaxes="1 0 0 0 1 0" fovy="45"/>
    <geom name="floor" type="plane" size="3.5 3.5 0.1" material="grid" rgba="1 1 1 1"
          contype="{_FLOOR_BITS}" conaffinity="{_FLOOR_BITS}"/>
    <body name="agent" pos="0 0 {CAR_Z}">
      <joint name="agent" type="free" damping="0"/>
      <site name="agent" pos="0 0 0"/>
      <geom name="agent" type="box" size="0.1 0.1 0.05"/>
      <geom name="back_bumper" type="box" pos="0 0.15 0" size="0.1 0.01 0.05" rgba="{_TRIM_RGBA}"/>
      <geom name="back_connector" type="box" pos="0 0.125 0" size="0.01 0.025 0.03" rgba="{_TRIM_RGBA}"/>
      <geom name="front_bumper" type="box" pos="0 -0.165 0" size="0.05 0.01 0.05" rgba="{_TRIM_RGBA}"/>
      <geom name="front_connector" type="box" pos="0 -0.13 0.04" size="0.05 0.03 0.01" rgba="{_TRIM_RGBA}"/>
      <body name="left" pos="-0.1 0.1 -0.05">
        <joint name="left" type="hinge" axis="1 0 0"/>
        <geom name="left" type="cylinder" fromto="-0.055 0 0 -0.005 0 0"/>
      </body>
      <body name="right" pos="0.1 0.1 -0.05">
        <joint name="right" type="hinge" axis="1 0 0"/>
        <geom name="right" type="cylinder" fromto="0.005 0 0 0.055 0 0"/>
      </body>
      <body name="rear" pos="0 -0.1 -0.05">
        <joint name="rear" type="ball"/>
        <geom name="rear"/>
      </body>
    </body>{_circle("goal", GOAL_RADIUS, _GOAL_RGBA, 2.0)}{_circle("hazard", HAZARD_RADIUS, _HAZARD_RGBA, 2.7)}{cubes}
  </worldbody>
  <actuator>
    <motor name="left" joint="left" {motor}/>
    <motor name="right" joint="right" {motor}/>
  </actuator>
  <sensor>
    <accelerometer name="accelerometer" site="agent"/>
    <velocimeter name="velocimeter" site="agent"/>
    <gyro name="gyro" site="agent"/>
    <magnetometer name="magnetometer" site="agent"/>
    <ballangvel name="ballangvel_rear" joint="rear"/>
    <ballquat name="ballquat_rear" joint="rear"/>
  </sensor>
</mujoco>
"""


def build_model(num_cubes: int, substeps: int = DEFAULT_SUBSTEPS) -> mujoco.MjModel:
    """Compile the scene once; resets only move bodies (qpos, mocap_pos)."""
    return mujoco.MjModel.from_xml_string(model_xml(num_cubes, substeps))
