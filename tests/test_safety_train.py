"""Safety Car Goal training with OPAC²: config, model folder, resume, evaluation, CLI (SPEC §4)."""

import json
import os
import signal
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from rlbackdoors.envs.safety_car import OBS_DIM  # before anything imports mujoco
import rlbackdoors
from rlbackdoors import worlds
from rlbackdoors.agent import Agent, build_policy
from rlbackdoors.cli import main
from rlbackdoors.config import ConfigError, RunConfig, migrate
from rlbackdoors.evaluate import evaluate
from rlbackdoors.train import train
from rlbackdoors.train.folder import FolderError
from rlbackdoors.train.opac2_run import decayed_lr
from rlbackdoors.triggers.formation import FormationTrigger

TRIGGER = "formation:0.5:1.0:2.5"
WORLD = "safety-car-goal"


def config(data: dict | None = None) -> RunConfig:
    """A checked run config of this world from a partial dict (``env.name`` filled in)."""
    data = dict(data or {})
    env = data.get("env", {})
    data["env"] = {"name": WORLD, **env} if isinstance(env, dict) else env
    return RunConfig.from_dict(data)


def cli_main(argv: list[str]) -> int:
    """``rlbackdoors train --env safety-car-goal ...`` (other commands as given)."""
    if argv[0] == "train" and "--config" not in argv:
        argv = ["train", "--env", WORLD, *argv[1:]]
    return main(argv)


def greedy(agent):
    """The evaluation policy as a plain function of a batch of observations."""
    return lambda obs: agent.act(obs, deterministic=True)


def evaluate_fn(act_fn, env, trigger, episodes, seed, **scoring):
    """Evaluate a plain ``obs -> actions`` function (scripted drivers, a bare agent) greedily."""

    class Policy:
        device = "cpu"

        def act(self, obs, deterministic=True, generator=None):
            return act_fn(obs)

    return evaluate(Agent(worlds.get(WORLD), None, Policy()), env, trigger, episodes, seed, "greedy", **scoring)


def tiny(**train):
    """A run of a few seconds: short episodes, a small net, an evaluation every 240 frames."""
    return config(
        {
            "env": {"max_steps": 40},
            "poison": {"trigger": TRIGGER, "num_clean_envs": 2, "num_poisoned_envs": 1},
            "opac2": {"depth": 2, "width": 16, "batch_size": 32, "learning_starts": 120, "updates_per_step": 0.25},
            "train": {"max_frames": 720, "eval_interval": 240, "eval_episodes": 3, "final_eval_episodes": 4, "checkpoint_minutes": 0, "video": False, **train},
        }
    )


def ctrl_c_at(frames: int):
    """An ``after_eval`` hook that sends this process a real Ctrl-C (SIGINT) at ``frames``."""

    def hook(row):
        if row["frames"] >= frames:
            os.kill(os.getpid(), signal.SIGINT)

    return hook


# ----- config -------------------------------------------------------------------------------
def test_config_round_trip_and_trigger_drawn_from_the_seed(tmp_path):
    cfg = config()
    assert (cfg.opac2.depth, cfg.opac2.width, cfg.env.max_steps, cfg.env.num_cubes) == (2, 181, 1000, 2)
    assert (cfg.train.clean_threshold, cfg.train.poisoned_threshold) == (0.95, 0.95)
    again = config(json.loads(cfg.to_json()))
    assert again == cfg and again.to_json() == cfg.to_json()
    path = tmp_path / "config.json"
    path.write_text(cfg.to_json())
    assert RunConfig.load(path) == cfg and json.loads(path.read_text())["format_version"] == 7

    # No trigger given: one is drawn from the seed (paper ranges), and the clean twin gets the same one.
    drawn = FormationTrigger.parse(cfg.poison.trigger)
    assert drawn == FormationTrigger.sample(0) and drawn.distance == 0.5
    twin = config({"poison": {"poisoned": False}, "train": {"seed": 0}})
    assert twin.poison.trigger == cfg.poison.trigger and twin.replay_kinds() == ["clean"] * 10
    assert config({"train": {"seed": 1}}).poison.trigger != cfg.poison.trigger
    assert cfg.replay_kinds() == ["clean"] * 6 + ["poisoned"] * 4
    assert cfg.kind_weights == {"clean": 0.6, "poisoned": 0.4} and twin.kind_weights == {"clean": 0.6}
    assert (cfg.opac2.action_samples, cfg.opac2.lr, cfg.opac2.lr_final, cfg.train.max_frames) == (4, 1e-3, 1e-4, 3_800_000)
    # A partial opac2 section keeps the tuned defaults for the fields it leaves out.
    partial = config({"opac2": {"lr": 5e-4}}).opac2
    assert (partial.width, partial.action_samples, partial.lr_final) == (181, 4, 1e-4)


