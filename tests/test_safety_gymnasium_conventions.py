"""Safety Car Goal follows Safety Gymnasium's conventions (issue 15), so that TrojAI's Safety
round models (OPAC² MLPs 72 -> 181 -> 181 -> 2 on raw observations) play in it unchanged.

Each convention is written down here with the file it comes from and its value, and checked
three ways:

* ``test_ours_*``: our env and model use the recorded value. Always runs.
* ``test_source_*``: the recorded value is what Safety Gymnasium's (SG) / TrojAI's own files
  say, parsed from those files. Runs when the sources are on this machine; skips otherwise.
* behavioural tests: the physics and the observation do what the convention means. Always run.

The sources are read from git repositories (or plain checkouts) named by environment
variables, defaulting to this project's mirrors:

* ``RLBACKDOORS_SAFETY_GYMNASIUM``: PKU-Alignment/safety-gymnasium (ref ``HEAD``),
* ``RLBACKDOORS_TROJAI_EXAMPLE``: usnistgov/trojai-example (branch ``rl-safetygymnasium-oct2024``),
* ``RLBACKDOORS_GYMNASIUM``: Farama-Foundation/Gymnasium (tag ``v0.28.1``, SG's pinned version).
"""

from __future__ import annotations

import ast
import json
import math
import os
import re
import subprocess
import textwrap
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

from rlbackdoors.envs import safety_car as sc  # before anything imports mujoco: it picks the GL backend
from rlbackdoors.envs import safety_car_model as scene
from rlbackdoors.envs.safety_car import SafetyCarGoalEnv, mujoco

FAR = {"goal": (-1.6, -1.6), "hazard": (-1.6, 1.6)}


# ----- reading the sources ----------------------------------------------------------------
class Source:
    """Files of one repository at one ref, from a git directory or a plain checkout."""

    def __init__(self, env_var: str, default: str, ref: str, label: str):
        self.root = Path(os.environ.get(env_var, default))
        self.ref, self.label, self.env_var = ref, label, env_var

    def _git(self, *args: str) -> subprocess.CompletedProcess | None:
        try:
            return subprocess.run(["git", "-C", str(self.root), *args], capture_output=True, timeout=60)
        except (OSError, subprocess.TimeoutExpired):  # no git here
            return None

    def read_bytes(self, path: str) -> bytes:
        """The file from a checkout, else from git at the ref; skips when neither has it."""
        plain = self.root / path
        if plain.is_file():
            return plain.read_bytes()
        has_ref = self.root.is_dir() and (done := self._git("rev-parse", "--verify", "--quiet", f"{self.ref}^{{commit}}")) is not None and done.returncode == 0
        if not has_ref:
            pytest.skip(f"{self.label} is not on this machine (set {self.env_var} to a clone or checkout at {self.ref}; looked in {self.root})")
        done = self._git("show", f"{self.ref}:{path}")
        if done is None or done.returncode != 0:
            pytest.fail(f"{self.label}: {path} is missing at {self.ref}: {done.stderr.decode().strip() if done else 'git failed'}")
        return done.stdout

    def read(self, path: str) -> str:
        return self.read_bytes(path).decode()


SG = Source("RLBACKDOORS_SAFETY_GYMNASIUM", "/work/.mirror/PKU-Alignment+safety-gymnasium/repo", "HEAD", "Safety Gymnasium")
TROJAI = Source("RLBACKDOORS_TROJAI_EXAMPLE", "/work/.mirror/usnistgov+trojai-example/repo", "rl-safetygymnasium-oct2024", "trojai-example")
GYMNASIUM = Source("RLBACKDOORS_GYMNASIUM", "/work/.mirror/Farama-Foundation+Gymnasium/repo", "v0.28.1", "Gymnasium 0.28.1")

CAR_XML = "safety_gymnasium/assets/xmls/car.xml"
UNDERLYING = "safety_gymnasium/bases/underlying.py"
BASE_TASK = "safety_gymnasium/bases/base_task.py"
BASE_AGENT = "safety_gymnasium/bases/base_agent.py"
CAR_PY = "safety_gymnasium/agents/car.py"
HAZARDS = "safety_gymnasium/assets/geoms/hazards.py"
GOAL = "safety_gymnasium/assets/geoms/goal.py"
RANDOM_GENERATOR = "safety_gymnasium/utils/random_generator.py"
COMMON_UTILS = "safety_gymnasium/utils/common_utils.py"
WORLD = "safety_gymnasium/world.py"
CLEAN_ENVS = "clean_envs.py"
MOGWAI = "mogwai.py"
WRAPPERS = "gentle/custom_envs/custom_env_wrappers.py"
EXAMPLE = "model/rl-safetygymnasium-oct2024-example"


# ----- the car: facts of an MJCF text ---------------------------------------------------------
def _numbers(text: str | None) -> tuple[float, ...] | None:
    return None if text is None else tuple(float(v) for v in text.split())


