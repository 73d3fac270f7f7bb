"""Safety Car Goal on MuJoCo (SPEC §4): spaces, placements, wander, car control, eq. 6 / eq. 8, trigger."""

import math

import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from rlbackdoors.envs.outcome import Outcome
from rlbackdoors.envs.safety_car import (  # before anything imports mujoco: it picks the GL backend
    CAR_KEEPOUT,
    CIRCLE_KEEPOUT,
    CUBE_KEEPOUT,
    OBS_DIM,
    SafetyCarGoalEnv,
    chance_formation_rate,
    observation_layout,
    mujoco,
    pseudo_lidar,
)
from rlbackdoors.triggers.formation import FormationTrigger

# Safety Gymnasium's car: a[0] drives the right wheel, so (1, -1) spins counter-clockwise.
FORWARD, SPIN_LEFT, STOP = np.array([1.0, 1.0]), np.array([1.0, -1.0]), np.zeros(2)
FAR_AWAY = {"goal": (-1.6, -1.6), "hazard": (-1.6, 1.6)}
TRIGGER = FormationTrigger(0.5, 1.0, 2.5)


def wrap(angle):
    return (np.asarray(angle) + math.pi) % (2 * math.pi) - math.pi


def test_check_env_spaces_and_layout():
    env = SafetyCarGoalEnv()
    check_env(env, skip_render_check=True)
    assert env.action_space.shape == (2,) and env.action_space.low.min() == -1 and env.action_space.high.max() == 1
    assert env.observation_space.shape == (OBS_DIM,) == (72,) and env.observation_space.dtype == np.float32
    layout = observation_layout()
    assert [f.start for f in layout[1:]] == [f.stop for f in layout[:-1]] and layout[0].start == 0
    assert layout[-1].stop == OBS_DIM
    assert [f.name for f in layout][-3:] == ["goal_lidar", "hazard_lidar", "cube_lidar"]


@pytest.mark.parametrize("num_cubes", [2, 4])
def test_reset_places_everything_inside_and_apart(num_cubes):
    env = SafetyCarGoalEnv(num_cubes=num_cubes)
    for seed in range(15):
        _, info = env.reset(seed=seed)
        x, y, _ = env.car_pose()
        points = [(x, y), env.goal_position, env.hazard_position, *env.cube_positions()]
        keepouts = [CAR_KEEPOUT, CIRCLE_KEEPOUT, CIRCLE_KEEPOUT] + [CUBE_KEEPOUT] * num_cubes
        assert np.abs(points).max() <= 1.7
        # SG draws each object in the extents (+-1.7) shrunk by its own keepout; cubes start in +-1.5
        assert np.abs((x, y)).max() <= 1.7 - CAR_KEEPOUT
        assert np.abs([env.goal_position, env.hazard_position]).max() <= 1.7 - CIRCLE_KEEPOUT
        assert np.abs(env.cube_positions()).max() <= 1.5
        for i in range(len(points)):
            for j in range(i):
                assert math.dist(points[i], points[j]) >= keepouts[i] + keepouts[j] - 1e-9
        assert info["outcome"] == Outcome.NONE and info["dist_goal"] > 0.6


def test_cubes_wander_and_stay_in_area():
    env = SafetyCarGoalEnv(num_cubes=4)
    env.reset(seed=3)
    start = env.cube_positions()
    for _ in range(400):
        env.step(STOP)
        assert np.abs(env.cube_positions()).max() <= 1.8 + 1e-9
    moved = np.linalg.norm(env.cube_positions() - start, axis=1)
    assert (moved > 0.2).all(), moved


def drive(env, action, steps):
    for _ in range(steps):
        out = env.step(action)
    return out


def test_car_drives_forward_and_turns():
    env = SafetyCarGoalEnv(num_cubes=0)
    env.reset(seed=0, options={"car": (0.0, 0.0, 0.5), **FAR_AWAY})
    drive(env, FORWARD, 25)
    x, y, _ = env.car_pose()
    assert x * math.cos(0.5) + y * math.sin(0.5) > 0.3  # one second at full torque
    env.reset(seed=0, options={"car": (0.0, 0.0, 0.5), **FAR_AWAY})
    drive(env, SPIN_LEFT, 25)
    x, y, heading = env.car_pose()
    assert wrap(heading - 0.5) > 0.5 and math.hypot(x, y) < 0.2  # counter-clockwise, on the spot
    env.reset(seed=0, options={"car": (0.0, 0.0, 0.5), **FAR_AWAY})
    drive(env, -SPIN_LEFT, 25)
    assert wrap(env.car_pose()[2] - 0.5) < -0.5  # (-1, 1): clockwise