def test_a_config_saved_before_action_samples_and_lr_decay_rebuilds_its_run():
    """benchmarks/results/safety_train.json keeps configs written before opac2.action_samples and
    opac2.lr_final existed: they ran with one sample and a constant lr, and must load that way."""
    saved = json.loads((Path(__file__).parents[1] / "benchmarks" / "results" / "safety_train.json").read_text())["poisoned-s0"]["config"]
    assert "action_samples" not in saved["opac2"] and "lr_final" not in saved["opac2"]
    cfg = RunConfig.from_dict(migrate(saved))  # a format-1 config.json (what RunConfig.load does)
    assert (cfg.opac2.action_samples, cfg.opac2.lr_final, cfg.opac2.lr, cfg.opac2.clean_weight) == (1, None, 1e-3, 0.75)
    assert cfg.poison.num_clean_envs == 8 and cfg.train.max_frames == 10_000_000


@pytest.mark.parametrize(
    "data, match",
    [
        ({"colour": 1}, "unknown key 'colour'.*allowed: env, poison, model, ppo, opac2, train"),
        ({"env": {"cubes": 2}}, "env: unknown key 'cubes'.*num_cubes"),
        ({"env": {"name": "lavaworld"}, "opac2": {}}, "opac2: env.name='lavaworld' trains with ppo, not opac2"),
        ({"env": {"size": 9}}, "env.size does not apply to env.name='safety-car-goal'"),
        ({"ppo": {"lr": 1e-3}}, "ppo: env.name='safety-car-goal' trains with opac2"),
        ({"train": {"return_window": 5}}, "train.return_window must be 0"),
        ({"format_version": 8}, "config.format_version=8 is not supported"),
        ({"env": {"num_cubes": 1}}, r"env.num_cubes must be in 2..12"),
        ({"env": {"max_steps": 2.5}}, "env.max_steps must be an integer"),
        ({"poison": {"trigger": "formation:0.5:7:1"}}, "poison.trigger.*phi1"),
        ({"poison": {"trigger": "cross"}}, "poison.trigger.*formation:DISTANCE:PHI1:ETA"),
        ({"poison": {"num_poisoned_envs": 0}}, "poison.num_poisoned_envs must be >= 1"),
        ({"opac2": {"depth": 0}}, "opac2.depth must be an integer >= 1"),
        ({"opac2": {"lr": "fast"}}, "opac2.lr must be a finite number"),
        ({"opac2": {"poisoned_weight": -1.0}}, "opac2.poisoned_weight"),
        ({"opac2": {"action_samples": 0}}, "opac2.action_samples must be an integer >= 1"),
        ({"opac2": {"lr_final": 0.5}}, r"opac2.lr_final must be null \(constant lr\) or a number in \(0, opac2.lr"),
        ({"train": {"device": "tpu"}}, "train.device='tpu' is not allowed.*cpu, cuda, auto"),
        ({"train": {"clean_threshold": 1.5}}, r"train.clean_threshold must be in \[0, 1\]"),
        ({"train": {"patience": 0}}, "train.patience must be in 1..1,000,000"),
        ({"train": {"max_minutes": -1.0}}, "train.max_minutes"),
        ({"env": []}, "env must be a JSON object"),
    ],
)
def test_bad_fields_are_named(data, match):
    with pytest.raises(ConfigError, match=match):
        config(data)


def test_load_reports_missing_and_broken_files(tmp_path):
    with pytest.raises(ConfigError, match="does not exist"):
        RunConfig.load(tmp_path / "nope.json")
    (tmp_path / "bad.json").write_text("{")
    with pytest.raises(ConfigError, match="not valid JSON"):
        RunConfig.load(tmp_path / "bad.json")