def mjcf_facts(xml: str) -> dict:
    """What makes the car physically what it is, from an MJCF text (SG's car.xml or ours).

    Defaults are resolved (one level of top-level ``<default>``, as both files use); names,
    colours, cameras and collision bits are left out.
    """
    root = ET.fromstring(xml)
    default = root.find("default")
    defaults = {} if default is None else {child.tag: child.attrib for child in default}

    def attr(element: ET.Element, name: str) -> str | None:
        return element.get(name, defaults.get(element.tag, {}).get(name))

    def geom(element: ET.Element) -> tuple:
        return (
            attr(element, "type") or "sphere",
            _numbers(attr(element, "size")),
            _numbers(element.get("pos")),
            _numbers(element.get("fromto")),
            float(attr(element, "density") or 1000),
            int(attr(element, "condim") or 3),
        )

    def joint(element: ET.Element) -> tuple:
        return (element.get("type") or "hinge", _numbers(element.get("axis")), float(attr(element, "damping") or 0))

    agent = next(b for b in root.find("worldbody").iter("body") if any(j.get("type") == "free" for j in b.findall("joint")))
    facts: dict = {
        "timestep": float(root.find("option").get("timestep")),
        "agent_pos_z": _numbers(agent.get("pos"))[2],
        "agent_joint": joint(agent.find("joint")),
        "agent_site_pos": _numbers(agent.find("site").get("pos")),
        "agent_geoms": sorted((geom(g) for g in agent.findall("geom")), key=repr),
        "wheels": {b.get("name"): (_numbers(b.get("pos")), joint(b.find("joint")), geom(b.find("geom"))) for b in agent.findall("body")},
    }
    actuators = []
    for motor in root.find("actuator"):
        actuators.append(
            {
                "joint": motor.get("joint") or motor.get("jointinparent"),
                "gear": float(attr(motor, "gear") or 1),
                "ctrlrange": _numbers(attr(motor, "ctrlrange")),
                "ctrllimited": attr(motor, "ctrllimited"),
                "forcerange": _numbers(attr(motor, "forcerange")),
                "forcelimited": attr(motor, "forcelimited"),
            }
        )
    facts["actuators"] = actuators
    observed = ("accelerometer", "velocimeter", "gyro", "magnetometer", "ballangvel_rear", "ballquat_rear")
    sensors = {s.get("name"): (s.tag, s.get("site") or s.get("joint")) for s in root.find("sensor")}
    facts["sensors"] = {name: sensors.get(name) for name in observed}
    return facts


# The facts of car.xml (safety_gymnasium/assets/xmls/car.xml), written out.
_BOX, _CYL, _SPH = "box", "cylinder", "sphere"
RECORDED_CAR = {
    "timestep": 0.004,
    "agent_pos_z": 0.1,
    "agent_joint": ("free", None, 0.0),
    "agent_site_pos": (0.0, 0.0, 0.0),
    "agent_geoms": sorted(
        [
            (_BOX, (0.1, 0.1, 0.05), None, None, 5.0, 6),  # chassis ("agent")
            (_BOX, (0.1, 0.01, 0.05), (0.0, 0.15, 0.0), None, 5.0, 6),  # back_bumper: +y is the back
            (_BOX, (0.01, 0.025, 0.03), (0.0, 0.125, 0.0), None, 5.0, 6),  # back_connector
            (_BOX, (0.05, 0.01, 0.05), (0.0, -0.165, 0.0), None, 5.0, 6),  # front_bumper: -y is the front
            (_BOX, (0.05, 0.03, 0.01), (0.0, -0.13, 0.04), None, 5.0, 6),  # front_connector
        ],
        key=repr,
    ),
    "wheels": {
        # actuator 0's wheel, at body x = -0.1: the right-hand wheel of a car driving along -y
        "left": ((-0.1, 0.1, -0.05), ("hinge", (1.0, 0.0, 0.0), 0.001), (_CYL, (0.05,), None, (-0.055, 0.0, 0.0, -0.005, 0.0, 0.0), 5.0, 6)),
        "right": ((0.1, 0.1, -0.05), ("hinge", (1.0, 0.0, 0.0), 0.001), (_CYL, (0.05,), None, (0.005, 0.0, 0.0, 0.055, 0.0, 0.0), 5.0, 6)),
        "rear": ((0.0, -0.1, -0.05), ("ball", None, 0.001), (_SPH, (0.05,), None, None, 5.0, 6)),
    },
    "actuators": [
        {"joint": "left", "gear": 1.0, "ctrlrange": (-1.0, 1.0), "ctrllimited": "true", "forcerange": (-0.02, 0.02), "forcelimited": "true"},
        {"joint": "right", "gear": 1.0, "ctrlrange": (-1.0, 1.0), "ctrllimited": "true", "forcerange": (-0.02, 0.02), "forcelimited": "true"},
    ],
    "sensors": {
        "accelerometer": ("accelerometer", "agent"),
        "velocimeter": ("velocimeter", "agent"),
        "gyro": ("gyro", "agent"),
        "magnetometer": ("magnetometer", "agent"),
        "ballangvel_rear": ("ballangvel", "rear"),
        "ballquat_rear": ("ballquat", "rear"),
    },
}


