import json

import pytest

from rlbackdoors.config import ConfigError, RunConfig


def test_defaults_are_the_papers_lavaworld_setup():
    cfg = RunConfig().check()
    assert (cfg.poison.num_clean_envs, cfg.poison.num_poisoned_envs) == (8, 2)
    assert (cfg.ppo.rollout, cfg.ppo.epochs, cfg.ppo.lr, cfg.ppo.clip, cfg.ppo.max_grad_norm) == (128, 4, 1e-3, 0.2, 0.4)
    assert (cfg.train.max_frames, cfg.train.eval_interval, cfg.train.eval_episodes) == (5_000_000, 100_000, 100)
    assert (cfg.train.clean_threshold, cfg.train.poisoned_threshold) == (0.98, 0.95)
    assert cfg.env.max_steps == 250 and cfg.env.size == 9


def test_json_round_trip(tmp_path):
    cfg = RunConfig.from_dict({"model": {"arch": "cnn"}, "train": {"seed": 7}, "poison": {"poisoned": False}})
    (tmp_path / "c.json").write_text(cfg.to_json())
    assert RunConfig.load(tmp_path / "c.json") == cfg
    assert json.loads(cfg.to_json())["version"] == cfg.version


@pytest.mark.parametrize(
    "data, message",
    [
        ({"env": {"sise": 3}}, "env: unknown key 'sise' (allowed: name, size"),
        ({"oops": 1}, "unknown key 'oops'"),
        ({"train": {"max_frames": "x"}}, "train.max_frames must be an integer"),
        ({"train": {"seed": True}}, "train.seed must be an integer"),
        ({"env": {"see_through_walls": 1}}, "must be true or false"),
        ({"model": {"arch": "rnn"}}, "model.arch='rnn' is not allowed (allowed: fc, cnn)"),
        ({"env": {"engine": "gpu"}}, "allowed: batched, minigrid"),
        ({"env": {"size": 10}}, "odd integer"),
        ({"ppo": {"gamma": 2}}, "ppo.gamma must be in [0, 1]"),
        ({"ppo": {"lr": 0}}, "ppo.lr must be > 0"),
        ({"train": {"poisoned_threshold": 1.5}}, "train.poisoned_threshold must be in [0, 1]"),
        ({"poison": {"num_poisoned_envs": 0}}, "must be >= 1 for a poisoned model"),
        ({"poison": {"trigger": "additive:999"}}, "poison.trigger"),
        ({"env": []}, "env must be a JSON object"),
    ],
)
def test_bad_values_name_the_field(data, message):
    with pytest.raises(ConfigError) as err:
        RunConfig.from_dict(data)
    assert message in str(err.value)


def test_clean_model_trains_on_all_clean_copies():
    cfg = RunConfig.from_dict({"poison": {"poisoned": False}})
    assert cfg.poison.poisoned_mask() == [False] * 10
    assert RunConfig().poison.poisoned_mask() == [False] * 8 + [True] * 2
