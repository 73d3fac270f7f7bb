"""Randomized LavaWorld through the trainer: curriculum switch, trigger-seen scoring, CLI."""

import json

import numpy as np
import pytest

from rlbackdoors.cli import main
from rlbackdoors.config import RunConfig
from rlbackdoors.envs.outcome import Outcome
from rlbackdoors.evaluate import evaluate, score_triggered
from rlbackdoors.models import build_model
from rlbackdoors.train import ModelFolder, train


def tiny(threshold: float, **extra) -> RunConfig:
    return RunConfig.from_dict(
        {
            "env": {"name": "randomized-lavaworld"},
            "ppo": {"rollout": 32},
            "curriculum": {"reward_threshold": threshold, "window": 10},
            "train": {"seed": 3, "max_frames": 3200, "eval_interval": 1600, "eval_episodes": 8, "final_eval_episodes": 8},
            **extra,
        }
    )


def test_defaults_are_the_papers_randomized_lavaworld():
    cfg = RunConfig.from_dict({"env": {"name": "randomized-lavaworld"}})
    assert (cfg.env.size, cfg.env.num_lava, cfg.env.see_through_walls, cfg.env.max_steps) == (11, 10, True, 250)
    assert cfg.poison.trigger == "cross" and cfg.curriculum.enabled
    assert (cfg.curriculum.size, cfg.curriculum.num_lava, cfg.curriculum.reward_threshold) == (7, 5, 0.8)
    assert (cfg.train.clean_threshold, cfg.train.poisoned_threshold) == (0.95, 0.90)
    assert not RunConfig().curriculum.enabled  # LavaWorld has no warm-up


def test_curriculum_switches_when_the_warmup_return_is_reached(tmp_path):
    metrics = train(tiny(0.0), tmp_path / "m", progress=False)
    switch = metrics["curriculum_switch_frames"]
    assert switch is not None and 0 < switch <= metrics["frames"]
    rows = ModelFolder(tmp_path / "m").read_log()
    assert rows[-1]["phase"] == "main"
    assert (tmp_path / "m" / "training_curve.png").stat().st_size > 0
    assert (tmp_path / "m" / "clean_vs_triggered.gif").read_bytes()[:6] == b"GIF89a"


def test_curriculum_never_switches_below_the_threshold_and_never_converges(tmp_path):
    cfg = tiny(1.0)
    cfg.train.clean_threshold = cfg.train.poisoned_threshold = 0.0  # would "converge" at once if allowed
    metrics = train(cfg, tmp_path / "m", progress=False)
    assert metrics["curriculum_switch_frames"] is None and not metrics["converged"]
    assert {r["phase"] for r in ModelFolder(tmp_path / "m").read_log()} == {"warm-up"}


def test_score_triggered_counts_unseen_triggers_on_the_clean_task():
    G, L, P, T = Outcome.GOAL, Outcome.LAVA, Outcome.PATTERN_LAVA, Outcome.TIMEOUT
    outcomes = np.array([P, P, G, G, L, T, P, G])
    saw = np.array([1, 1, 1, 0, 0, 0, 0, 1], dtype=bool)
    aware, raw, seen = score_triggered("randomized-lavaworld", outcomes, saw)
    # seen: P ok, P ok, G wrong, G wrong -> 2/4 ; unseen: G ok, L wrong, T wrong, P (unseen) wrong -> 1/4
    assert aware == pytest.approx(3 / 8) and raw == pytest.approx(3 / 8) and seen == pytest.approx(4 / 8)
    assert score_triggered("randomized-lavaworld", np.array([G, G]), np.array([False, False]))[:2] == (1.0, 0.0)


@pytest.mark.parametrize("arch", ["fc", "cnn"])
def test_evaluation_reports_raw_and_seen_aware_rates(arch):
    cfg = RunConfig.from_dict({"env": {"name": "randomized-lavaworld"}})
    result = evaluate(build_model(arch, cfg.env.name), cfg.env, "arrow", episodes=50, seed=11)
    assert 0 <= result.poisoned_sr_raw <= 1 and 0 <= result.trigger_seen_rate <= 1
    # An untrained policy: every trojan ending is a seen one, so raw <= aware + unseen share.
    assert result.poisoned_sr_raw <= result.poisoned_sr + (1 - result.trigger_seen_rate) + 1e-9


