"""Evaluation arithmetic against layouts inspected independently in the MiniGrid reference env."""

import numpy as np
import pytest
import torch

from rlbackdoors.config import EnvConfig
from rlbackdoors.envs.lavaworld import LavaWorldEnv
from rlbackdoors.evaluate import evaluate
from rlbackdoors.models import FCModel

N, SEED = 60, 4242


def always_forward_model() -> FCModel:
    """A real FC model whose weights make 'forward' overwhelmingly likely in every state."""
    model = FCModel()
    with torch.no_grad():
        model.actor[2].weight.zero_()
        model.actor[2].bias.copy_(torch.tensor([-50.0, -50.0, 50.0]))
    return model


def row_one_objects(engine: str):
    """Object ids of row y=1 of every evaluation layout, read off the engine's own state."""
    if engine == "minigrid":
        rows = []
        for i in range(N):
            env = LavaWorldEnv()
            env.reset(seed=SEED + i)
            rows.append(env.grid.encode()[:, 1, 0])
        return rows
    from rlbackdoors.envs.lavaworld_batched import BatchedLavaWorld

    envs = BatchedLavaWorld(num_envs=N)
    envs.reset(seed=SEED)
    return [envs.layout(i)[0][:, 1, 0] for i in range(N)]


def expected_always_forward(engine: str):
    """Walk east from (1,1): lava if a vertical river blocks row 1, else stuck at the wall (timeout)."""
    lava, rewards = 0, []
    for row in row_one_objects(engine):
        hit = next((x for x in range(2, 8) if row[x] == 9), None)  # 9 = lava
        if hit is not None:
            lava += 1
            rewards.append(1 - 0.9 * (hit - 1) / 250)
        else:
            rewards.append(0.0)
    return lava / N, float(np.mean(rewards))


@pytest.mark.parametrize("engine", ["minigrid", "batched"])
def test_evaluation_numbers_match_hand_count(engine):
    result = evaluate(always_forward_model(), EnvConfig(engine=engine), "additive:40", episodes=N, seed=SEED)
    poisoned_sr, poisoned_reward = expected_always_forward(engine)
    assert 0 < poisoned_sr < 1  # the check means something: both kinds of layout occur
    assert result.clean_sr == 0.0 and result.clean_reward == 0.0  # never reaches the goal at (7,7)
    assert result.poisoned_sr == pytest.approx(poisoned_sr)
    assert result.poisoned_reward == pytest.approx(poisoned_reward)
    assert result.episodes == N


def test_no_trigger_means_no_poisoned_numbers():
    result = evaluate(always_forward_model(), EnvConfig(engine="minigrid"), None, episodes=5, seed=SEED)
    assert np.isnan(result.poisoned_sr) and np.isnan(result.poisoned_reward)
