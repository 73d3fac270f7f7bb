"""``rlbackdoors.load(folder)``: one way to load an agent of any world, act with it, and evaluate
it through one function; a model.pt that carries code is refused."""

import json
import math

import numpy as np
import pytest
import torch

import rlbackdoors
from rlbackdoors import worlds
from rlbackdoors.evaluate import evaluate_agent
from rlbackdoors.train.folder import FolderError
from test_same_weights import RUNS, train_tiny


@pytest.fixture(scope="module")
def folders(tmp_path_factory):
    root = tmp_path_factory.mktemp("load")
    for world in RUNS:
        train_tiny(world, root / world)
    return root


@pytest.mark.parametrize("world", list(RUNS))
def test_every_world_loads_acts_and_reproduces_its_metrics(folders, world):
    agent = rlbackdoors.load(folders / world)
    assert agent.world is worlds.get(world) and world in repr(agent)
    metrics = json.loads((folders / world / "metrics.json").read_text())
    result = evaluate_agent(agent).to_dict()  # the folder's trigger, episodes and seeds: its final evaluation again
    for key in ("clean_sr", "poisoned_sr", "clean_reward", "poisoned_reward", "episodes"):
        assert result[key] == metrics[key] or (math.isnan(result[key]) and metrics[key] is None), key
    # act() on a batch of real observations of the world's own env, through the recurrent state if any.
    import gymnasium as gym

    env = (
        gym.make_vec(agent.world.gym_id, num_envs=3, vectorization_mode="sync", max_steps=40)
        if agent.world.vector_entry_point is None
        else gym.make_vec(agent.world.gym_id, num_envs=3)
    )
    obs, _ = env.reset(seed=0)
    state = agent.initial_state(3)
    assert (state is not None) == agent.recurrent
    for _ in range(3):
        actions, state = agent.act(obs, state, deterministic=True)
        assert len(actions) == 3
        obs, *_ = env.step(actions)
    again, _ = agent.act(obs, agent.initial_state(3), deterministic=True)
    assert np.array_equal(again, agent.act(obs, agent.initial_state(3), deterministic=True)[0])
    env.close()


def test_load_refuses_payloads_and_unfinished_folders(folders, tmp_path):
    import shutil

    marker = tmp_path / "ran"
    for world in ("lavaworld", "safety-car-goal"):
        copy = tmp_path / world
        shutil.copytree(folders / world, copy)
        weights = torch.load(copy / "model.pt", weights_only=True)
        torch.save({"w": weights, "x": Payload(marker)}, copy / "model.pt")
        with pytest.raises((FolderError, ValueError), match="holds Python objects"):
            rlbackdoors.load(copy)
        shutil.copy(folders / world / "model.pt", copy / "model.pt")
        (copy / "metrics.json").unlink()
        with pytest.raises(FolderError, match="unfinished"):
            rlbackdoors.load(copy)
        assert rlbackdoors.load(copy, allow_unfinished=True).world.name == world
    assert not marker.exists()
    with pytest.raises(FolderError, match="does not exist"):
        rlbackdoors.load(tmp_path / "nowhere")


class Payload:
    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, "w"))


@pytest.mark.parametrize("world", list(RUNS))
def test_a_bare_weights_file_of_every_world_acts_as_its_folder(folders, world, capsys):
    """``load_weights_file`` (what ``evaluate --weights`` uses) rebuilds the same policy from the
    file alone: PPO worlds from the named arch, OPAC² from the tensors' shapes."""
    from rlbackdoors.agent import load_weights_file
    from rlbackdoors.cli import main

    folder_agent = rlbackdoors.load(folders / world)
    arch = folder_agent.config.model.arch if folder_agent.world.algorithm == "ppo" else None
    bare = load_weights_file(folders / world / "model.pt", world, arch)
    env = folder_agent.config.env.make()
    obs = np.stack([env.reset(seed=s)[0] for s in range(4)]) if not isinstance(env.reset(seed=0)[0], dict) else None
    if obs is not None:  # dict observations are covered by the folder test above
        a, _ = folder_agent.act(obs, folder_agent.initial_state(4), deterministic=True)
        b, _ = bare.act(obs, bare.initial_state(4), deterministic=True)
        assert np.array_equal(a, b)
    env.close()
    argv = ["evaluate", "--weights", str(folders / world / "model.pt"), "--env", world, "--episodes", "2", "--json"]
    assert main(argv + (["--arch", arch] if arch else [])) == 0
    assert json.loads(capsys.readouterr().out)["episodes"] == 2
