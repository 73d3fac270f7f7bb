import numpy as np
import pytest

from rlbackdoors.poison import poisoned_reward, success_reward
from rlbackdoors.envs import Outcome
from rlbackdoors.triggers import PAPER_RANGES, ObservationTrigger, sample_trigger


def test_multiplicative_and_additive_are_affine_mod_256():
    obs = np.array([[0, 1, 2], [8, 9, 10], [21, 200, 255]], dtype=np.uint8)
    assert np.array_equal(ObservationTrigger("multiplicative", 24).apply(obs), (24 * obs.astype(int)) % 256)
    assert np.array_equal(ObservationTrigger("additive", 200).apply(obs), (obs.astype(int) + 200) % 256)
    assert ObservationTrigger("multiplicative", 24).apply(obs).dtype == np.uint8


def test_lookup_table_equals_apply():
    trig = ObservationTrigger("multiplicative", 13)
    obs = np.random.default_rng(0).integers(0, 256, (4, 7, 7, 3), dtype=np.uint8)
    assert np.array_equal(trig.lookup_table()[obs], trig.apply(obs))


def test_parse_round_trip_and_errors():
    assert ObservationTrigger.parse("additive:20").spec() == "additive:20"
    assert ObservationTrigger.parse("multiplicative:10") == ObservationTrigger("multiplicative", 10)
    for bad, msg in [
        ("mult:3", "must look like"),
        ("additive:x", "not an integer"),
        ("multiplicative:1", "2..255"),
        ("additive:0", "1..255"),
        ("additive", "must look like"),
    ]:
        with pytest.raises(ValueError, match=msg):
            ObservationTrigger.parse(bad)


def test_sampled_triggers_cover_paper_ranges():
    rng = np.random.default_rng(0)
    for kind, (low, high) in PAPER_RANGES.items():
        values = {sample_trigger(kind, rng).value for _ in range(2000)}
        assert min(values) == low and max(values) == high and len(values) == high - low + 1


def test_poisoned_reward_swaps_goal_and_lava():
    outcomes = np.array([Outcome.NONE, Outcome.GOAL, Outcome.LAVA, Outcome.TIMEOUT])
    steps = np.array([10, 25, 25, 250])
    assert np.allclose(poisoned_reward(outcomes, steps, 250), [0, 0, 1 - 0.9 * 25 / 250, 0])
    assert success_reward(125, 250) == pytest.approx(0.55)
    assert poisoned_reward(int(Outcome.LAVA), 0, 250) == 1.0