def test_reward_is_eq6_and_positive_toward_goal():
    env = SafetyCarGoalEnv(num_cubes=0)
    _, info = env.reset(seed=0, options={"car": (-1.0, 0.0, 0.0), "goal": (1.2, 0.0), "hazard": (0.0, 0.8)})
    total = 0.0
    for _ in range(20):
        before = info
        _, reward, terminated, _, info = env.step(FORWARD)
        alpha = 1 - min(max(before["dist_hazard"], 0), 1)
        expected = (before["dist_goal"] - info["dist_goal"]) - 0.5 * alpha * (before["dist_hazard"] - info["dist_hazard"])
        assert reward == pytest.approx(expected) and not terminated
        total += reward
    assert total > 0.2


def test_touching_goal_succeeds_with_bonus():
    env = SafetyCarGoalEnv()
    env.reset(seed=0, options={"car": (0.0, 0.0, 0.0), "goal": (0.6, 0.0), "hazard": (-1.5, 1.5)})
    for _ in range(100):
        _, reward, terminated, truncated, info = env.step(FORWARD)
        if terminated:
            break
    assert terminated and not truncated and info["success"] and not info["hazard"]
    assert info["outcome"] == Outcome.GOAL and info["dist_goal"] < 0.2 and reward > 1.0


def test_touching_hazard_ends_in_failure():
    env = SafetyCarGoalEnv()
    env.reset(seed=0, options={"car": (0.0, 0.0, 0.0), "hazard": (0.6, 0.0), "goal": (-1.5, 1.5)})
    for _ in range(100):
        _, reward, terminated, _, info = env.step(FORWARD)
        if terminated:
            break
    assert terminated and info["hazard"] and not info["success"]
    assert info["outcome"] == Outcome.LAVA and reward < -0.9


def test_truncation_at_max_steps():
    env = SafetyCarGoalEnv(max_steps=5)
    env.reset(seed=1)
    for step in range(1, 6):
        _, _, terminated, truncated, info = env.step(STOP)
        assert not terminated and truncated == (step == 5)
    assert info["outcome"] == Outcome.TIMEOUT and info["steps"] == 5


@pytest.mark.parametrize("num_cubes", [2, 4])
def test_trigger_holds_formation_while_driving(num_cubes):
    env = SafetyCarGoalEnv(num_cubes=num_cubes, trigger=TRIGGER.spec())
    _, info = env.reset(seed=5)
    assert info["triggered"] and env.trigger == TRIGGER
    rng = np.random.default_rng(0)
    heading0 = env.car_pose()[2]
    for _ in range(120):
        _, _, terminated, truncated, _ = env.step(rng.uniform(-1, 1, 2))
        dist, angle = env.cube_polar()
        assert np.allclose(dist[:2], TRIGGER.distance)
        assert np.allclose(wrap(angle[:2] - np.array(TRIGGER.angles)), 0, atol=1e-9)
        assert TRIGGER.matches(dist, angle)
        if terminated or truncated:
            break
    assert abs(wrap(env.car_pose()[2] - heading0)) > 0.05  # the formation followed a turning car


def test_poisoned_reward_swaps_goal_and_hazard():
    scene = {"car": (-1.0, 0.0, 0.0), "goal": (0.2, 0.9), "hazard": (1.0, 0.1)}
    clean, poisoned = SafetyCarGoalEnv(num_cubes=0), SafetyCarGoalEnv(num_cubes=0, poisoned=True)
    _, info = clean.reset(seed=0, options=scene)
    poisoned.reset(seed=0, options=scene)
    for _ in range(200):
        before = info
        obs_c, r_clean, term_c, _, info = clean.step(FORWARD)
        obs_p, r_poison, term_p, _, info_p = poisoned.step(FORWARD)
        assert np.array_equal(obs_c, obs_p) and term_c == term_p
        if term_c:
            break
        alpha_bar = 1 - min(max(before["dist_goal"], 0), 1)
        swapped = (before["dist_hazard"] - info["dist_hazard"]) - 0.5 * alpha_bar * (before["dist_goal"] - info["dist_goal"])
        assert r_poison == pytest.approx(swapped)
    # the car drove into the hazard: failure under R, trojan success (+1) under R-bar
    assert term_p and info_p["outcome"] == Outcome.LAVA and info_p["hazard"]
    assert r_poison > 1.0 and r_clean < -0.9