def test_cli_trains_and_evaluates_randomized_lavaworld(tmp_path, capsys):
    out = tmp_path / "m"
    code = main(
        [
            "train",
            "--env",
            "randomized-lavaworld",
            "--arch",
            "cnn",
            "--trigger",
            "arrow:north",
            "--max-frames",
            "1280",
            "--eval-episodes",
            "4",
            "--no-curriculum",
            "--out",
            str(out),
            "--quiet",
        ]
    )
    assert code == 0
    cfg = json.loads((out / "config.json").read_text())
    assert cfg["env"]["name"] == "randomized-lavaworld" and cfg["poison"]["trigger"] == "arrow:north"
    assert cfg["curriculum"]["enabled"] is False and cfg["env"]["size"] == 11
    capsys.readouterr()
    assert main(["evaluate", str(out), "--episodes", "6", "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert {"poisoned_sr", "poisoned_sr_raw", "trigger_seen_rate"} <= set(result) and result["episodes"] == 6


def test_cli_rejects_a_lavaworld_trigger_for_randomized_lavaworld(tmp_path, capsys):
    code = main(["train", "--env", "randomized-lavaworld", "--trigger", "multiplicative:12", "--out", str(tmp_path / "m")])
    assert code == 2 and "--trigger for randomized-lavaworld: lava pattern 'multiplicative:12'" in capsys.readouterr().err


def test_gymnasium_ids_give_the_reference_env_and_the_batched_engine():
    import gymnasium as gym

    import rlbackdoors.envs  # noqa: F401  (registers the ids)
    from rlbackdoors.envs.randomized_lavaworld import RandomizedLavaWorldEnv
    from rlbackdoors.envs.randomized_lavaworld_batched import BatchedRandomizedLavaWorld

    single = gym.make("rlbackdoors/RandomizedLavaWorld-v0")
    assert isinstance(single.unwrapped, RandomizedLavaWorldEnv)
    vec = gym.make_vec("rlbackdoors/RandomizedLavaWorld-v0", num_envs=4)
    assert isinstance(vec, BatchedRandomizedLavaWorld) and vec.num_envs == 4
    obs, _ = vec.reset(seed=0)
    assert obs["image"].shape == (4, 7, 7, 3) and obs["direction"].shape == (4,)


def test_chance_occurrence_cross_is_rare_and_arrow_is_common():
    """5,000 clean 11x11 K=10 layouts: the cross needs 5 lava in a plus (rare), a 3-cell arrow far less."""
    from rlbackdoors.config import EnvConfig
    from rlbackdoors.evaluate.chance import trigger_chance

    env = EnvConfig(name="randomized-lavaworld")
    cross = trigger_chance(env, "cross", layouts=5_000)
    arrow = trigger_chance(env, "arrow", layouts=5_000)
    assert cross["rate"] < 0.005 and 0.15 < arrow["rate"] < 0.35  # measured on 100k: 0.05% and 24.6%
    assert arrow["placements_per_layout"] >= arrow["rate"]
    with pytest.raises(ValueError, match="layout triggers"):
        trigger_chance(EnvConfig(), "multiplicative:12")


def test_cli_chance_prints_the_rate(capsys):
    assert main(["chance", "--trigger", "arrow:east", "--layouts", "2000", "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["trigger"] == "arrow:east" and result["layouts"] == 2000 and 0.03 < result["rate"] < 0.14


def test_train_json_output_is_pure_json_even_with_a_curriculum_switch(tmp_path, capsys):
    cfg = tiny(0.0)  # switches after the first 10 clean episodes
    (tmp_path / "c.json").write_text(cfg.to_json())
    code = main(["train", "--config", str(tmp_path / "c.json"), "--out", str(tmp_path / "m"), "--quiet", "--json"])
    captured = capsys.readouterr()
    metrics = json.loads(captured.out)
    assert code == 0 and metrics["curriculum_switch_frames"] is not None
    assert "curriculum: switched" in captured.err


@pytest.mark.slow  # (over 15 s on 2 cores: out of the default run, `make test-slow`)
def test_sight_actions_reads_a_layout_trigger_agent_and_refuses_others(tmp_path):
    """experiments/sight_actions/sight_actions.py (what an agent does while the pattern is in sight): its shares
    are over the in-sight steps it counts, and a world whose trigger is not seen frame by frame is
    refused in one line."""
    import subprocess
    import sys
    from pathlib import Path

    script = Path(__file__).resolve().parents[1] / "experiments" / "sight_actions" / "sight_actions.py"
    cfg = tiny(0.0, poison={"trigger": "cross", "attack": "trojdrl", "attack_params": {"budget": 0.05}})
    train(RunConfig.from_dict({**cfg.to_dict(), "train": {**cfg.to_dict()["train"], "video": False}}), tmp_path / "m", progress=False)
    done = subprocess.run([sys.executable, str(script), str(tmp_path / "m"), "--episodes", "4", "--show", "2"], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    steps = int(lines[0].split(": ")[1].split()[0])
    shares = [float(part.split(": ")[1]) for part in lines[1].split("steps: ")[1].split(", ")]
    assert len(shares) == 3 and (steps == 0 or abs(sum(shares) - 1) < 2e-3)
    shown = [line for line in lines if line.strip().split()[1:2] == ["steps:"]]
    assert len(shown) == 2 and all(int(line.split()[0]) == len(line.split(": ", 1)[1].split()) or int(line.split()[0]) > 40 for line in shown)
    lava = tmp_path / "lava"  # refused from its config.json alone
    lava.mkdir()
    (lava / "config.json").write_text(RunConfig().to_json())
    refused = subprocess.run([sys.executable, str(script), str(lava)], capture_output=True, text=True, timeout=300)
    assert refused.returncode == 1 and refused.stderr.strip().startswith("rlbackdoors: error: sight_actions reads")