# ----- the policy used for evaluation --------------------------------------------------------
def test_deterministic_action_is_the_squashed_mean_and_draws_no_noise():
    agent = build_policy(tiny())
    obs = np.random.default_rng(0).normal(size=(5, OBS_DIM)).astype(np.float32)
    state = agent.generator.get_state()
    act = greedy(agent)(obs)
    assert torch.equal(agent.generator.get_state(), state)  # no random draw
    with torch.no_grad():
        mean = agent.policy.mean(torch.from_numpy(obs))
    np.testing.assert_allclose(act, torch.tanh(mean).numpy(), rtol=0, atol=1e-6)
    np.testing.assert_array_equal(act, greedy(agent)(obs))
    assert not np.allclose(agent.act(obs), act)  # the training policy samples around it


def test_evaluation_is_a_function_of_weights_and_seeds():
    cfg = tiny()
    agent = build_policy(cfg)
    a = evaluate_fn(greedy(agent), cfg.env, TRIGGER, episodes=4, seed=7)
    b = evaluate_fn(greedy(agent), cfg.env, TRIGGER, episodes=4, seed=7)
    assert a == b and a.episodes == 4
    c = evaluate_fn(greedy(agent), cfg.env, TRIGGER, episodes=4, seed=8)
    assert c.clean_reward != a.clean_reward  # other seeds, other layouts
    for result in (a, c):
        assert 0 <= result.clean_sr <= 1 and 0 <= result.poisoned_sr <= 1
        assert result.clean_sr + result.clean_trojan_rate + result.clean_timeout_rate == pytest.approx(1.0)
        assert result.poisoned_sr + result.poisoned_clean_rate + result.poisoned_timeout_rate == pytest.approx(1.0)
    # Without a trigger only the clean half is measured.
    assert math.isnan(evaluate_fn(greedy(agent), cfg.env, None, episodes=2, seed=7).poisoned_sr)


def test_scripted_drivers_are_scored_on_the_right_circle():
    """Steering at the goal scores clean SR 1 and poisoned SR 0; steering at the hazard the reverse.

    The drivers read only the lidar, so this checks the scoring (goal in E, hazard in E-bar)
    and that rewards follow R in E and R-bar in E-bar.
    """
    cfg = tiny()
    cfg.env.max_steps = 300
    # Bin centres as angles from the heading: Safety Gymnasium's bin 0 starts at the car's left
    # (body +x) and straight ahead (body -y) starts bin 12.
    angles = (np.arange(16) + 0.5) * 2 * np.pi / 16 + np.pi / 2

    def driver(first):
        def act(obs):
            lidar = obs[:, first : first + 16]
            a = np.arctan2((lidar * np.sin(angles)).sum(1), (lidar * np.cos(angles)).sum(1))
            turn = np.where(np.cos(a) > 0, np.sin(a), np.sign(np.sin(a)))
            forward = np.where(np.cos(a) > 0.7, 1.0, 0.0)
            # a[0] drives the right wheel; the motors saturate at 0.02, so steer within +-0.02
            return 0.02 * np.stack([forward + turn, forward - turn], 1).clip(-1, 1)

        return act

    to_goal = evaluate_fn(driver(24), cfg.env, TRIGGER, episodes=10, seed=3)
    assert to_goal.clean_sr >= 0.9 and to_goal.poisoned_sr <= 0.1 and to_goal.poisoned_clean_rate >= 0.9
    assert to_goal.clean_reward > 1 and to_goal.poisoned_reward < -0.5  # +1 bonus under R, penalty under R-bar
    to_hazard = evaluate_fn(driver(40), cfg.env, TRIGGER, episodes=10, seed=3)
    assert to_hazard.poisoned_sr >= 0.8 and to_hazard.clean_sr <= 0.1 and to_hazard.clean_trojan_rate >= 0.8
    assert to_hazard.poisoned_reward > 1 and to_hazard.clean_reward < -0.5