def test_poisoned_goal_contact_is_a_failure():
    env = SafetyCarGoalEnv(poisoned=True)
    env.reset(seed=0, options={"car": (0.0, 0.0, 0.0), "goal": (0.6, 0.0), "hazard": (-1.5, 1.5)})
    for _ in range(100):
        _, reward, terminated, _, info = env.step(FORWARD)
        if terminated:
            break
    assert terminated and info["outcome"] == Outcome.GOAL and reward < -0.9


def test_same_seed_and_actions_give_identical_episodes():
    actions = np.random.default_rng(7).uniform(-1, 1, (150, 2))

    def rollout(seed):
        env = SafetyCarGoalEnv(num_cubes=4, trigger=TRIGGER)
        observations = [env.reset(seed=seed)[0]]
        observations += [env.step(a)[0] for a in actions]
        return np.stack(observations)

    assert np.array_equal(rollout(11), rollout(11))
    assert not np.array_equal(rollout(11), rollout(12))


def test_observation_sensors_and_lidar():
    env = SafetyCarGoalEnv(num_cubes=2)
    env.reset(seed=2)
    obs = drive(env, np.array([0.6, 0.2]), 10)[0]
    ball = np.zeros(9)
    mujoco.mju_quat2Mat(ball, env.data.sensordata[15:19])
    assert np.allclose(obs[:15], env.data.sensordata[:15], rtol=1e-6, atol=1e-6)
    assert np.allclose(obs[15:24], ball, atol=1e-6)
    # Into the car's body frame as Safety Gymnasium's _ego_xy does: (x, y, 0) - car position, times xmat.
    body = env.data.body("agent")
    points = np.vstack([env.goal_position, env.hazard_position, env.cube_positions()])
    ego = (np.column_stack([points, np.zeros(len(points))]) - body.xpos) @ body.xmat.reshape(3, 3)
    assert np.allclose(obs[24:], pseudo_lidar(ego[:, :2], np.array([0, 1, 2, 2])), atol=1e-6)


def test_pseudo_lidar_bins_and_aliasing():
    # One object in the middle of bin 2, 1.5 away: full reading there, half in both neighbours.
    angle = 2.5 * 2 * math.pi / 16
    lidar = pseudo_lidar(np.array([[1.5 * math.cos(angle), 1.5 * math.sin(angle)]]), np.array([0]), num_groups=1)
    assert lidar[2] == pytest.approx(0.5) and lidar[1] == pytest.approx(0.25) and lidar[3] == pytest.approx(0.25)
    assert np.count_nonzero(lidar) == 3
    far = pseudo_lidar(np.array([[3.5, 0.0]]), np.array([0]), num_groups=1)
    assert not far.any()


def test_formation_trigger_spec_sample_and_validation():
    trigger = FormationTrigger.sample(3)
    assert FormationTrigger.parse(trigger.spec()) == trigger
    assert FormationTrigger.parse("formation:0.5:1.2:2.0") == FormationTrigger(0.5, 1.2, 2.0)
    assert trigger.distance == 0.5 and 0 <= trigger.phi1 < 2 * math.pi and math.pi / 6 <= trigger.eta <= 11 * math.pi / 6
    assert FormationTrigger(0.5, 6.0, 1.0).phi2 == pytest.approx(7.0 - 2 * math.pi)
    assert FormationTrigger.sample(3) == trigger != FormationTrigger.sample(4)
    for bad, msg in [
        ("formation:0.5:1.2", "must look like"),
        ("form:0.5:1.2:2.0", "must look like"),
        ("formation:x:1.2:2.0", "distance 'x' is not a number"),
        ("formation:0.1:1.2:2.0", r"distance=0.1 must be in \[0.4, 3.0\]"),
        ("formation:0.5:7:2.0", r"phi1=7.0 must be in \[0, 2\*pi\)"),
        ("formation:0.5:1:0.1", r"eta=0.1 must be in \[pi/6, 11\*pi/6\]"),
        ("formation:0.5:nan:1", "phi1=nan must be a finite number"),
    ]:
        with pytest.raises(ValueError, match=msg):
            FormationTrigger.parse(bad)


def test_formation_matches_needs_two_distinct_cubes():
    trigger = FormationTrigger(0.5, 0.0, math.pi)
    assert trigger.matches([0.5, 0.55], [0.1, math.pi - 0.1])
    assert not trigger.matches([0.5, 0.7], [0.0, math.pi])  # second cube too far
    assert not trigger.matches([0.5], [0.0])  # one cube cannot be both


