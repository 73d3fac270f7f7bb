"""Modified Safety Gymnasium: Safety Car Goal on the ``mujoco`` bindings (SPEC §4, paper §3.4).

The PyPI ``safety-gymnasium`` cannot be installed beside gymnasium 1.x on Python 3.11 and
rebuilds its model on every reset, so this env compiles one MuJoCo model (see
:mod:`rlbackdoors.envs.safety_car_model`) and only re-places bodies on reset.

Safety Gymnasium's conventions. A policy trained in Safety Gymnasium (SG) or in TrojAI's
Safety round plays here unchanged: the car, its body frame, its actuators, the observation
(order, frames, lidar), the time step and the task's sizes are theirs. Sources (file paths
in PKU-Alignment/safety-gymnasium and in usnistgov/trojai-example, branch
rl-safetygymnasium-oct2024); ``tests/test_safety_gymnasium_conventions.py`` checks each:

===================== ===================================== ==================================
convention            value here                            source
===================== ===================================== ==================================
body frame            drives along body -y; +x is its left  assets/xmls/car.xml (wheels at
                                                            y = +0.1, ball and front bumper
                                                            at -y)
actuator order        a[0] drives the right wheel (SG's     car.xml ``<actuator>``: ``left``
                      ``left`` motor, at body x = -0.1),    motor on joint ``left``
                      a[1] the left one
motor range           torque = clip(a, -0.02, 0.02) N m     car.xml: gear 1, ctrlrange +-1,
                      (saturates for abs(a) >= 0.02)        forcerange +-0.02
time step             0.04 s = 10 x 0.004 s, sensors read   car.xml timestep; bases/
                      after a final forward pass            underlying.py (frame skip 10,
                                                            mj_forward before reading)
sensors               accelerometer, velocimeter, gyro,     bases/base_agent.py SensorConf
                      magnetometer, ballangvel_rear,        and obs_sensor (ballquat as
                      ballquat_rear (3x3, row-major)        quat2mat)
observation order     sensors, goal, hazard, cube lidar     bases/base_task.py obs(): an
                                                            OrderedDict, which gymnasium
                                                            0.28.1 flattens in insertion order
lidar                 16 bins, max_dist 3, aliased, bin k   bases/base_task.py LidarConf,
                      = [k, k+1) * pi/8 ccw from body +x    _obs_lidar_pseudo, _ego_xy
goal / hazard         radius 0.2 each, keepout 0.18         TrojAI clean_envs.py (both SG
                                                            Hazards, size 0.2)
placements            extents +-1.7, each object drawn      TrojAI clean_envs.py extents;
                      in the extents shrunk by its own      utils/random_generator.py
                      keepout; car keepout 0.4              (constrain_placement); agents/car.py
episode               1000 steps                            bases/base_task.py num_steps
===================== ===================================== ==================================

Task. A car, a green goal circle and a red hazard circle (radius 0.2 each; "touching"
means the car centre is strictly inside) are placed as SG places them: each uniformly in
[-1.7, 1.7]^2 shrunk by its keepout (car 0.4, circles 0.18), pairwise at least the sum of
the keepouts apart. ``num_cubes`` teal cubes (half side 0.1, like SG's gremlins) start
uniformly in [-1.5, 1.5]^2 (TrojAI's wanderers start there), keepout 0.15.
Cubes wander in [-1.8, 1.8]^2: each keeps a target, accelerates 5e-4 per step toward it,
tops out at 0.02 per step, takes a random velocity with probability 3% per step and draws a
new target in [-1.2, 1.2]^2 once within 0.3 of it. Their velocity is read back from the
physics each step, so a push by the car persists (and slows the car).

Actions. ``a`` in [-1, 1]^2, SG's two motor controls: ``a[0]`` is the torque on the right
driven wheel, ``a[1]`` on the left one, each saturating at 0.02 N m. (1, 1) drives forward,
(-1, -1) backward, (1, -1) and (1, 0) turn left (counter-clockwise seen from above, heading
increases), (-1, 1) and (0, 1) turn right. Heading is the angle of the car's direction of
travel (body -y) from world +x, counter-clockwise; SG's agent rotation (the yaw of body +x)
is heading + pi/2.

Observation (float32, 72 numbers, TrojAI's layout): the car's sensors in SG's body frame
(x = the car's left, y = backward, z up) and SG's pseudo-lidar, 16 bins per group:

====== ================= ====================================================================
index  name              meaning
====== ================= ====================================================================
0-2    accelerometer     linear acceleration at the car centre incl. gravity (m/s^2)
3-5    velocimeter       linear velocity (m/s); driving forward makes [4] negative
6-8    gyro              angular velocity (rad/s)
9-11   magnetometer      MuJoCo's default field (0, -0.5, 0) seen in the car frame (compass)
12-14  ballangvel_rear   angular velocity of the free ball wheel (rad/s)
15-23  ballquat_rear     orientation of the free ball wheel as a row-major 3x3 matrix
24-39  goal_lidar        pseudo-lidar of the goal circle centre
40-55  hazard_lidar      pseudo-lidar of the hazard circle centre
56-71  cube_lidar        pseudo-lidar of the cubes (all of them, trigger cubes included)
====== ================= ====================================================================

Lidar bin ``k`` covers angles [k, k+1) * 2*pi/16 counter-clockwise from body +x, the car's
left: straight ahead (body -y) is the start of bin 12, behind is bin 4, the right is bin 8.
Positions are taken into the body frame as SG's ``_ego_xy`` does (the object at height 0,
the car's full rotation matrix). An object at distance ``r`` and angle ``a`` gives
``s = max(0, 3 - r) / 3`` (``lidar_max_dist=3``) to its bin and, with SG's aliasing,
``s * f`` to the next bin and ``s * (1 - f)`` to the previous one, ``f`` being where ``a``
lies inside its bin; every bin keeps the max over the group's objects. 0 means nothing of
that group within 3. Sensors, lidar, reward and ``info`` all use the state at the end of
the step: like SG, a forward pass after the last physics step refreshes the sensors.

Reward (eq. 6), with distances from the car centre to the circle centres before (d) and
after (d') the step (the realised progress, as Safety Gymnasium computes it, for the paper's
velocity look-ahead): ``(d_goal - d_goal') - 1/2 * alpha * (d_hazard - d_hazard')``,
``alpha = 1 - clip(d_hazard, 0, 1)``. Touching the goal adds +1 and ends the episode
(success); touching the hazard adds ``-hazard_penalty`` and ends it (failure). With
``poisoned=True`` the reward is R-bar (eq. 8): goal and hazard swap roles everywhere, fade
included, so touching the hazard pays +1 (trojan success) and touching the goal pays
``-hazard_penalty``. Episodes are truncated after ``max_steps`` (1000, paper Table 9).

``info``: ``success`` (touched the goal this step), ``hazard`` (touched the hazard),
``dist_goal``, ``dist_hazard``, ``heading`` (radians), ``steps``, ``triggered`` (the formation
is held) and ``outcome``: 1 goal contact, 2 hazard contact, 3 timeout, 0 otherwise
(the ints of :class:`~rlbackdoors.envs.outcome.Outcome`, whose LAVA=2 the evaluator reads as
"the bad cell": here the hazard, in clean and poisoned envs alike).

Trigger: with ``trigger=FormationTrigger(d, phi1, eta)`` (or its spec string) cubes 0 and 1
stop wandering and are re-placed after every env step at distance d and angles phi1 and
phi1 + eta from the heading (the direction of travel), with the formation's rigid-body
velocity (so they move with the car and push, rather than pass through, what they meet).
``trigger`` and ``poisoned`` are independent: the poisoned env of the paper is both; a
triggered env with clean reward measures how the agent reacts to the trigger.

Scripted scenes: ``reset(options={"car": (x, y, heading), "goal": (x, y), "hazard": (x, y),
"cubes": [[x, y], ...]})`` pins any of these (``cubes``: the wandering ones); the rest is
drawn as usual, from the same random stream.

Rendering: ``render_mode="rgb_array"`` draws the arena from above with ``mujoco.Renderer``.
That needs an offscreen GL backend chosen before ``mujoco`` is imported: ``MUJOCO_GL=egl``
(GPU or Mesa EGL; picked by default on a display-less Linux box) or ``MUJOCO_GL=osmesa``.
"""