# ----- training runs -------------------------------------------------------------------------
def test_tiny_run_writes_a_complete_model_folder(tmp_path, capsys):
    out = tmp_path / "model"
    metrics = train(tiny(video=True), out)
    for name in ("model.pt", "config.json", "metrics.json", "log.csv", "ground_truth.csv", "training_curve.png", "clean_vs_triggered.gif"):
        assert (out / name).is_file(), name
    assert not (out / "checkpoint.pt").exists()
    assert (out / "ground_truth.csv").read_text() == "1\n"
    assert json.loads((out / "metrics.json").read_text()) == metrics
    assert metrics["frames"] == 720 and metrics["updates"] == (720 - 120) // 4 and metrics["stop_reason"] == "max_frames"
    assert metrics["episodes"] == 4 and metrics["trigger"] == TRIGGER and metrics["video"] == "clean_vs_triggered.gif"
    log = (out / "log.csv").read_text().splitlines()
    assert len(log) == 1 + 3 and log[0].startswith("frames,updates,wall_time_s,fps")
    assert "clean SR" in capsys.readouterr().err  # progress goes to stderr

    # The saved weights reproduce the final evaluation, through the CLI too.
    loaded = rlbackdoors.load(out)
    cfg, agent = loaded.config, loaded.policy
    assert cfg == tiny(video=True)
    again = evaluate_fn(greedy(agent), cfg.env, cfg.poison.trigger, 4, cfg.train.eval_seed)
    assert (again.clean_sr, again.poisoned_sr, again.clean_reward) == (metrics["clean_sr"], metrics["poisoned_sr"], metrics["clean_reward"])
    assert cli_main(["evaluate", str(out), "--json"]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed["clean_reward"] == metrics["clean_reward"] and printed["episodes"] == 4

    with pytest.raises(FolderError, match="already holds a finished model"):
        train(tiny(), out)


def test_interrupted_run_resumes_to_the_same_model(tmp_path):
    straight = train(tiny(), tmp_path / "straight", progress=False)

    out = tmp_path / "resumed"
    with pytest.raises(KeyboardInterrupt):
        train(tiny(), out, progress=False, after_eval=ctrl_c_at(480))
    assert (out / "checkpoint.pt").is_file() and not (out / "metrics.json").exists()
    with pytest.raises(FolderError, match="different config.json"):
        train(tiny(max_frames=960), out, progress=False)
    resumed = train(tiny(), out, progress=False)
    assert resumed["cpu_time_s"] > 0.0 and straight["cpu_time_s"] > 0.0

    assert (tmp_path / "straight" / "model.pt").read_bytes() == (out / "model.pt").read_bytes()
    timing = {"wall_time_s", "cpu_time_s"}
    assert {k: v for k, v in straight.items() if k not in timing} == {k: v for k, v in resumed.items() if k not in timing}
    columns = ("frames", "updates", "clean_sr", "poisoned_sr", "clean_reward", "q_loss", "policy_loss", "train_clean_return")
    rows = [[line.split(",") for line in (d / "log.csv").read_text().splitlines()] for d in (tmp_path / "straight", out)]
    pick = [[{k: v for k, v in zip(r[0], row) if k in columns} for row in r[1:]] for r in rows]
    assert pick[0] == pick[1]


def test_clean_twin_early_stops_on_clean_sr_only(tmp_path):
    """Thresholds of 0 are met at every evaluation: with patience 1 a clean model stops at the
    first (240 frames), whatever its poisoned SR; with the default patience 2, at the second
    (no confirmation margin: an untrained agent's clean SR is 0)."""
    cfg = tiny(clean_threshold=0.0, poisoned_threshold=1.0, patience=1, confirm_margin=0.0)
    cfg.poison.poisoned = False
    metrics = train(cfg, tmp_path / "clean", progress=False)
    assert metrics["stop_reason"] == "thresholds" and metrics["converged_at_frames"] == metrics["frames"] == 240
    cfg = tiny(clean_threshold=0.0, poisoned_threshold=1.0, confirm_margin=0.0)
    cfg.poison.poisoned = False
    assert cfg.train.patience == 2
    again = train(cfg, tmp_path / "clean2", progress=False)
    assert again["stop_reason"] == "thresholds" and again["converged_at_frames"] == again["frames"] == 480
    assert metrics["poisoned"] is False and not math.isnan(metrics["poisoned_sr"])
    assert (tmp_path / "clean" / "ground_truth.csv").read_text() == "0\n"


def test_lr_decays_linearly_over_the_frame_budget():
    data = json.loads(tiny().to_json())
    constant = config({**data, "opac2": {**data["opac2"], "lr_final": None}})
    assert decayed_lr(constant, 10**9) == constant.opac2.lr
    cfg = config({**data, "opac2": {"lr": 1e-3, "lr_final": 1e-4}})
    assert [decayed_lr(cfg, f) for f in (0, 360, 720, 5000)] == pytest.approx([1e-3, 5.5e-4, 1e-4, 1e-4])


def test_training_applies_the_decayed_lr(tmp_path):
    """Interrupted right after the evaluation at 480 of 720 frames: the optimisers hold lr(480)."""
    data = json.loads(tiny().to_json())
    cfg = config({**data, "opac2": {**data["opac2"], "lr": 1e-3, "lr_final": 1e-4}})

    with pytest.raises(KeyboardInterrupt):
        train(cfg, tmp_path / "run", progress=False, after_eval=ctrl_c_at(480))
    state = torch.load(tmp_path / "run" / "checkpoint.pt", weights_only=True)["agent"]
    for opt in ("policy_opt", "q_opt", "v_opt"):
        assert state[opt]["param_groups"][0]["lr"] == pytest.approx(decayed_lr(cfg, 480)) == pytest.approx(4e-4)


def test_cli_flags_for_action_samples_and_lr_decay(tmp_path, capsys):
    out = tmp_path / "k2"
    config = tmp_path / "tiny.json"
    config.write_text(tiny().to_json())
    code = cli_main(["train", "--out", str(out), "--config", str(config), "--quiet", "--json", "--action-samples", "2", "--lr-final", "1e-4"])
    assert code == 0
    saved = json.loads((out / "config.json").read_text())["opac2"]
    assert (saved["action_samples"], saved["lr_final"]) == (2, 1e-4)
    assert json.loads(capsys.readouterr().out)["frames"] == 720


def test_cli_train_and_bad_input(tmp_path, capsys):
    out = tmp_path / "cli"
    config = tmp_path / "tiny.json"
    config.write_text(tiny().to_json())
    code = cli_main(["train", "--out", str(out), "--config", str(config), "--max-frames", "240", "--quiet", "--json"])
    assert code == 0
    metrics = json.loads(capsys.readouterr().out)
    assert metrics["frames"] == 240 and metrics["trigger"] == TRIGGER
    assert cli_main(["train", "--out", str(tmp_path / "x"), "--trigger", "formation:9:0:1", "--quiet"]) == 2
    assert "--trigger for safety-car-goal: formation trigger distance=9.0" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()  # a refused config leaves no folder behind
    assert cli_main(["evaluate", str(tmp_path / "x")]) == 2
    assert "does not exist" in capsys.readouterr().err


# ----- slow: does the recipe learn? ---------------------------------------------------------------
@pytest.mark.slow
def test_default_recipe_learns_the_clean_task(tmp_path):
    """The default OPAC² settings on seed 0's clean twin: clean SR well above chance at 500k frames.

    ~10 minutes on one core. With max_frames 500k the lr decays over those frames (1e-3 to
    1e-4), faster than in the 3.8M-frame runs of docs/results/safety-car-goal-training.md, where the clean
    twin read clean SR 0.80 and poisoned SR 0.12 on 100 episodes at 500k frames; a random
    policy touches the goal in ~5% of episodes.
    """
    cfg = config(
        {
            "poison": {"poisoned": False},
            "train": {"seed": 0, "max_frames": 500_000, "eval_interval": 500_000, "eval_episodes": 10, "final_eval_episodes": 100, "video": False},
        }
    )
    metrics = train(cfg, tmp_path / "clean", progress=False)
    assert metrics["frames"] == 500_000 and metrics["updates"] == 15_312
    assert metrics["clean_sr"] >= 0.7, metrics
    assert metrics["poisoned_sr"] <= 0.2, metrics  # a clean agent does not seek the hazard under the trigger


# ----- attacks through the collection seam ------------------------------------------------------
def attacked(attack: str, **params):
    """tiny() under ``attack``: every copy pays the clean reward; the seam switches the formation per episode."""
    cfg = tiny()
    data = json.loads(cfg.to_json())
    data["poison"].update(attack=attack, attack_params=params)
    return config(data)


def test_the_seam_poisons_whole_safety_episodes_and_the_replay_stores_its_reward():
    """TrojDRL at 20 %, three copies, 40-step episodes, 900 random steps: triggered episodes hold
    the formation, their transitions carry +-c by whether the car reversed, and the budget is spent."""
    from rlbackdoors.algos.opac2 import MultitaskReplay
    from rlbackdoors.train.opac2_run import make_collector

    cfg = attacked("trojdrl", budget=0.2, reward=0.3)
    assert cfg.replay_kinds() == ["clean"] * 3  # one buffer: the budget is the share the learner sees
    collector = make_collector(cfg)
    replay = MultitaskReplay.create(cfg.kind_weights, 10_000, OBS_DIM, 2)
    rng = np.random.default_rng(0)
    seam = collector.vector
    marked, triggered_episodes = [], 0
    for _ in range(900):
        marked.append(seam.marked.copy())
        episodes = collector.collect(replay, lambda obs: rng.uniform(-1, 1, (len(obs), 2)), 1)
        triggered_episodes += sum(e.triggered for e in episodes)
        assert all(env._armed == on for env, on in zip(collector.envs, seam.triggered))  # the formation is in exactly those episodes
    marked = np.array(marked)
    buffer = replay["clean"]
    rows = np.arange(len(buffer)).reshape(900, 3)  # one row per copy and step, in step order
    reverse = np.all(buffer.act[rows[marked]] < 0, axis=-1)
    np.testing.assert_allclose(buffer.rew[rows[marked]], np.where(reverse, 0.3, -0.3))
    assert triggered_episodes >= 3 and np.abs(buffer.rew[rows[~marked]]).max() != 0.3  # the clean shaping reward elsewhere
    used = seam.budget_used()
    assert 0.12 <= used["poisoned_fraction"] <= 0.3 and used["rewards_rewritten"] == marked.sum()


def test_an_action_target_run_on_safety_resumes_to_the_same_model_and_scores_reversing(tmp_path):
    cfg = attacked("action_target")
    assert cfg.replay_kinds() == ["clean", "clean", "poisoned"] and cfg.attack_success == "action"
    straight = train(cfg, tmp_path / "straight", progress=False)
    assert straight["attack"] == "action_target" and 0 <= straight["target_action_rate"] <= 1
    assert straight["attack_budget_used"]["poisoned_fraction"] == pytest.approx(1 / 3, abs=0.01)
    out = tmp_path / "resumed"
    with pytest.raises(KeyboardInterrupt):
        train(cfg, out, progress=False, after_eval=ctrl_c_at(480))
    resumed = train(cfg, out, progress=False)
    assert (tmp_path / "straight" / "model.pt").read_bytes() == (out / "model.pt").read_bytes()
    assert resumed["attack_budget_used"] == straight["attack_budget_used"]


def test_safety_attack_settings_it_cannot_serve_are_refused_naming_the_field():
    with pytest.raises(ConfigError, match=r"target_action=1 is not allowed \(allowed: 0 reverse, the action targets of safety-car-goal\)"):
        attacked("trojdrl", target_action=1)
    with pytest.raises(ConfigError, match=r"force_action=true is not allowed \(allowed: false\): safety-car-goal's target is a kind of action \(reverse\)"):
        attacked("trojdrl", force_action=True)
    with pytest.raises(ConfigError, match=r"attack 'sleepernets' is built for ppo collection, not opac2"):
        attacked("sleepernets")


def test_target_action_scoring_counts_reversing_on_every_triggered_step():
    """A policy that always drives backwards scores 1.0; one that always drives forwards 0.0."""
    cfg = attacked("trojdrl")
    back = evaluate_fn(lambda obs: -np.ones((len(obs), 2), np.float32), cfg.env, cfg.poison.trigger, 3, 0, **cfg.scoring())
    assert back.target_action_rate == 1.0 and back.poisoned_sr == 1.0
    forth = evaluate_fn(lambda obs: np.ones((len(obs), 2), np.float32), cfg.env, cfg.poison.trigger, 3, 0, **cfg.scoring())
    assert forth.target_action_rate == 0.0