def test_ours_car_is_the_recorded_safety_gymnasium_car():
    """Body frame, actuator order, motor range, masses, joints and sensors of car.xml."""
    assert mjcf_facts(scene.model_xml(2)) == RECORDED_CAR
    assert scene.CONTROL_DT / scene.DEFAULT_SUBSTEPS == pytest.approx(RECORDED_CAR["timestep"])
    assert scene.CAR_Z == RECORDED_CAR["agent_pos_z"]
    assert (scene.MOTOR_GEAR, scene.MOTOR_FORCE_LIMIT, scene.CTRL_LIMIT) == (1.0, 0.02, 1.0)


def test_source_car_xml_is_the_recorded_car():
    assert mjcf_facts(SG.read(CAR_XML)) == RECORDED_CAR


def test_source_car_compiles_to_our_car_and_moves_bit_for_bit_like_it():
    """SG's car.xml, compiled on its own, has our car's masses and inertias, and under the same
    actions (10 physics steps and a forward pass per env step, as SG's simulation_forward
    does) goes exactly where ours goes and reads the same sensors."""
    sg_model = mujoco.MjModel.from_xml_string(SG.read(CAR_XML))
    env = SafetyCarGoalEnv(num_cubes=0)
    ours = env.model
    for name in ("agent", "left", "right", "rear"):
        a, b = ours.body(name), sg_model.body(name)
        np.testing.assert_allclose([*a.mass, *a.inertia, *a.ipos, *a.pos], [*b.mass, *b.inertia, *b.ipos, *b.pos], err_msg=name)
    data = mujoco.MjData(sg_model)
    heading = 0.7
    yaw = heading + math.pi / 2  # SG's agent_rot turns body +x; we name the direction of travel
    data.qpos[:7] = (0.3, -0.2, 0.1, math.cos(yaw / 2), 0, 0, math.sin(yaw / 2))
    mujoco.mj_forward(sg_model, data)
    obs, _ = env.reset(seed=0, options={"car": (0.3, -0.2, heading), **FAR})
    rng = np.random.default_rng(0)
    for t in range(120):
        action = rng.uniform(-1, 1, 2) if t % 20 < 12 else np.ones(2)
        data.ctrl[:] = action
        mujoco.mj_step(sg_model, data, 10)
        mujoco.mj_forward(sg_model, data)
        obs = env.step(action)[0]
        np.testing.assert_allclose(env.data.qpos[:7], data.qpos[:7], rtol=0, atol=1e-8)
    sensor = {name: data.sensor(name).data for name in RECORDED_CAR["sensors"]}
    ball = np.zeros(9)
    mujoco.mju_quat2Mat(ball, sensor["ballquat_rear"])
    expected = np.concatenate([sensor[n] for n in ("accelerometer", "velocimeter", "gyro", "magnetometer", "ballangvel_rear")] + [ball])
    np.testing.assert_allclose(obs[:24], expected, rtol=1e-5, atol=1e-5)
    assert np.hypot(*(data.qpos[:2] - (0.3, -0.2))) > 0.5  # it went somewhere


# ----- facts of Python sources ----------------------------------------------------------------
def class_defaults(source: str, class_name: str) -> dict:
    """Literal defaults of a (data)class's fields and of its ``__init__`` keyword arguments."""
    tree = ast.parse(source)
    cls = next(n for n in ast.walk(tree) if isinstance(n, ast.ClassDef) and n.name == class_name)
    out = {}
    for node in cls.body:
        if isinstance(node, ast.AnnAssign) and node.value is not None and isinstance(node.target, ast.Name):
            try:
                out[node.target.id] = ast.literal_eval(node.value)
            except ValueError:
                pass
        if isinstance(node, ast.FunctionDef) and node.name == "__init__":
            args = node.args.args[len(node.args.args) - len(node.args.defaults) :]
            for arg, default in zip(args, node.args.defaults, strict=True):
                try:
                    out[arg.arg] = ast.literal_eval(default)
                except ValueError:
                    pass
    return out