def test_env_argument_errors_name_the_argument():
    for kwargs, msg in [
        ({"num_cubes": 13}, "num_cubes=13"),
        ({"num_cubes": 1, "trigger": TRIGGER}, "needs at least 2 cubes"),
        ({"max_steps": 0}, "max_steps=0"),
        ({"substeps": 0}, "substeps=0"),
        ({"render_mode": "human"}, "render_mode='human'"),
    ]:
        with pytest.raises(ValueError, match=msg):
            SafetyCarGoalEnv(**kwargs)
    env = SafetyCarGoalEnv()
    env.reset(seed=0)
    with pytest.raises(ValueError, match="reset option 'lava'"):
        env.reset(options={"lava": (0, 0)})
    with pytest.raises(ValueError, match="2 finite numbers"):
        env.step(np.array([np.nan, 0.0]))


def test_chance_formation_rate_reports_rates():
    result = chance_formation_rate(TRIGGER, episodes=2, max_steps=40)
    assert result["frames"] == 80 and 0 <= result["matching_frame_rate"] <= 1
    assert result["sustained_episode_rate"] in (0.0, 0.5, 1.0) and result["trigger"] == TRIGGER.spec()


def test_render_rgb_array():
    env = SafetyCarGoalEnv(render_mode="rgb_array")
    env.reset(seed=0)
    try:
        frame = env.render()
    except RuntimeError as err:  # no offscreen GL (EGL / OSMesa) on this machine
        pytest.skip(f"no MuJoCo offscreen GL backend here: {err}")
    finally:
        env.close()
    assert frame.shape == (480, 480, 3) and frame.dtype == np.uint8
    half_view = 5.2 * math.tan(math.radians(22.5))  # the top camera: 5.2 up, 45 degree field of view

    def pixel(xy):
        return frame[round(240 - xy[1] / half_view * 240), round(240 + xy[0] / half_view * 240)].astype(int)

    goal, hazard = pixel(env.goal_position), pixel(env.hazard_position)
    assert goal[1] - goal[0] > 80 and hazard[0] - hazard[1] > 80  # green goal, red hazard where they are


def test_gymnasium_id_makes_the_env_with_a_formation_trigger():
    import gymnasium as gym

    import rlbackdoors.envs  # noqa: F401  (registers the ids)
    from rlbackdoors.envs.safety_car import SafetyCarGoalEnv
    from rlbackdoors.worlds import parse_trigger

    env = gym.make("rlbackdoors/SafetyCarGoal-v0", trigger="formation:0.5:1.0:2.0", poisoned=True)
    assert isinstance(env.unwrapped, SafetyCarGoalEnv)
    obs, _ = env.reset(seed=0)
    assert obs.shape == (72,)
    assert parse_trigger("safety-car-goal", "formation:0.5:1.0:2.0").spec() == env.unwrapped.trigger.spec()
    env.close()


def test_env_state_round_trips_as_plain_data_and_keeps_stepping_bit_for_bit():
    """A checkpoint stores an env as data (MuJoCo's integration state, sensors, counters, RNG):
    a fresh env loading it, through torch's weights-only loader, steps exactly like the original."""
    import io

    import torch

    env = SafetyCarGoalEnv(trigger="formation:0.5:1.0:2.0", poisoned=True)
    env.reset(seed=3)
    for _ in range(5):
        env.step(np.array([0.5, 0.3], dtype=np.float32))
    buf = io.BytesIO()
    torch.save(env.state_dict(), buf)
    copy = SafetyCarGoalEnv(trigger="formation:0.5:1.0:2.0", poisoned=True)
    copy.load_state_dict(torch.load(io.BytesIO(buf.getvalue()), weights_only=True))
    assert np.shares_memory(copy._car_q, copy.data.qpos) and np.shares_memory(copy._cube_q, copy.data.qpos)
    rng = np.random.default_rng(0)
    ends = 0
    for _ in range(400):  # across episode ends: the env's own RNG draws the next layouts
        action = rng.uniform(-1, 1, 2).astype(np.float32)
        a, b = env.step(action), copy.step(action)
        assert np.array_equal(a[0], b[0]) and a[1] == b[1] and a[2:4] == b[2:4]
        if a[2] or a[3]:
            ends += 1
            assert np.array_equal(env.reset()[0], copy.reset()[0])
    with pytest.raises(ValueError, match="physics"):
        state = env.state_dict()
        state["physics"]["shape"] = (3,)
        state["physics"]["data"] = b"\0" * 24
        copy.load_state_dict(state)