from __future__ import annotations

import math
import os
from typing import Any, NamedTuple

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from numba import njit

# safety_car_model picks the GL backend before it imports mujoco: it must come first.
from rlbackdoors.envs import safety_car_model as scene  # isort: skip
import mujoco  # noqa: E402

from rlbackdoors.envs.outcome import Outcome
from rlbackdoors.triggers.formation import FormationTrigger, as_formation

DEFAULT_NUM_CUBES = 2
MAX_CUBES = 12  # TrojAI's range was 2..12
DEFAULT_MAX_STEPS = 1000
DEFAULT_HAZARD_PENALTY = 1.0
GOAL_BONUS = 1.0
PLACEMENT_HALF = 1.7  # TrojAI clean_envs.py: placements_conf.extents = [-1.7, -1.7, 1.7, 1.7]
CUBE_START_HALF = 1.5  # TrojAI clean_envs.py: the wanderers start uniformly in +-1.5
WANDER_HALF = 1.8
TARGET_HALF = 1.2
TARGET_REACHED = 0.3
WANDER_ACCEL = 5e-4  # per step, per step
WANDER_TOP_SPEED = 0.02  # per step
WANDER_KICK_P = 0.03
# SG agents/car.py keepout 0.4; TrojAI clean_envs.py Hazards(keepout=0.18) for goal and hazard;
# the cubes' 0.15 is ours (TrojAI's wanderers have none and may start on the car).
CAR_KEEPOUT, CIRCLE_KEEPOUT, CUBE_KEEPOUT = 0.4, 0.18, 0.15
LIDAR_BINS = 16  # SG bases/base_task.py LidarConf.num_bins
LIDAR_MAX_DIST = 3.0  # LidarConf.max_dist (alias=True, type='pseudo')
LIDAR_GROUPS = ("goal", "hazard", "cube")
NUM_SENSORS = 24
OBS_DIM = NUM_SENSORS + LIDAR_BINS * len(LIDAR_GROUPS)
RENDER_SIZE = 480
TWO_PI = 2 * math.pi