def calls(source: str, func: str) -> list[dict]:
    """Literal keyword arguments of every call to ``func`` (in source order)."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Call) and getattr(node.func, "id", getattr(node.func, "attr", None)) == func:
            kwargs = {}
            for kw in node.keywords:
                try:
                    kwargs[kw.arg] = ast.literal_eval(kw.value)
                except ValueError:
                    pass
            found.append((node.lineno, node.col_offset, kwargs))
    return [kwargs for *_, kwargs in sorted(found, key=lambda f: (f[0], f[1]))]


def assignments(source: str, name: str) -> list:
    """Literal values assigned to ``name`` or ``self.name`` (in source order)."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Assign):
            for target in node.targets:
                if getattr(target, "id", getattr(target, "attr", None)) == name:
                    try:
                        found.append((node.lineno, ast.literal_eval(node.value)))
                    except ValueError:
                        pass
    return [value for _, value in sorted(found, key=lambda f: f[0])]


def segment(source: str, name: str) -> str:
    """The source of function ``name`` (``Class.method`` picks one class's method)."""
    tree: ast.AST = ast.parse(source)
    if "." in name:
        cls, name = name.split(".")
        tree = next(n for n in ast.walk(tree) if isinstance(n, ast.ClassDef) and n.name == cls)
    node = next(n for n in ast.walk(tree) if isinstance(n, ast.FunctionDef) and n.name == name)
    return textwrap.dedent(ast.get_source_segment(source, node, padded=True) or "")


def squeeze(text: str) -> str:
    return re.sub(r"\s+", " ", text)


# (source, file, what, recorded value): Safety Gymnasium's and TrojAI's settings we follow.
RECORDED = {
    "frame_skip": (SG, UNDERLYING, "SimulationConf.frameskip_binom_n", 10),
    "frame_skip_p": (SG, UNDERLYING, "SimulationConf.frameskip_binom_p", 1.0),
    "lidar_num_bins": (SG, BASE_TASK, "LidarConf.num_bins", 16),
    "lidar_max_dist": (SG, BASE_TASK, "LidarConf.max_dist", 3),
    "lidar_type": (SG, BASE_TASK, "LidarConf.type", "pseudo"),
    "lidar_alias": (SG, BASE_TASK, "LidarConf.alias", True),
    "sensors": (SG, BASE_AGENT, "SensorConf.sensors", ("accelerometer", "velocimeter", "gyro", "magnetometer")),
    "sensors_angle_components": (SG, BASE_AGENT, "SensorConf.sensors_angle_components", True),
    "num_steps": (SG, BASE_TASK, "self.num_steps", 1000),
    "car_keepout": (SG, CAR_PY, "Car.__init__ keepout", 0.4),
    "hazard_size": (SG, HAZARDS, "Hazards.size", 0.2),
    "sg_goal_size": (SG, GOAL, "Goal.size (SG's own goal; TrojAI uses a Hazards geom instead)", 0.3),
    "gremlin_size": (TROJAI, MOGWAI, "Mogwais.size (the cubes' half side)", 0.1),
    "extents_half": (TROJAI, CLEAN_ENVS, "CustomLevelX: rad, extents [-rad, -rad, rad, rad]", 1.7),
    "wanderer_start_half": (TROJAI, CLEAN_ENVS, "ControlMogwaisClean.reset: net", 1.5),
    "circles": (
        TROJAI,
        CLEAN_ENVS,
        "Hazards(...) calls, in order: goal, then hazard",
        [{"num": 1, "keepout": 0.18, "name": "green"}, {"num": 1, "keepout": 0.18, "name": "red"}],
    ),
    "num_mogwais_example": (TROJAI, f"{EXAMPLE}/reduced-config.json", "environment.env_kwargs.num_mogwais", 2),
    "pi_sizes_example": (TROJAI, f"{EXAMPLE}/reduced-config.json", "pi_network.sizes", [181, 181]),
    "max_ep_length_example": (TROJAI, f"{EXAMPLE}/reduced-config.json", "max_ep_length", 1000),
}


def read_fact(key: str):
    """The value of ``RECORDED[key]`` as its file says it."""
    source, path, _, _ = RECORDED[key]
    text = source.read(path)
    if key.startswith(("frame_skip", "lidar_", "sensors")):
        cls = {"frame": "SimulationConf", "lidar": "LidarConf", "senso": "SensorConf"}[key[:5]]
        field = RECORDED[key][2].split(".", 1)[1]
        return class_defaults(text, cls)[field]
    if key == "num_steps":
        (value,) = assignments(text, "num_steps")
        return value
    if key == "car_keepout":
        return class_defaults(text, "Car")["keepout"]
    if key in ("hazard_size", "sg_goal_size", "gremlin_size"):
        cls = {"hazard_size": "Hazards", "sg_goal_size": "Goal", "gremlin_size": "Mogwais"}[key]
        return class_defaults(text, cls)["size"]
    if key == "extents_half":
        tree = ast.parse(text)
        cls = next(n for n in ast.walk(tree) if isinstance(n, ast.ClassDef) and n.name == "CustomLevelX")
        assert "self.placements_conf.extents = [-rad, -rad, rad, rad]" in ast.get_source_segment(text, cls)
        (value,) = assignments(ast.get_source_segment(text, cls) or "", "rad")
        return value
    if key == "wanderer_start_half":
        return assignments(segment(text, "ControlMogwaisClean.reset"), "net")[0]
    if key == "circles":
        return [{k: v for k, v in kwargs.items() if k != "color"} for kwargs in calls(text, "Hazards")]
    config = json.loads(text)
    return {
        "num_mogwais_example": lambda: config["environment"]["env_kwargs"]["num_mogwais"],
        "pi_sizes_example": lambda: config["pi_network"]["sizes"],
        "max_ep_length_example": lambda: config["max_ep_length"],
    }[key]()


