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
        ({"env": {"sise": 3}}, "env: unknown key 'sise' (allowed: name, max_steps, size, see_through_walls, engine, num_crossings)"),
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


# ----- format versions (issue 14: one config for every world) --------------------------------------
FORMAT_1_COLORFUL = {
    "env": {"name": "colorful-memory", "size": 7, "max_steps": 250, "see_through_walls": False, "engine": "batched", "num_crossings": 1, "num_lava": 10},
    "poison": {"trigger": "end", "poisoned": True, "num_clean_envs": 4, "num_close_envs": 4, "num_poisoned_envs": 2, "close_k_min": 1, "close_k_max": 3},
    "model": {"arch": "cnn-gru-small-onehot"},
    "train": {"seed": 3, "max_frames": 5_000_000, "patience": 10, "patience_reward": 0.8},
    "curriculum": {"enabled": False, "size": 7, "num_lava": 5, "reward_threshold": 0.8, "window": 100},
    "version": "0.1.0",
}


def test_a_format_1_grid_config_file_means_the_same_run(tmp_path):
    """Format 1 (no format_version) called the mean-return rule train.patience; loading it gives
    that rule as train.return_window and counts evaluations with the new default patience."""
    path = tmp_path / "config.json"
    path.write_text(json.dumps(FORMAT_1_COLORFUL))
    cfg = RunConfig.load(path)
    assert (cfg.train.return_window, cfg.train.return_threshold, cfg.train.patience) == (10, 0.8, 1)
    assert cfg.format_version == 7 and cfg.env.num_crossings is None and cfg.env.num_lava is None
    assert cfg.train.confirm is False  # format 1 runs stopped without confirming
    saved = json.loads(cfg.to_json())
    assert "num_crossings" not in saved["env"] and "curriculum" not in saved and "opac2" not in saved
    assert RunConfig.from_dict(saved) == cfg  # today's format round-trips as is


def test_a_format_2_config_file_stops_without_confirming_as_it_did(tmp_path):
    """Format 2 had no train.confirm: its runs stopped at the first streak, so it loads as
    confirm false; a new config confirms by default; both save the field."""
    new = RunConfig.from_dict({"env": {"name": "lavaworld"}})
    assert new.train.confirm is True and new.format_version == 7
    data = json.loads(new.to_json())
    del data["train"]["confirm"], data["train"]["confirm_margin"]
    data["format_version"] = 2
    path = tmp_path / "config.json"
    path.write_text(json.dumps(data))
    old = RunConfig.load(path)
    assert old.train.confirm is False and old.format_version == 7
    assert json.loads(old.to_json())["train"]["confirm"] is False
    with pytest.raises(ConfigError, match=r"train.confirm must be true or false, got 'yes'"):
        RunConfig.from_dict({"env": {"name": "lavaworld"}, "train": {"confirm": "yes"}})


def test_a_format_3_config_file_confirms_without_a_margin_as_it_did(tmp_path):
    """Format 3 had no train.confirm_margin: its confirmations asked for the thresholds alone, so
    it loads with margin 0 even where the world's default (Safety Car Goal: 0.02) is not."""
    new = RunConfig.from_dict({"env": {"name": "safety-car-goal"}})
    assert new.train.confirm_margin == 0.02 and RunConfig.from_dict({"env": {"name": "lavaworld"}}).train.confirm_margin == 0.0
    data = json.loads(new.to_json())
    del data["train"]["confirm_margin"]
    data["format_version"] = 3
    path = tmp_path / "config.json"
    path.write_text(json.dumps(data))
    old = RunConfig.load(path)
    assert old.train.confirm_margin == 0.0 and old.format_version == 7 and old.train.confirm is True
    for bad in (-0.01, 1.5, "0.02", True):
        with pytest.raises(ConfigError, match=r"^train.confirm_margin must be "):
            RunConfig.from_dict({"env": {"name": "safety-car-goal"}, "train": {"confirm_margin": bad}})


def test_a_format_4_config_file_stops_at_any_evaluation_as_it_did(tmp_path):
    """Format 4 had no train.min_frames: it loads with 0 (a stop at any evaluation) and saves it."""
    data = json.loads(RunConfig.from_dict({"env": {"name": "lavaworld"}, "train": {"min_frames": 10}}).to_json())
    assert data["train"]["min_frames"] == 10 and data["format_version"] == 7
    del data["train"]["min_frames"]
    data["format_version"] = 4
    path = tmp_path / "config.json"
    path.write_text(json.dumps(data))
    old = RunConfig.load(path)
    assert old.train.min_frames == 0 and old.format_version == 7
    for bad in (-1, 10**13, "0", 1.5):
        with pytest.raises(ConfigError, match=r"^train.min_frames "):
            RunConfig.from_dict({"env": {"name": "lavaworld"}, "train": {"min_frames": bad}})