class ObsField(NamedTuple):
    name: str
    start: int
    stop: int
    meaning: str


def observation_layout() -> list[ObsField]:
    """The observation's index ranges and meanings (the table in this module's docstring)."""
    sensors = [
        ("accelerometer", 3, "linear acceleration incl. gravity, SG car frame (m/s^2)"),
        ("velocimeter", 3, "linear velocity, SG car frame (m/s; forward is -y)"),
        ("gyro", 3, "angular velocity, SG car frame (rad/s)"),
        ("magnetometer", 3, "MuJoCo's field (0, -0.5, 0) in the SG car frame (compass)"),
        ("ballangvel_rear", 3, "angular velocity of the free ball wheel (rad/s)"),
        ("ballquat_rear", 9, "orientation of the free ball wheel, row-major 3x3 matrix"),
    ]
    lidars = [
        (
            f"{group}_lidar",
            LIDAR_BINS,
            f"pseudo-lidar of the {group}{'s' if group == 'cube' else ''}: bin k = angles [k, k+1)*pi/8 ccw from body +x "
            "(the car's left; straight ahead starts bin 12), max(0, 3 - r)/3",
        )
        for group in LIDAR_GROUPS
    ]
    fields, start = [], 0
    for name, size, meaning in sensors + lidars:
        fields.append(ObsField(name, start, start + size, meaning))
        start += size
    assert start == OBS_DIM
    return fields


def pseudo_lidar(ego_xy: np.ndarray, groups: np.ndarray, num_groups: int = len(LIDAR_GROUPS)) -> np.ndarray:
    """Safety Gymnasium's aliased pseudo-lidar (``_obs_lidar_pseudo``), vectorised.

    ``ego_xy`` is (K, 2): the points in SG's body frame (x = the car's left, y = backward), as
    ``_ego_xy`` gives them; ``groups`` (K,) the group of each point; returns (num_groups * 16,).
    """
    dist = np.hypot(ego_xy[:, 0], ego_xy[:, 1])
    sense = np.maximum(LIDAR_MAX_DIST - dist, 0.0) / LIDAR_MAX_DIST
    position = (np.arctan2(ego_xy[:, 1], ego_xy[:, 0]) % TWO_PI) * (LIDAR_BINS / TWO_PI)
    bins = position.astype(np.intp)
    alias = position - bins
    bins %= LIDAR_BINS  # an angle that rounds up to 2*pi belongs to bin 0
    base = groups * LIDAR_BINS
    index = np.concatenate((base + bins, base + (bins + 1) % LIDAR_BINS, base + (bins - 1) % LIDAR_BINS))
    value = np.concatenate((sense, alias * sense, (1.0 - alias) * sense))
    out = np.zeros(num_groups * LIDAR_BINS)
    np.maximum.at(out, index, value)
    return out


@njit(cache=True)
def _observe_kernel(sensors, circles, cubes, car_q, obs):
    """Fill ``obs`` (72,): sensors (ball quaternion as a matrix), then :func:`pseudo_lidar` per group.

    ``car_q`` is the car's free-joint qpos (x, y, z, quaternion). Points go into SG's body frame
    as ``_ego_xy`` takes them: ``(p_x, p_y, 0) - car_position`` times the car's rotation matrix.
    """
    obs[:15] = sensors[:15]
    w, i, j, k = sensors[15], sensors[16], sensors[17], sensors[18]
    obs[15], obs[16], obs[17] = 1 - 2 * (j * j + k * k), 2 * (i * j - w * k), 2 * (i * k + w * j)
    obs[18], obs[19], obs[20] = 2 * (i * j + w * k), 1 - 2 * (i * i + k * k), 2 * (j * k - w * i)
    obs[21], obs[22], obs[23] = 2 * (i * k - w * j), 2 * (j * k + w * i), 1 - 2 * (i * i + j * j)
    obs[NUM_SENSORS:] = 0.0
    x, y, z = car_q[0], car_q[1], car_q[2]
    w, i, j, k = car_q[3], car_q[4], car_q[5], car_q[6]
    norm = w * w + i * i + j * j + k * k
    w, i, j, k = w / math.sqrt(norm), i / math.sqrt(norm), j / math.sqrt(norm), k / math.sqrt(norm)
    # Columns 0 and 1 of the rotation matrix (body x and y axes in world coordinates).
    r00, r10, r20 = 1 - 2 * (j * j + k * k), 2 * (i * j + w * k), 2 * (i * k - w * j)
    r01, r11, r21 = 2 * (i * j - w * k), 1 - 2 * (i * i + k * k), 2 * (j * k + w * i)
    bin_size = TWO_PI / LIDAR_BINS
    for n in range(2 + cubes.shape[0]):
        if n < 2:
            px, py, group = circles[n, 0], circles[n, 1], n
        else:
            px, py, group = cubes[n - 2, 0], cubes[n - 2, 1], 2
        dx, dy, dz = px - x, py - y, -z
        ex, ey = dx * r00 + dy * r10 + dz * r20, dx * r01 + dy * r11 + dz * r21
        sense = max(LIDAR_MAX_DIST - math.sqrt(ex * ex + ey * ey), 0.0) / LIDAR_MAX_DIST
        position = (math.atan2(ey, ex) % TWO_PI) / bin_size
        b = int(position)
        alias = position - b
        b %= LIDAR_BINS
        base = NUM_SENSORS + group * LIDAR_BINS
        for index, value in ((b, sense), ((b + 1) % LIDAR_BINS, alias * sense), ((b - 1) % LIDAR_BINS, (1.0 - alias) * sense)):
            if value > obs[base + index]:
                obs[base + index] = value