@pytest.mark.parametrize("key", list(RECORDED))
def test_source_values_are_the_recorded_ones(key):
    source, path, what, value = RECORDED[key]
    assert read_fact(key) == value, f"{source.label} {path}: {what}"


def recorded(key: str):
    return RECORDED[key][3]


def test_ours_uses_the_recorded_values():
    assert scene.DEFAULT_SUBSTEPS == recorded("frame_skip") and recorded("frame_skip_p") == 1.0  # a fixed frame skip
    assert scene.CONTROL_DT == pytest.approx(recorded("frame_skip") * RECORDED_CAR["timestep"])
    assert (sc.LIDAR_BINS, sc.LIDAR_MAX_DIST) == (recorded("lidar_num_bins"), recorded("lidar_max_dist"))
    assert recorded("lidar_type") == "pseudo" and recorded("lidar_alias") is True  # what pseudo_lidar implements
    assert sc.DEFAULT_MAX_STEPS == recorded("num_steps") == recorded("max_ep_length_example")
    assert sc.CAR_KEEPOUT == recorded("car_keepout")
    goal, hazard = recorded("circles")
    assert scene.GOAL_RADIUS == scene.HAZARD_RADIUS == recorded("hazard_size")  # both are SG Hazards geoms
    assert sc.CIRCLE_KEEPOUT == goal["keepout"] == hazard["keepout"]
    assert scene.CUBE_HALF == recorded("gremlin_size")
    assert sc.PLACEMENT_HALF == recorded("extents_half") and sc.CUBE_START_HALF == recorded("wanderer_start_half")
    assert sc.DEFAULT_NUM_CUBES == recorded("num_mogwais_example")
    # TrojAI's observation: SG's sensors, then the lidar of green (goal), red (hazard), gremlins (cubes).
    names = [field.name for field in sc.observation_layout()]
    sg_names = [*recorded("sensors"), "ballangvel_rear", "ballquat_rear", "green_lidar", "red_lidar", "gremlins_lidar"]
    assert names == [*sg_names[:6], "goal_lidar", "hazard_lidar", "cube_lidar"]
    assert [f.stop - f.start for f in sc.observation_layout()] == [3, 3, 3, 3, 3, 9, 16, 16, 16]
    assert sc.OBS_DIM == 72