def test_a_format_6_config_file_evaluates_with_torch_as_it_did(tmp_path):
    """Format 6 had no train.eval_backend: it loads with torch's evaluations (what its runs did)."""
    data = json.loads(
        RunConfig.from_dict({"env": {"name": "lavaworld"}, "ppo": {"update_backend": "compiled"}, "train": {"eval_backend": "compiled"}}).to_json()
    )
    assert data["train"]["eval_backend"] == "compiled" and data["format_version"] == 7
    del data["train"]["eval_backend"]
    data["format_version"] = 6
    path = tmp_path / "config.json"
    path.write_text(json.dumps(data))
    old = RunConfig.load(path)
    assert old.train.eval_backend == "torch" and old.format_version == 7 and old.ppo.update_backend == "compiled"


def test_compiled_evaluations_need_the_compiled_trainer():
    with pytest.raises(ConfigError, match=r"^train.eval_backend='compiled' .* needs ppo.update_backend='compiled' \(here 'jax'\); use 'torch'$"):
        RunConfig.from_dict({"env": {"name": "lavaworld"}, "ppo": {"update_backend": "jax"}, "train": {"eval_backend": "compiled"}})
    with pytest.raises(ConfigError, match=r"^train.eval_backend='numba' is not allowed \(allowed: torch, compiled\)$"):
        RunConfig.from_dict({"env": {"name": "lavaworld"}, "train": {"eval_backend": "numba"}})


def test_an_unknown_format_version_is_refused_by_number(tmp_path):
    path = tmp_path / "config.json"
    path.write_text(json.dumps({"env": {"name": "lavaworld"}, "format_version": 8}))
    with pytest.raises(ConfigError, match=r"config.format_version=8 is not supported by rlbackdoors .* \(it reads 1 to 7\)"):
        RunConfig.load(path)


@pytest.mark.parametrize("world", ["lavaworld", "randomized-lavaworld", "colorful-memory", "safety-car-goal"])
def test_one_config_class_for_every_world_with_its_algorithm_section(world):
    cfg = RunConfig.from_dict({"env": {"name": world}})
    data = json.loads(cfg.to_json())
    assert cfg.algorithm in data and ({"ppo", "opac2"} - {cfg.algorithm}).isdisjoint(data)
    assert set(data["env"]) == {"name", "max_steps", *cfg.world.env_fields}
    assert RunConfig.from_dict(data) == cfg


@pytest.mark.parametrize(
    "data, backend",
    [
        ({}, "compiled"),  # LavaWorld fc, the env mix: measured faster and tested equivalent
        ({"poison": {"poisoned": False}}, "compiled"),
        ({"env": {"name": "randomized-lavaworld"}, "model": {"arch": "cnn"}}, "compiled"),
        ({"model": {"arch": "cnn"}}, "torch"),  # faster, but no equivalence report
        ({"env": {"name": "randomized-lavaworld"}}, "torch"),  # its fc: the same
        ({"env": {"name": "colorful-memory"}}, "torch"),  # no JAX engine
        ({"poison": {"attack": "trojdrl"}}, "torch"),  # equivalence was tested for the env mix alone
        ({"poison": {"evasion": {"near": 1.0}}}, "torch"),
        ({"train": {"device": "cuda"}}, "torch"),  # not measured on a GPU
        ({"ppo": {"batch_size": 100}}, "torch"),  # a minibatch the compiled trainer refuses
    ],
)
def test_auto_takes_the_compiled_trainer_only_where_it_was_measured_to_win(data, backend):
    data = {**data, "ppo": {**data.get("ppo", {}), "update_backend": "auto"}}
    cfg = RunConfig.from_dict(data)
    assert cfg.ppo.update_backend == backend
    assert json.loads(cfg.to_json())["ppo"]["update_backend"] == backend  # recorded as chosen, never "auto"


def test_a_config_without_the_backend_field_is_torchs():
    """The default stays torch's: a config (or a format 5 file) that names no backend keeps its bytes."""
    assert RunConfig.from_dict({}).ppo.update_backend == "torch"
    assert RunConfig.from_dict({"env": {"name": "randomized-lavaworld"}, "model": {"arch": "cnn"}}).ppo.update_backend == "torch"
    with pytest.raises(ConfigError, match=r"^ppo: env.name='safety-car-goal' trains with opac2, not ppo \(drop the ppo section\)$"):
        RunConfig.from_dict({"env": {"name": "safety-car-goal"}, "ppo": {"update_backend": "auto"}})