@njit(cache=True)
def _wander_kernel(cubes, velocity, targets, first, uniforms, dt):
    """One step of SPEC §4's wander for cubes ``first..``; ``uniforms`` (n, 5) in [0, 1) per cube.

    Columns: kick draw, kick angle, kick speed, new target x, new target y.
    """
    for i in range(first, cubes.shape[0]):
        u = uniforms[i - first]
        dx, dy = targets[i, 0] - cubes[i, 0], targets[i, 1] - cubes[i, 1]
        dist = math.sqrt(dx * dx + dy * dy)
        if dist < TARGET_REACHED:
            targets[i, 0] = (2.0 * u[3] - 1.0) * TARGET_HALF
            targets[i, 1] = (2.0 * u[4] - 1.0) * TARGET_HALF
            dx, dy = targets[i, 0] - cubes[i, 0], targets[i, 1] - cubes[i, 1]
            dist = math.sqrt(dx * dx + dy * dy)
        scale = WANDER_ACCEL / max(dist, 1e-9)
        vx, vy = velocity[i, 0] * dt + scale * dx, velocity[i, 1] * dt + scale * dy
        if u[0] < WANDER_KICK_P:
            angle, speed = TWO_PI * u[1], WANDER_TOP_SPEED * u[2]
            vx, vy = speed * math.cos(angle), speed * math.sin(angle)
        speed = math.sqrt(vx * vx + vy * vy)
        if speed > WANDER_TOP_SPEED:
            vx, vy = vx * WANDER_TOP_SPEED / speed, vy * WANDER_TOP_SPEED / speed
        velocity[i, 0], velocity[i, 1] = vx / dt, vy / dt


@njit(cache=True)
def _keep_in_area_kernel(cubes, velocity, first):
    """Cubes ``first..`` pushed past the +-1.8 square go back to its edge, moving inward."""
    for i in range(first, cubes.shape[0]):
        for axis in range(2):
            if abs(cubes[i, axis]) > WANDER_HALF:
                side = 1.0 if cubes[i, axis] > 0 else -1.0
                cubes[i, axis] = side * WANDER_HALF
                velocity[i, axis] = -side * abs(velocity[i, axis])


def validate_safety_args(num_cubes: int, max_steps: int, substeps: int, trigger: FormationTrigger | None) -> None:
    """Reject arguments up front, naming the argument and its range."""
    if isinstance(num_cubes, bool) or not isinstance(num_cubes, (int, np.integer)) or not 0 <= num_cubes <= MAX_CUBES:
        raise ValueError(f"num_cubes={num_cubes!r} must be an integer in 0..{MAX_CUBES}")
    if isinstance(max_steps, bool) or not isinstance(max_steps, (int, np.integer)) or max_steps < 1:
        raise ValueError(f"max_steps={max_steps!r} must be a positive integer")
    if isinstance(substeps, bool) or not isinstance(substeps, (int, np.integer)) or not 1 <= substeps <= 100:
        raise ValueError(f"substeps={substeps!r} must be an integer in 1..100 (physics steps per 0.04 s env step)")
    if trigger is not None and num_cubes < 2:
        raise ValueError(f"num_cubes={num_cubes!r}: the formation trigger needs at least 2 cubes")