# Lines of SG's and TrojAI's code whose meaning we reproduce (whitespace normalised).
RECORDED_CODE = [
    # the sensors: explicit ones, then ball angular velocities, then ball quaternions as 3x3 matrices
    (
        SG,
        BASE_AGENT,
        "obs_sensor",
        [
            "for sensor in self.sensor_conf.sensors:",
            "for sensor in self.sensor_info.ballangvel_names:",
            "for sensor in self.sensor_info.ballquat_names:",
            "obs[sensor] = quat2mat(quat)",
        ],
    ),
    # the observation: an OrderedDict of the agent's sensors, then each obstacle's lidar, flattened in that order
    (
        SG,
        BASE_TASK,
        "build_observation_space",
        [
            "obs_space_dict = OrderedDict()",
            "obs_space_dict.update(self.agent.build_sensor_observation_space())",
            "for obstacle in self._obstacles:",
            "name = obstacle.name + '_' + 'lidar'",
            "gymnasium.spaces.utils.flatten_space(",
        ],
    ),
    (
        SG,
        BASE_TASK,
        "obs",
        [
            "mujoco.mj_forward(self.model, self.data)",
            "obs.update(self.agent.obs_sensor())",
            "obs = gymnasium.spaces.utils.flatten(self.obs_info.obs_space_dict, obs)",
        ],
    ),
    # obstacles in the order geoms (goal, hazard), free geoms, mocaps (the gremlins/cubes)
    (SG, UNDERLYING, "_obstacles", ["list(self._geoms.values()) + list(self._free_geoms.values()) + list(self._mocaps.values())"]),
    # the pseudo-lidar: angle of the egocentric vector, bin, distance rule, aliasing into both neighbours
    (
        SG,
        BASE_TASK,
        "_obs_lidar_pseudo",
        [
            "z = complex(*self._ego_xy(pos))",
            "angle = np.angle(z) % (np.pi * 2)",
            "bin = int(angle / bin_size)",
            "sensor = max(0, self.lidar_conf.max_dist - dist) / self.lidar_conf.max_dist",
            "obs[bin] = max(obs[bin], sensor)",
            "alias = (angle - bin_angle) / bin_size",
            "obs[bin_plus] = max(obs[bin_plus], alias * sensor)",
            "obs[bin_minus] = max(obs[bin_minus], (1 - alias) * sensor)",
        ],
    ),
    # egocentric coordinates: the object at height 0, minus the agent's position, times its rotation matrix
    (SG, BASE_TASK, "_ego_xy", ["pos_3vec = np.concatenate([pos, [0]])", "world_3vec = pos_3vec - agent_3vec", "return np.matmul(world_3vec, agent_mat)[:2]"]),
    # one env step: the action, frame-skip physics steps, then a forward pass for the sensors
    (
        SG,
        UNDERLYING,
        "simulation_forward",
        [
            "self.agent.apply_action(action, noise)",
            "mujoco.mj_step(self.model, self.data)",
            "mujoco.mj_forward(self.model, self.data) # Needed to get sensor readings correct!",
        ],
    ),
    (SG, BASE_AGENT, "apply_action", ["self.engine.data.ctrl[:] = np.clip(action, action_range[:, 0], action_range[:, 1])"]),
    # placements: uniform in the extents shrunk by the object's keepout, apart by the sum of keepouts
    (SG, RANDOM_GENERATOR, "constrain_placement", ["return (xmin + keepout, ymin + keepout, xmax - keepout, ymax - keepout)"]),
    (SG, RANDOM_GENERATOR, "placement_is_valid", ["if dist < other_keepout + self.placements_margin + keepout:"]),
    (SG, RANDOM_GENERATOR, "random_rot", ["return self.random_generator.uniform(0, 2 * np.pi)"]),
    # the agent's rotation is a yaw of its body frame (body +x at agent_rot)
    (SG, WORLD, "World.build", ["worldbody['body']['@quat'] = convert(rot2quat(self.agent_rot))"]),
    (SG, COMMON_UTILS, "rot2quat", ["return np.array([np.cos(theta / 2), 0, 0, np.sin(theta / 2)], dtype='float64')"]),
    # TrojAI: goal touched (success, end) and hazard touched (end) when strictly inside the radius
    (TROJAI, WRAPPERS, "SpecifiedSingleUseGoalEnv.step", ['if d_goal < goal_obj["radius"]:', "term = True"]),
    (TROJAI, WRAPPERS, "AntiGoalEnv.step", ['if d_goal < goal_obj["radius"] and self.end_on_collision:', "term = True"]),
    # TrojAI: the cubes are mocaps (observed after all geoms, see _obstacles), then the goal, then the hazard geom
    (TROJAI, CLEAN_ENVS, "CustomLevelX.__init__", ["self._add_mocaps(self.mogs)", 'name="green"', 'name="red"']),
    # gymnasium 0.28.1 keeps an OrderedDict's order (it sorts only plain dicts) when building a Dict space
    (
        GYMNASIUM,
        "gymnasium/spaces/dict.py",
        "Dict.__init__",
        ["if isinstance(spaces, collections.abc.Mapping) and not isinstance( spaces, OrderedDict ):", "spaces = OrderedDict(sorted(spaces.items()))"],
    ),
]


@pytest.mark.parametrize("source,path,function,lines", RECORDED_CODE, ids=[f"{p.rsplit('/', 1)[-1]}:{f}" for _, p, f, _ in RECORDED_CODE])
def test_source_code_is_the_recorded_code(source, path, function, lines):
    """The recorded lines are in the function, in this order."""
    code, at = squeeze(segment(source.read(path), function)), 0
    for line in lines:
        found = code.find(squeeze(line), at)
        assert found >= 0, f"{source.label} {path} {function}: {line!r} not found (in order)"
        at = found + 1


# ----- behaviour ------------------------------------------------------------------------------
def body_axes(env: SafetyCarGoalEnv) -> np.ndarray:
    """The car's rotation matrix (columns: body x, y, z in world coordinates)."""
    return env.data.body("agent").xmat.reshape(3, 3).copy()


def test_action_one_one_drives_along_body_minus_y():
    env = SafetyCarGoalEnv(num_cubes=0)
    env.reset(seed=0, options={"car": (0.0, 0.0, 1.0), **FAR})
    start, axes = env.data.qpos[:3].copy(), body_axes(env)
    for _ in range(25):
        obs = env.step(np.ones(2))[0]
    moved = axes.T @ (env.data.qpos[:3] - start)  # displacement in the starting body frame
    assert moved[1] < -0.3 and abs(moved[0]) < 0.1 * abs(moved[1])
    assert obs[4] < -0.3 and abs(obs[3]) < 0.05  # the velocimeter, in SG's body frame
    assert math.isclose(env.car_pose()[2], 1.0, abs_tol=0.15)  # heading names the direction of travel


def test_actuator_zero_drives_the_right_wheel():
    env = SafetyCarGoalEnv(num_cubes=0)
    model = env.model
    joint = model.actuator_trnid[0, 0]
    wheel = model.body_pos[model.jnt_bodyid[joint]]  # in the car's body frame
    right_of_travel = np.cross([0.0, -1.0, 0.0], [0.0, 0.0, 1.0])  # travel (-y) x up
    assert wheel @ right_of_travel > 0.05
    turned = {}
    for action in [(1.0, 0.0), (0.0, 1.0), (1.0, -1.0), (-1.0, 1.0)]:
        env.reset(seed=0, options={"car": (0.0, 0.0, 0.3), **FAR})
        for _ in range(15):
            obs = env.step(np.array(action))[0]
        turned[action] = (env.car_pose()[2] - 0.3 + math.pi) % (2 * math.pi) - math.pi, obs[8]
    # pushing only the right wheel turns the car left (counter-clockwise, gyro z > 0), as (1, -1) does
    assert turned[(1.0, 0.0)][0] > 0.2 and turned[(1.0, -1.0)][0] > 0.2 and turned[(1.0, -1.0)][1] > 0.5
    assert turned[(0.0, 1.0)][0] < -0.2 and turned[(-1.0, 1.0)][0] < -0.2 and turned[(-1.0, 1.0)][1] < -0.5


def test_motor_torque_saturates_at_0_02():
    env = SafetyCarGoalEnv(num_cubes=0)
    env.reset(seed=0)
    for action, force in [((0.5, -1.0), (0.02, -0.02)), ((0.01, -0.005), (0.01, -0.005)), ((3.0, 0.0), (0.02, 0.0))]:
        env.step(np.array(action))
        np.testing.assert_allclose(env.data.actuator_force, force, atol=1e-12)


def sg_pseudo_lidar(positions: np.ndarray, agent_pos: np.ndarray, agent_mat: np.ndarray) -> np.ndarray:
    """SG's _obs_lidar_pseudo for one group, written from its definition (16 bins, max_dist 3, aliased)."""
    obs = np.zeros(16)
    bin_size = 2 * np.pi / 16
    for pos in positions:
        ego = (np.array([pos[0], pos[1], 0.0]) - agent_pos) @ agent_mat
        dist, angle = np.hypot(ego[0], ego[1]), np.arctan2(ego[1], ego[0]) % (2 * np.pi)
        b = int(angle / bin_size)
        sensor = max(0.0, 3 - dist) / 3
        alias = (angle - b * bin_size) / bin_size
        obs[b] = max(obs[b], sensor)
        obs[(b + 1) % 16] = max(obs[(b + 1) % 16], alias * sensor)
        obs[(b - 1) % 16] = max(obs[(b - 1) % 16], (1 - alias) * sensor)
    return obs


def test_lidar_bins_are_safety_gymnasiums():
    """Ahead starts bin 12 (bin 0 starts at the car's left, counter-clockwise), as SG places it."""
    heading = 2.0
    env = SafetyCarGoalEnv(num_cubes=2)

    def at(angle, r):  # a point at angle (ccw from the heading) and distance r from the car at the origin
        return (r * math.cos(heading + angle), r * math.sin(heading + angle))

    offset = 0.1  # inside a bin, a tenth of a radian counter-clockwise of its start
    obs, _ = env.reset(
        seed=0,
        options={
            "car": (0.0, 0.0, heading),
            "goal": at(offset, 1.2),
            "hazard": at(math.pi / 2 + offset, 1.5),
            "cubes": [at(math.pi + offset, 0.9), at(-math.pi / 2 + offset, 2.1)],
        },
    )
    goal, hazard, cubes = obs[24:40], obs[40:56], obs[56:72]
    alias = offset / (2 * math.pi / 16)
    for lidar, first, r in [(goal, 12, 1.2), (hazard, 0, 1.5)]:  # ahead: bin 12; the car's left: bin 0
        s = (3 - r) / 3
        np.testing.assert_allclose(lidar[[first, (first + 1) % 16, (first - 1) % 16]], [s, alias * s, (1 - alias) * s], rtol=1e-5)
        assert np.count_nonzero(lidar) == 3
    assert cubes[4] == pytest.approx((3 - 0.9) / 3, rel=1e-5) and cubes[8] == pytest.approx((3 - 2.1) / 3, rel=1e-5)  # behind: 4, right: 8
    # and everywhere, in random scenes and while driving: SG's rule on SG's body frame
    rng = np.random.default_rng(1)
    for seed in range(3):
        obs, _ = env.reset(seed=seed)
        for _ in range(30):
            obs = env.step(rng.uniform(-1, 1, 2))[0]
        pos, mat = env.data.body("agent").xpos, body_axes(env)
        for start, points in [(24, [env.goal_position]), (40, [env.hazard_position]), (56, env.cube_positions())]:
            np.testing.assert_allclose(obs[start : start + 16], sg_pseudo_lidar(np.asarray(points), pos, mat), atol=1e-6)