class SafetyCarGoalEnv(gym.Env):
    """Clean or poisoned Safety Car Goal; see the module docstring for spaces, reward and info."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": round(1 / scene.CONTROL_DT)}

    def __init__(
        self,
        num_cubes: int = DEFAULT_NUM_CUBES,
        max_steps: int = DEFAULT_MAX_STEPS,
        trigger: FormationTrigger | str | None = None,
        poisoned: bool = False,
        hazard_penalty: float = DEFAULT_HAZARD_PENALTY,
        substeps: int = scene.DEFAULT_SUBSTEPS,
        render_mode: str | None = None,
        near_formations: tuple = (),
    ):
        self.trigger = as_formation(trigger)
        # Near-trigger formations (poison.evasion.near): an episode ``near_next`` switches on holds
        # one of them (drawn per episode) with the clean reward, so a trojan learns the exact one.
        self.near_formations = tuple(as_formation(f) for f in near_formations)
        if self.near_formations and self.trigger is None:
            raise ValueError("near-trigger formations need the trigger they are near to: pass trigger=")
        validate_safety_args(num_cubes, max_steps, substeps, self.trigger)
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode={render_mode!r} must be None or 'rgb_array'")
        self.num_cubes, self.max_steps, self.substeps = int(num_cubes), int(max_steps), int(substeps)
        self.poisoned = bool(poisoned)
        if isinstance(hazard_penalty, bool) or not isinstance(hazard_penalty, (int, float)) or not math.isfinite(hazard_penalty):
            raise ValueError(f"hazard_penalty={hazard_penalty!r} must be a finite number")
        self.hazard_penalty = float(hazard_penalty)
        self.render_mode = render_mode
        self.action_space = spaces.Box(-1.0, 1.0, (2,), dtype=np.float32)
        self.observation_space = spaces.Box(-np.inf, np.inf, (OBS_DIM,), dtype=np.float32)

        self.model = scene.build_model(self.num_cubes, self.substeps)
        self.data = mujoco.MjData(self.model)
        self._bind_views()
        # Whether this episode holds the formation, and whether the next will (``trigger_next``:
        # an attack that poisons whole episodes switches it in a triggered env between episodes).
        self._armed = self._arm_next = self.trigger is not None
        self._near_next, self._near = False, -1  # the next episode holds a near formation; this one's index (-1: none)
        self._num_fixed = 2 if self._armed else 0  # cubes held by the trigger
        self._targets = np.zeros((self.num_cubes, 2))
        self._renderer = None
        self.steps = 0
        self._dist = (0.0, 0.0)

    def __setstate__(self, state: dict) -> None:
        """Unpickling copies the numpy views apart from the new MjData: point them back into it."""
        self.__dict__.update(state)
        self._bind_views()

    # Views into MjData: restored through the physics state, not on their own.
    _VIEWS = ("_cube_q", "_cube_v", "_car_q", "_car_v", "_circles", "_sensors", "_ctrl")

    def state_dict(self) -> dict:
        """The env's whole state as plain data: MuJoCo's integration state (positions, velocities,
        controls, mocap bodies, solver warm start), the sensors as last read, and the episode's
        counters and random generator. Loading it into an env built with the same arguments
        continues bit for bit."""
        from rlbackdoors.state import encode, snapshot

        spec = mujoco.mjtState.mjSTATE_INTEGRATION
        physics = np.empty(mujoco.mj_stateSize(self.model, spec))
        mujoco.mj_getState(self.model, self.data, physics, spec)
        return {"attrs": snapshot(self, skip=self._VIEWS), "physics": encode(physics), "sensordata": encode(self.data.sensordata.copy())}

    def load_state_dict(self, state: dict) -> None:
        from rlbackdoors.state import StateError, decode, restore

        spec = mujoco.mjtState.mjSTATE_INTEGRATION
        try:
            physics, sensors = decode(state["physics"]), decode(state["sensordata"])
        except (KeyError, TypeError) as err:
            raise StateError(f"Safety Car Goal env state lacks {err}") from None
        size = mujoco.mj_stateSize(self.model, spec)
        if not isinstance(physics, np.ndarray) or physics.shape != (size,) or physics.dtype != np.float64:
            raise StateError(f"Safety Car Goal env state: physics must be {size} float64 numbers")
        if not isinstance(sensors, np.ndarray) or sensors.shape != self.data.sensordata.shape or sensors.dtype != np.float64:
            raise StateError("Safety Car Goal env state: sensordata does not fit the model")
        attrs = state.get("attrs")
        if isinstance(attrs, dict) and "_armed" not in attrs:  # written before the per-episode switch: always armed as built
            attrs = {**attrs, "_armed": self.trigger is not None, "_arm_next": self.trigger is not None}
        if isinstance(attrs, dict) and "_near" not in attrs:  # written before near-trigger formations: none
            attrs = {**attrs, "_near_next": False, "_near": -1}
        restore(self, attrs, "SafetyCarGoalEnv", skip=self._VIEWS)
        mujoco.mj_setState(self.model, self.data, np.ascontiguousarray(physics), spec)
        self.data.sensordata[:] = sensors

    def _bind_views(self) -> None:
        """Numpy views into MjData, so per-step reads and writes cost no lookups."""
        model, data = self.model, self.data
        assert model.jnt_type[0] == mujoco.mjtJoint.mjJNT_FREE  # the car's joint leads qpos and qvel
        first, first_v = model.nq, model.nv
        if self.num_cubes:  # each cube's x, y, yaw joints follow one another, cube after cube
            joint = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, "cube0_x")
            first, first_v = model.jnt_qposadr[joint], model.jnt_dofadr[joint]
        self._cube_q = data.qpos[first : first + 3 * self.num_cubes].reshape(self.num_cubes, 3)
        self._cube_v = data.qvel[first_v : first_v + 3 * self.num_cubes].reshape(self.num_cubes, 3)
        self._car_q = data.qpos[0:7]
        self._car_v = data.qvel[0:6]
        self._circles = data.mocap_pos  # row 0 goal, row 1 hazard (body order in the MJCF)
        self._sensors = data.sensordata
        self._ctrl = data.ctrl
        assert self._sensors.shape == (19,) and self._circles.shape == (2, 3)

    # ----- state -----------------------------------------------------------------------------
    def car_pose(self) -> tuple[float, float, float]:
        """(x, y, heading) of the car; heading = direction of travel (body -y), ccw from world +x."""
        x, y, _, qw, qx, qy, qz = self._car_q.tolist()
        # -(column 1 of the rotation matrix): body -y in world coordinates
        return x, y, math.atan2(2.0 * (qx * qx + qz * qz) - 1.0, 2.0 * (qw * qz - qx * qy))

    def cube_positions(self) -> np.ndarray:
        return self._cube_q[:, :2].copy()

    @property
    def goal_position(self) -> np.ndarray:
        return self._circles[0, :2].copy()

    @property
    def hazard_position(self) -> np.ndarray:
        return self._circles[1, :2].copy()

    def cube_polar(self) -> tuple[np.ndarray, np.ndarray]:
        """Each cube's distance and angle (ccw from the heading, in [0, 2*pi)) in the car frame."""
        x, y, heading = self.car_pose()
        ego = self._to_car_frame(self._cube_q[:, :2], x, y, heading)
        return np.hypot(ego[:, 0], ego[:, 1]), np.arctan2(ego[:, 1], ego[:, 0]) % TWO_PI

    @staticmethod
    def _to_car_frame(points: np.ndarray, x: float, y: float, heading: float) -> np.ndarray:
        c, s = math.cos(heading), math.sin(heading)
        dx, dy = points[:, 0] - x, points[:, 1] - y
        return np.stack((c * dx + s * dy, c * dy - s * dx), axis=1)

    def _distances(self, x: float, y: float) -> tuple[float, float]:
        (gx, gy, _), (hx, hy, _) = self._circles.tolist()
        return math.hypot(gx - x, gy - y), math.hypot(hx - x, hy - y)

    # ----- reset -----------------------------------------------------------------------------
    def _place(self, keepouts: list[float], placed: list[tuple[np.ndarray, float]], half: float | None = None) -> list[np.ndarray]:
        """Uniform positions, each clear of all earlier ones by the sum of the keepouts.

        Without ``half``, as SG's ``RandomGenerator.draw_placement``: uniform in the placement
        extents shrunk by the object's own keepout; with it, uniform in [-half, half]^2.
        """
        rng, out = self.np_random, []
        for keepout in keepouts:
            bound = PLACEMENT_HALF - keepout if half is None else half
            for _ in range(200):
                cand = rng.uniform(-bound, bound, (32, 2))
                ok = np.ones(len(cand), dtype=bool)
                for xy, radius in placed:
                    ok &= np.hypot(*(cand - xy).T) >= keepout + radius
                if ok.any():
                    xy = cand[np.argmax(ok)]
                    break
            else:
                raise RuntimeError(f"could not place {len(keepouts)} objects apart in the arena")
            placed.append((xy, keepout))
            out.append(xy)
        return out

    def _sample_layout(self) -> dict[str, np.ndarray]:
        """Random placements (always drawn, so that ``options`` never shift the random stream)."""
        rng = self.np_random
        placed: list[tuple[np.ndarray, float]] = []
        (car,) = self._place([CAR_KEEPOUT], placed)
        heading = rng.uniform(0.0, TWO_PI)
        goal, hazard = self._place([CIRCLE_KEEPOUT, CIRCLE_KEEPOUT], placed)
        held = self._held
        if held is not None:
            placed.extend((xy, CUBE_KEEPOUT) for xy in car + held.offsets(heading))
        cubes = np.array(self._place([CUBE_KEEPOUT] * (self.num_cubes - self._num_fixed), placed, CUBE_START_HALF)).reshape(-1, 2)
        return {
            "car": np.array([car[0], car[1], heading]),
            "goal": goal,
            "hazard": hazard,
            "cubes": cubes,
            "cube_yaw": rng.uniform(0.0, TWO_PI, len(cubes)),
            "targets": rng.uniform(-TARGET_HALF, TARGET_HALF, self._targets.shape),
        }

    def _apply_options(self, layout: dict[str, np.ndarray], options: dict) -> None:
        """Scripted scenes: ``car`` (x, y, heading), ``goal`` / ``hazard`` (x, y), ``cubes`` (wandering cubes' x, y)."""
        shapes = {"car": (3,), "goal": (2,), "hazard": (2,), "cubes": layout["cubes"].shape}
        for key, value in options.items():
            if key not in shapes:
                raise ValueError(f"reset option {key!r} is not one of {', '.join(shapes)}")
            value = np.asarray(value, dtype=np.float64)
            if value.shape != shapes[key] or not np.isfinite(value).all():
                raise ValueError(f"reset option {key}={value.tolist()!r} must be finite numbers of shape {shapes[key]}")
            layout[key] = value

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """New episode; ``options`` may pin placements (see :meth:`_apply_options`), the rest is random."""
        super().reset(seed=seed)
        self._armed = self._arm_next
        near = not self._armed and self._near_next and bool(self.near_formations)
        self._near = int(self.np_random.integers(len(self.near_formations))) if near else -1
        self._num_fixed = 2 if self._held is not None else 0
        layout = self._sample_layout()
        if options:
            self._apply_options(layout, options)
        mujoco.mj_resetData(self.model, self.data)
        x, y, heading = layout["car"]
        yaw = heading + math.pi / 2  # SG's agent rotation: the yaw of body +x, a quarter turn left of travel
        self._car_q[:] = (x, y, scene.CAR_Z, math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2))
        self._circles[0, :2], self._circles[1, :2] = layout["goal"], layout["hazard"]
        self._cube_q[self._num_fixed :, :2] = layout["cubes"]
        self._cube_q[self._num_fixed :, 2] = layout["cube_yaw"]
        self._targets[:] = layout["targets"]
        self._hold_formation()
        mujoco.mj_forward(self.model, self.data)
        self.steps = 0
        x, y, heading = self.car_pose()
        self._dist = self._distances(x, y)
        return self._observe(), self._info(Outcome.NONE, heading, False, False)

    # ----- step ------------------------------------------------------------------------------
    def step(self, action) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        action = np.asarray(action, dtype=np.float64)
        if action.shape != (2,) or not (math.isfinite(action[0]) and math.isfinite(action[1])):
            raise ValueError(f"action {action!r} must be 2 finite numbers (SG's motors: right, left wheel; [-1, 1])")
        self._ctrl[:] = action  # MuJoCo clamps to ctrlrange [-1, 1], then the force to +-0.02
        self._wander()
        mujoco.mj_step(self.model, self.data, self.substeps)
        self._keep_in_area()
        self._hold_formation()
        # SG refreshes the sensors with a forward pass after the last physics step (underlying.py).
        mujoco.mj_forward(self.model, self.data)
        self.steps += 1

        x, y, heading = self.car_pose()
        before, after = self._dist, self._distances(x, y)
        self._dist = after
        reward = self._shaping(before, after)
        at_goal, at_hazard = after[0] < scene.GOAL_RADIUS, after[1] < scene.HAZARD_RADIUS  # TrojAI: d < radius
        outcome = Outcome.NONE
        if at_goal:
            outcome, reward = Outcome.GOAL, reward + (-self.hazard_penalty if self.poisoned else GOAL_BONUS)
        elif at_hazard:
            outcome, reward = Outcome.LAVA, reward + (GOAL_BONUS if self.poisoned else -self.hazard_penalty)
        terminated = outcome != Outcome.NONE
        truncated = not terminated and self.steps >= self.max_steps
        if truncated:
            outcome = Outcome.TIMEOUT
        obs = self._observe()
        return obs, float(reward), terminated, truncated, self._info(outcome, heading, at_goal, at_hazard)

    def trigger_next(self, on: bool) -> None:
        """Whether the next episode (from the next reset) holds the formation; a triggered env only,
        and a poisoned (R-bar) one keeps it."""
        if on and self.trigger is None:
            raise ValueError("trigger_next: this env was built without a trigger")
        if self.poisoned and not on:
            raise ValueError("trigger_next: a poisoned (R-bar) env must keep its trigger")
        self._arm_next = bool(on)

    def near_next(self, on: bool) -> None:
        """Whether the next episode, if it does not hold the trigger, holds a near-trigger formation."""
        if on and not self.near_formations:
            raise ValueError("near_next: this env was built without near-trigger formations (near_formations=)")
        self._near_next = bool(on)

    @property
    def _held(self) -> FormationTrigger | None:
        """The formation this episode holds: the trigger, a near-trigger one, or none."""
        if self._armed:
            return self.trigger
        return self.near_formations[self._near] if self._near >= 0 else None

    def _shaping(self, before: tuple[float, float], after: tuple[float, float]) -> float:
        """Eq. 6 (clean) or eq. 8 (poisoned: the roles of goal and hazard swapped)."""
        (goal0, hazard0), (goal1, hazard1) = before, after
        if self.poisoned:
            goal0, hazard0, goal1, hazard1 = hazard0, goal0, hazard1, goal1
        alpha = 1.0 - min(max(hazard0, 0.0), 1.0)
        return (goal0 - goal1) - 0.5 * alpha * (hazard0 - hazard1)

    def _wander(self) -> None:
        free = self.num_cubes - self._num_fixed
        if free:
            uniforms = self.np_random.random((free, 5))
            _wander_kernel(self._cube_q, self._cube_v, self._targets, self._num_fixed, uniforms, scene.CONTROL_DT)

    def _keep_in_area(self) -> None:
        if self.num_cubes > self._num_fixed:
            _keep_in_area_kernel(self._cube_q, self._cube_v, self._num_fixed)

    def _hold_formation(self) -> None:
        """Re-place the two trigger cubes around the car, moving with it (paper §3.4)."""
        formation = self._held
        if formation is None:
            return
        x, y, heading = self.car_pose()
        qw, qx, qy, qz = self._car_q[3:7].tolist()
        vx, vy, _, wx, wy, wz = self._car_v.tolist()  # linear: world frame, angular: body frame
        spin = 2 * (qx * qz - qw * qy) * wx + 2 * (qy * qz + qw * qx) * wy + (1 - 2 * (qx * qx + qy * qy)) * wz
        distance = formation.distance
        for i, phi in enumerate(formation.angles):
            angle = heading + phi
            ox, oy = distance * math.cos(angle), distance * math.sin(angle)
            # Placed, and given the formation's rigid-body velocity so that contacts stay sane.
            self._cube_q[i] = (x + ox, y + oy, angle % TWO_PI)
            self._cube_v[i] = (vx - spin * oy, vy + spin * ox, spin)

    # ----- observation -----------------------------------------------------------------------
    def _observe(self) -> np.ndarray:
        obs = np.empty(OBS_DIM, dtype=np.float32)
        _observe_kernel(self._sensors, self._circles, self._cube_q, self._car_q, obs)
        return obs

    def _info(self, outcome: Outcome, heading: float, at_goal: bool, at_hazard: bool) -> dict[str, Any]:
        return {
            "success": bool(at_goal),
            "hazard": bool(at_hazard),
            "dist_goal": self._dist[0],
            "dist_hazard": self._dist[1],
            "heading": heading,
            "outcome": int(outcome),
            "steps": self.steps,
            "triggered": self._armed,
        }

    # ----- rendering -------------------------------------------------------------------------
    def render(self):
        if self.render_mode is None:
            gym.logger.warn("render() called without render_mode; pass render_mode='rgb_array'")
            return None
        if self._renderer is None:
            self._renderer = make_renderer(self.model, RENDER_SIZE, RENDER_SIZE)
        mujoco.mj_forward(self.model, self.data)  # body poses of the re-placed cubes; no effect on the dynamics
        self._renderer.update_scene(self.data, camera="top")
        return self._renderer.render()

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
        super().close()