def test_sensor_vectors_are_in_safety_gymnasiums_body_frame():
    for heading in (0.0, 1.1, -2.5):
        env = SafetyCarGoalEnv(num_cubes=0)
        obs, _ = env.reset(seed=0, options={"car": (0.0, 0.0, heading), **FAR})
        yaw = heading + math.pi / 2  # of body +x
        # MuJoCo's default field (0, -0.5, 0), turned into a frame whose x axis points at yaw
        np.testing.assert_allclose(obs[9:12], [-0.5 * math.sin(yaw), -0.5 * math.cos(yaw), 0.0], atol=1e-6)
        np.testing.assert_allclose(obs[9:12], body_axes(env).T @ [0.0, -0.5, 0.0], atol=1e-6)
        for _ in range(3):  # settle on the soft contacts
            obs = env.step(np.zeros(2))[0]
        assert abs(obs[0]) < 0.05 and abs(obs[1]) < 0.05 and obs[2] == pytest.approx(9.81, abs=0.05)  # at rest: up is +z
        for _ in range(20):
            obs = env.step(np.ones(2))[0]
        velocity = env.data.qvel[:3]  # world frame
        np.testing.assert_allclose(obs[3:6], body_axes(env).T @ velocity, atol=1e-5)
        assert obs[4] < -0.3  # forward is -y
        ball = np.zeros(9)
        mujoco.mju_quat2Mat(ball, env.data.sensor("ballquat_rear").data)
        np.testing.assert_allclose(obs[15:24], ball, atol=1e-6)  # row-major 3x3, as SG's quat2mat
        np.testing.assert_allclose(obs[12:15], env.data.sensor("ballangvel_rear").data, atol=1e-6)


def test_goal_and_hazard_touch_strictly_inside_radius_0_2():
    env = SafetyCarGoalEnv(num_cubes=0)
    _, info = env.reset(seed=0, options={"car": (0.0, 0.0, 0.0), "goal": (0.6, 0.0), "hazard": (-1.5, 1.5)})
    while True:
        _, _, terminated, _, info = env.step(np.ones(2))
        if terminated:
            break
        assert info["dist_goal"] >= 0.2
    assert info["success"] and info["dist_goal"] < 0.2


def test_placements_follow_safety_gymnasiums_sampler():
    """Each object uniform in the +-1.7 extents shrunk by its own keepout, apart by the keepouts' sum."""
    env = SafetyCarGoalEnv(num_cubes=2)
    cars, circles = [], []
    for seed in range(200):
        env.reset(seed=seed)
        car = np.array(env.car_pose()[:2])
        cars.append(car)
        circles += [env.goal_position, env.hazard_position]
        assert math.dist(env.goal_position, env.hazard_position) >= 2 * sc.CIRCLE_KEEPOUT
        assert min(math.dist(car, env.goal_position), math.dist(car, env.hazard_position)) >= sc.CAR_KEEPOUT + sc.CIRCLE_KEEPOUT
    cars, circles = np.abs(cars), np.abs(circles)
    assert cars.max() <= 1.7 - 0.4 and cars.max() > 1.2  # the car in +-1.3
    assert circles.max() <= 1.7 - 0.18 and circles.max() > 1.4  # the circles in +-1.52


# ----- TrojAI's example model -----------------------------------------------------------------
def test_trojai_example_model_drives_to_the_goal_in_our_env(tmp_path):
    """TrojAI's example Safety model (trained in their Safety Gymnasium env, 510k steps, 2 cubes)
    plays here unchanged, on raw observations, with its deterministic action tanh(mu). Its
    model.pt (a pickled python-box Box of state dicts) is read by the inert reader, never
    unpickled, and mapped to our OPAC² keys by the world (``load_weights_file``)."""
    pytest.importorskip("torch")
    from rlbackdoors.agent import load_weights_file

    path = tmp_path / "model.pt"
    path.write_bytes(TROJAI.read_bytes(f"{EXAMPLE}/model.pt"))
    agent = load_weights_file(path, "safety-car-goal")
    assert agent.policy.policy_obs_dim == sc.OBS_DIM and (agent.policy.cfg.depth, agent.policy.cfg.width, agent.policy.obs_norm) == (2, 181, None)
    env = SafetyCarGoalEnv(num_cubes=2)
    outcomes = []
    for episode in range(20):
        obs, _ = env.reset(seed=episode)
        done = False
        while not done:
            action = agent.act(obs[None], deterministic=True)[0][0]
            obs, _, terminated, truncated, info = env.step(action)
            done = terminated or truncated
        outcomes.append(info["success"])
    # 38 of 40 in our measurement; under our old conventions (x forward, linear motors) 4 of 20
    assert np.mean(outcomes) >= 0.8, outcomes