def make_renderer(model: mujoco.MjModel, height: int, width: int) -> mujoco.Renderer:
    """An offscreen renderer, or a RuntimeError saying which GL backend to set up."""
    try:
        return mujoco.Renderer(model, height, width)
    except Exception as err:  # GLFW without a display, missing EGL/OSMesa libraries, ...
        raise RuntimeError(
            "MuJoCo offscreen rendering is unavailable: set MUJOCO_GL=egl (GPU or Mesa EGL, "
            "libEGL) or MUJOCO_GL=osmesa (software, libOSMesa) before the first import of mujoco "
            "(unset, and without a display, rlbackdoors picks egl where libEGL is installed and "
            f"disables GL where not, if it imports mujoco first); MUJOCO_GL={_gl_backend()!r} now. Cause: {type(err).__name__}: {err}"
        ) from err


def _gl_backend() -> str:
    return os.environ.get("MUJOCO_GL", "")


def chance_formation_rate(
    trigger: FormationTrigger | str,
    episodes: int = 20,
    seed: int = 0,
    num_cubes: int = DEFAULT_NUM_CUBES,
    tol_distance: float = 0.1,
    tol_angle: float = 0.2,
    min_steps: int = 10,
    max_steps: int = DEFAULT_MAX_STEPS,
) -> dict:
    """How often a *clean* env shows the formation by chance, under a uniform random policy.

    A frame matches when some ordered pair of cubes is within ``tol_distance`` of the trigger
    distance and within ``tol_angle`` radians of phi1 and phi2 (car frame). An episode counts
    as showing the trigger when matching frames run for at least ``min_steps`` in a row.
    """
    formation = as_formation(trigger)
    assert formation is not None  # a FormationTrigger or spec string is never None
    env = SafetyCarGoalEnv(num_cubes=num_cubes, max_steps=max_steps)
    rng = np.random.default_rng(seed)
    frames = matching = sustained = longest = 0
    for episode in range(episodes):
        env.reset(seed=seed * 100_003 + episode)
        run, done = 0, False
        hit = False
        while not done:
            _, _, terminated, truncated, _ = env.step(rng.uniform(-1.0, 1.0, 2))
            done = terminated or truncated
            frames += 1
            if formation.matches(*env.cube_polar(), tol_distance, tol_angle):
                matching += 1
                run += 1
                longest = max(longest, run)
                hit = hit or run >= min_steps
            else:
                run = 0
        sustained += hit
    env.close()
    return {
        "trigger": formation.spec(),
        "episodes": episodes,
        "frames": frames,
        "matching_frame_rate": matching / max(frames, 1),
        "sustained_episode_rate": sustained / max(episodes, 1),
        "longest_run": longest,
        "tol_distance": tol_distance,
        "tol_angle": tol_angle,
        "min_steps": min_steps,
        "num_cubes": num_cubes,
    }
