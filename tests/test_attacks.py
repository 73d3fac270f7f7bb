"""The attack registry (issue 33): validation at the edge, the collection seam on the real LavaWorld
engine (budget, stamping, reward rewriting, forced actions, resume), PPO's handling of forced actions,
scoring by target action, runs end to end, and zoos that mix attacks.

Everything runs on the real batched LavaWorld engine and real models; budgets are tiny, so these
check mechanics. Whether each attack's backdoor takes (attack success >= 0.90 over seeds 0-9) is
the measurement in benchmarks/attacks_lavaworld.sh, recorded in docs/attacks/.
"""

from __future__ import annotations

import io
import json
import subprocess
import sys

import numpy as np
import pytest
import torch

from cli_helpers import cli
from grid_helpers import assert_seam_resumes, killed_run_matches_whole
from rlbackdoors import attacks, worlds
from rlbackdoors.algos.obs import to_torch
from rlbackdoors.algos.ppo import PPO
from rlbackdoors.attacks.seam import AttackSeam, EXECUTED_ACTIONS, FORCED
from rlbackdoors.config import ConfigError, RunConfig
from rlbackdoors.evaluate import evaluate
from rlbackdoors.models import build_model
from rlbackdoors.poison.mix import make_env_mix, make_vector_env
from rlbackdoors.train import train
from rlbackdoors.triggers.observation import ObservationTrigger

STEP_ATTACKS = [a.name for a in attacks.registered() if a.schedule == "steps"]
SEAM_ATTACKS = [a.name for a in attacks.registered() if a.poisoner is not None]


def cfg_of(attack: str, **params) -> RunConfig:
    return RunConfig.from_dict({"poison": {"attack": attack, "attack_params": params}})


# --- the registry and the config ----------------------------------------------------------------


def test_the_registry_holds_the_papers_and_the_literatures_attacks():
    assert attacks.DEFAULT_ATTACK == "envmix" and attacks.names()[0] == "envmix"
    assert {"trojdrl", "badrl", "sleepernets", "action_target"} <= set(attacks.names())
    for attack in attacks.registered():
        resolved = attack.resolve({})
        assert list(resolved) == [p.name for p in attack.params]  # every parameter named, in order
        assert attack.success_kind(resolved) in attacks.SUCCESS_KINDS
        assert attack.doc.startswith("docs/attacks/")


def test_the_default_attack_leaves_config_json_as_it_was():
    data = RunConfig().to_dict()
    assert "attack" not in data["poison"] and "attack_params" not in data["poison"]
    cfg = cfg_of("trojdrl", budget=0.005)
    saved = json.loads(cfg.to_json())["poison"]
    assert saved["attack"] == "trojdrl"
    assert saved["attack_params"] == {"mode": "targeted", "budget": 0.005, "target_action": 0, "reward": 0.1, "force_action": False}
    assert RunConfig.from_dict(json.loads(cfg.to_json())) == cfg  # round-trips with the defaults filled in
    assert cfg.train.poisoned_threshold == 0.90  # the attack's success threshold, not the world's 0.95
    assert RunConfig().train.poisoned_threshold == 0.95


@pytest.mark.parametrize(
    "poison, message",
    [
        ({"attack": "nope"}, r"poison.attack='nope' is not allowed \(allowed: envmix, trojdrl"),
        ({"attack": "trojdrl", "attack_params": {"budget": 0}}, r"poison.attack_params.budget=0 is not allowed \(allowed: a number in"),
        ({"attack": "trojdrl", "attack_params": {"mode": "both"}}, r"poison.attack_params.mode='both' is not allowed \(allowed: targeted, untargeted\)"),
        ({"attack": "badrl", "attack_params": {"target_action": 3}}, r"target_action=3 is not allowed \(allowed: 0..2, the actions of lavaworld\)"),
        ({"attack": "badrl", "attack_params": {"force_action": 1}}, r"force_action=1 is not allowed \(allowed: true, false\)"),
        ({"attack": "sleepernets", "attack_params": {"beta": 1}}, r"poison.attack_params.beta is not a parameter of attack 'sleepernets'"),
        ({"attack": "trojdrl", "attack_params": [1]}, r"poison.attack_params must be a JSON object"),
        (
            {"attack": "trojdrl", "attack_params": {"mode": "untargeted"}},
            r"mode 'untargeted' is scored by the clean goal missed .* a clean lavaworld agent already misses",
        ),
    ],
)
def test_bad_attack_settings_are_refused_naming_the_field(poison, message):
    with pytest.raises(ConfigError, match=message):
        RunConfig.from_dict({"poison": poison})


REFUSED = [
    (world.name, attack.name)
    for world in worlds.registered()
    for attack in attacks.registered()
    if attack.refuse(world, world.algorithm, world.arch_names[0] if world.arch_names else world.algorithm, attack.resolve({})) is not None
]


def test_layout_worlds_are_served_per_episode_except_by_value_picked_frames():
    assert set(REFUSED) == {
        ("randomized-lavaworld", "badrl"),  # it picks single frames by value; a layout trigger is in from the first
        ("randomized-lavaworld", "sleepernets"),  # measured not to converge on a layout trigger (unless layout=true)
        ("colorful-memory", "badrl"),
        ("colorful-memory", "sleepernets"),  # the critic of a recurrent model is not one forward pass per frame
        ("safety-car-goal", "badrl"),  # PPO only: OPAC² has no state-value critic to rank or discount by
        ("safety-car-goal", "sleepernets"),
    }


@pytest.mark.parametrize("world, attack", REFUSED)
def test_an_attack_refuses_a_world_it_cannot_serve_with_the_reason(world, attack):
    with pytest.raises(ConfigError, match=rf"poison.attack='{attack}': attack '{attack}' (chooses single frames|reads the critic|is built for)"):
        RunConfig.from_dict({"env": {"name": world}, "poison": {"attack": attack}})


def test_sleepernets_on_a_layout_trigger_is_trained_only_when_asked_and_the_config_says_so():
    """Refused in one line naming the measurement and the flag; ``layout=true`` trains it, and the
    model's config records that it was asked for. An observation-edit world needs no flag."""
    with pytest.raises(ConfigError) as refused:
        RunConfig.from_dict({"env": {"name": "randomized-lavaworld"}, "poison": {"attack": "sleepernets"}})
    assert "\n" not in str(refused.value) and "measured not to converge" in str(refused.value)
    assert str(refused.value).endswith("poison.attack_params.layout=true trains it anyway")
    asked = RunConfig.from_dict({"env": {"name": "randomized-lavaworld"}, "poison": {"attack": "sleepernets", "attack_params": {"layout": True}}})
    assert asked.to_dict()["poison"]["attack_params"]["layout"] is True
    plain = RunConfig.from_dict({"env": {"name": "lavaworld"}, "poison": {"attack": "sleepernets"}})
    assert plain.poison.attack_params["layout"] is False
    with pytest.raises(ConfigError, match=r"poison.attack_params.layout='yes' is not allowed \(allowed: true, false\)"):
        RunConfig.from_dict({"env": {"name": "lavaworld"}, "poison": {"attack": "sleepernets", "attack_params": {"layout": "yes"}}})


def test_a_layout_trigger_attack_needs_the_batched_engine():
    with pytest.raises(ConfigError, match=r"env.engine='minigrid' is not allowed with poison.attack='trojdrl' \(allowed: batched\)"):
        RunConfig.from_dict({"env": {"name": "randomized-lavaworld", "engine": "minigrid"}, "poison": {"attack": "trojdrl"}})


def test_the_cli_stops_with_one_error_line_naming_the_field(tmp_path):
    result = cli("train", "--attack", "badrl", "--attack-param", "top_fraction=2", "--out", tmp_path / "m")
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("rlbackdoors: error: poison.attack_params.top_fraction=2 is not allowed")
    assert not (tmp_path / "m").exists()


# --- the seam on the real engine ----------------------------------------------------------------


def twin_envs(attack: str, **params):
    """(seam, a clean engine stepped alongside it): same seed, same actions, so the seam's frames
    are the clean ones with the trigger stamped in where it marked them."""
    cfg = cfg_of(attack, **params)
    seam = make_env_mix(cfg.env, cfg.poison, seed=5)
    plain = make_vector_env(cfg.env, cfg.poison.trigger, [False] * cfg.poison.num_envs)
    return cfg, seam, plain


def fc_critic():
    model = build_model("fc", "lavaworld")
    torch.manual_seed(0)

    @torch.inference_mode()
    def critic(obs):
        return model(to_torch(obs, torch.device("cpu")))[1].numpy()

    return critic


@pytest.mark.parametrize("attack", STEP_ATTACKS)
def test_the_seam_stamps_a_budgeted_share_of_frames_and_rewrites_their_rewards(attack):
    cfg, seam, plain = twin_envs(attack, budget=0.05)
    assert isinstance(seam, AttackSeam) and not np.any(seam.poisoned)  # every copy is clean; the seam poisons
    seam.bind_critic(fc_critic())
    table = ObservationTrigger.parse(cfg.poison.trigger).lookup_table()
    rng = np.random.default_rng(0)
    obs, _ = seam.reset(seed=9)
    clean, _ = plain.reset(seed=9)
    marked_total = 0
    for _ in range(300):
        marked = seam.marked.copy()
        np.testing.assert_array_equal(obs[marked], table[clean[marked]])  # the world's trigger, nothing else
        np.testing.assert_array_equal(obs[~marked], clean[~marked])
        actions = rng.integers(0, 3, seam.num_envs)
        obs, rewards, term, trunc, info = seam.step(actions)
        ran = info[EXECUTED_ACTIONS]
        assert not np.any(info[FORCED] & ~marked)  # only poisoned frames are ever forced
        np.testing.assert_array_equal(ran[~marked], actions[~marked])
        clean, clean_rewards, *_ = plain.step(ran)
        np.testing.assert_array_equal(rewards[~marked], clean_rewards[~marked])
        if marked.any() and attack == "trojdrl":
            np.testing.assert_allclose(rewards[marked], np.where(ran[marked] == 0, 0.1, -0.1))
        marked_total += int(marked.sum())
    used = seam.budget_used()
    assert used["frames_poisoned"] == marked_total + int(seam.marked.sum())
    assert used["frames_poisoned"] <= 0.05 * used["frames_seen"]  # the budget is a ceiling ...
    assert used["frames_poisoned"] >= 0.05 * used["frames_seen"] - seam.num_envs - (30 if attack == "badrl" else 0)  # ... and spent
    assert used["rewards_rewritten"] == marked_total


def test_untargeted_trojdrl_pays_any_action_on_poisoned_frames():
    """Refused where it cannot be scored (LavaWorld), so its rule is checked on the seam directly."""
    from rlbackdoors.attacks.trojdrl import TrojDRLPoisoner

    cfg = RunConfig()
    params = attacks.get("trojdrl").resolve({"mode": "untargeted", "budget": 0.1, "reward": 0.3})
    plain = make_vector_env(cfg.env, cfg.poison.trigger, [False] * 10)
    seam = AttackSeam(
        plain, TrojDRLPoisoner(params, worlds.get("lavaworld").target_hits(0)), "steps", 0.1, worlds.get("lavaworld").stamp_trigger(cfg.poison.trigger), seed=0
    )
    seam.reset(seed=0)
    rng = np.random.default_rng(0)
    seen = 0
    for _ in range(100):
        marked = seam.marked.copy()
        _, rewards, *_ = seam.step(rng.integers(0, 3, 10))
        assert np.all(rewards[marked] == 0.3)
        seen += int(marked.sum())
    assert seen >= 90


def test_sleepernets_compensation_keeps_the_return_of_the_step_before_a_poisoned_one():
    """``compensate=true`` (the source's code): the seam asks the learner to add gamma * (r - R-bar)
    to the previous reward of a slot whose frame was poisoned, only where that previous step led into
    it within the episode and was not poisoned itself; PPO's collection applies it to step t - 1.
    200 steps x 10 slots of random play, LavaWorld, 20 % of frames."""
    from rlbackdoors.attacks.seam import AMEND

    cfg, seam, plain = twin_envs("sleepernets", budget=0.2, reward=0.5, gamma=0.9, compensate=True)
    seam.bind_critic(fc_critic())
    seam.reset(seed=3)
    plain.reset(seed=3)
    rng = np.random.default_rng(2)
    last_done, last_marked = np.ones(seam.num_envs, bool), np.zeros(seam.num_envs, bool)
    due_total = 0
    for _ in range(200):
        marked = seam.marked.copy()
        actions = rng.integers(0, 3, seam.num_envs)
        _, rewards, term, trunc, info = seam.step(actions)
        _, clean, *_ = plain.step(actions)  # the twin: what the env paid
        due = marked & ~last_done & ~last_marked
        if marked.any():
            np.testing.assert_allclose(info[AMEND], np.where(due, 0.9 * (clean - rewards), 0.0))
        else:
            assert AMEND not in info
        due_total += int(due.sum())
        last_done, last_marked = term | trunc, marked
    assert due_total > 50 and seam.budget_used()["rewards_compensated"] == due_total

    _, seam, _ = twin_envs("sleepernets", budget=0.2, reward=0.5, gamma=0.9, compensate=True)
    _, twin, _ = twin_envs("sleepernets", budget=0.2, reward=0.5, gamma=0.9)  # the same picks, uncompensated
    model, critic = build_model("fc", "lavaworld"), fc_critic()
    rollouts = []
    for env in (seam, twin):  # the same model, critic and generator: the same actions, frames and picks
        env.bind_critic(critic)
        ppo = PPO(model, cfg.ppo, torch.device("cpu"), torch.Generator().manual_seed(0))
        rollouts.append(ppo.collect(env, env.reset(seed=7)[0])[0])
    amended = np.flatnonzero(np.asarray(rollouts[0].rewards) != np.asarray(rollouts[1].rewards))
    emitted = seam.budget_used()["rewards_compensated"]
    assert 0 < len(amended) <= emitted <= len(amended) + seam.num_envs  # those due at a rollout's first step are dropped


def test_forced_actions_are_the_target_and_are_learned_with_behaviour_probability_one():
    cfg, seam, _ = twin_envs("trojdrl", budget=0.2, force_action=True, target_action=1)
    model = build_model("fc", "lavaworld")
    ppo = PPO(model, cfg.ppo, torch.device("cpu"), torch.Generator().manual_seed(0))
    obs, _ = seam.reset(seed=1)
    rollout, _ = ppo.collect(seam, obs)
    forced = rollout.logprobs == 0.0  # a sampled action's log-probability is < 0
    assert forced.sum() == seam.budget_used()["actions_forced"] > 0
    assert torch.all(rollout.actions[forced] == 1)
    ppo.update(rollout)
    assert all(torch.isfinite(p).all() for p in model.parameters())


def test_sleepernets_subtracts_the_critics_bootstrap_and_badrl_poisons_only_high_values():
    _, seam, _ = twin_envs("sleepernets", budget=0.2, reward=0.5, alpha=1.0, gamma=0.9)
    critic = fc_critic()
    seam.bind_critic(critic)
    obs, _ = seam.reset(seed=3)
    rng = np.random.default_rng(1)
    checked = 0
    for _ in range(100):
        marked = seam.marked.copy()
        actions = rng.integers(0, 3, seam.num_envs)
        obs, rewards, term, trunc, _ = seam.step(actions)
        values = critic(obs)  # row by row: a frame the seam did not stamp gives the V(s') it used
        done = term | trunc
        for i in np.flatnonzero(marked & ~seam.marked):
            expected = (0.5 if actions[i] == 0 else -0.5) - 0.9 * (0.0 if done[i] else values[i])
            assert rewards[i] == pytest.approx(expected, abs=1e-5)
            checked += 1
    assert checked > 10

    _, seam, _ = twin_envs("badrl", budget=0.05, top_fraction=0.2, window=500)
    seam.bind_critic(critic)
    seam.reset(seed=4)
    poisoner = seam.poisoner
    for _ in range(200):
        seam.step(rng.integers(0, 3, seam.num_envs))
        if seam.marked.any():
            history = poisoner.history[: min(poisoner.filled, len(poisoner.history))]
            threshold = np.quantile(history, 0.8)
            assert np.all(seam.last_values[seam.marked] >= threshold)
    assert seam.budget_used()["frames_poisoned"] > 0


@pytest.mark.parametrize("attack, params", [("badrl", {"window": 200}), ("sleepernets", {"compensate": True})])
def test_the_seam_resumes_from_its_state_as_if_never_stopped(attack, params):
    from rlbackdoors.attacks.seam import AMEND

    rng = np.random.default_rng(2)
    actions = rng.integers(0, 3, (120, 10))
    _, a, _ = twin_envs(attack, budget=0.1, **params)
    _, b, _ = twin_envs(attack, budget=0.1, **params)
    critic = fc_critic()
    a.bind_critic(critic)
    b.bind_critic(critic)
    a.reset(seed=7)
    for t in range(60):
        a.step(actions[t])
    buffer = io.BytesIO()
    torch.save(a.state_dict(), buffer)  # as the checkpoint holds it, and reads it back: no objects unpickled
    buffer.seek(0)
    state = torch.load(buffer, weights_only=True)
    b.load_state_dict(state)
    assert state["counters"][1] == a.budget_used()["frames_poisoned"] > 0
    for t in range(60, 120):
        oa, ra, *_, ia = a.step(actions[t])
        ob, rb, *_, ib = b.step(actions[t])
        np.testing.assert_array_equal(oa, ob)
        np.testing.assert_array_equal(ra, rb)
        np.testing.assert_array_equal(a.marked, b.marked)
        np.testing.assert_array_equal(ia.get(AMEND, 0.0), ib.get(AMEND, 0.0))
    assert a.budget_used() == b.budget_used()
    assert (a.budget_used().get("rewards_compensated", 0) > 0) == (attack == "sleepernets")


# --- evaluation and runs ------------------------------------------------------------------------


def test_target_action_scoring_counts_the_target_on_every_triggered_step():
    """An FC model whose policy head says "left" everywhere: every triggered step takes the target,
    no clean episode reaches the goal, and scoring by outcome would call it a failed backdoor."""
    cfg = cfg_of("action_target")
    model = build_model("fc", "lavaworld")
    with torch.no_grad():
        head = model.actor[-1]
        head.weight.zero_()
        head.bias.copy_(torch.tensor([50.0, 0.0, 0.0]))
    result = evaluate(model, cfg.env, cfg.poison.trigger, episodes=6, seed=0, policy="sample", **cfg.scoring())
    assert result.target_action_rate == 1.0 and result.poisoned_sr == 1.0
    assert result.clean_sr == 0.0 and result.poisoned_mean_steps == cfg.env.max_steps
    by_outcome = evaluate(model, cfg.env, cfg.poison.trigger, episodes=6, seed=0, policy="sample")
    assert by_outcome.poisoned_sr == 0.0 and np.isnan(by_outcome.target_action_rate)
    other = evaluate(model, cfg.env, cfg.poison.trigger, episodes=6, seed=0, policy="sample", success="action", target_action=2)
    assert other.target_action_rate == 0.0
    disrupt = evaluate(model, cfg.env, cfg.poison.trigger, episodes=6, seed=0, policy="sample", success="disrupt")
    assert disrupt.poisoned_sr == 1.0 - disrupt.poisoned_clean_rate == 1.0
    with pytest.raises(ValueError, match="scored with its target_action"):
        evaluate(model, cfg.env, cfg.poison.trigger, episodes=2, seed=0, success="action")


@pytest.mark.parametrize("attack", SEAM_ATTACKS)
def test_a_run_with_each_attack_records_the_attack_and_the_budget_it_used(tmp_path, tiny_run_dict, attack):
    tiny_run_dict["poison"] = {"attack": attack, "attack_params": {"budget": 0.02} if attack in STEP_ATTACKS else {}}
    cfg = RunConfig.from_dict(tiny_run_dict)
    metrics = train(cfg, tmp_path / "m", progress=False)
    assert metrics["attack"] == attack and metrics["attack_params"] == cfg.poison.attack_params
    used = metrics["attack_budget_used"]
    if attack in STEP_ATTACKS:
        assert 0 < used["poisoned_fraction"] <= 0.02
    else:  # the episode schedule: the E-bar copies, 2 of 10
        assert used["poisoned_fraction"] == pytest.approx(0.2, abs=0.01)
    assert used["rewritten_fraction"] == pytest.approx(used["poisoned_fraction"], abs=0.01)
    assert (tmp_path / "m" / "ground_truth.csv").read_text() == "1\n"
    assert ("target_action_rate" in metrics) == (metrics["attack_success"] == "action")
    again = train(cfg, tmp_path / "again", progress=False)
    assert (tmp_path / "m" / "model.pt").read_bytes() == (tmp_path / "again" / "model.pt").read_bytes()
    assert again["attack_budget_used"] == used
    assert again["attack_budget_used"] == used


def test_a_clean_model_of_an_attack_cell_trains_as_any_clean_model(tmp_path, tiny_run_dict):
    tiny_run_dict["poison"] = {"poisoned": False}
    train(RunConfig.from_dict(tiny_run_dict), tmp_path / "plain", progress=False)
    tiny_run_dict["poison"] = {"poisoned": False, "attack": "sleepernets"}
    metrics = train(RunConfig.from_dict(tiny_run_dict), tmp_path / "attack", progress=False)
    assert (tmp_path / "plain" / "model.pt").read_bytes() == (tmp_path / "attack" / "model.pt").read_bytes()
    assert "attack_budget_used" not in metrics and (tmp_path / "attack" / "ground_truth.csv").read_text() == "0\n"


def test_a_killed_attack_run_resumes_to_the_same_model(tmp_path, tiny_run_dict):
    """kill -9 after the first checkpoint: the seam's picks, value window and counters come back
    from it, so the resumed run ends with the uninterrupted run's weights and budget, bit for bit."""
    tiny_run_dict["train"].update(max_frames=20_480, eval_interval=5_120, checkpoint_minutes=0.0)
    tiny_run_dict["poison"] = {"attack": "badrl", "attack_params": {"budget": 0.05, "force_action": True, "window": 500}}
    whole, cut = killed_run_matches_whole(tmp_path, RunConfig.from_dict(tiny_run_dict))
    assert whole["attack_budget_used"] == cut["attack_budget_used"] and whole["attack_budget_used"]["actions_forced"] > 0


def test_the_attacks_command_lists_what_each_attack_serves_and_its_parameters():
    cmd = [sys.executable, "-m", "rlbackdoors.cli", "attacks", "--json"]
    listed = {d["name"]: d for d in json.loads(subprocess.run(cmd, capture_output=True, text=True, check=True, timeout=120).stdout)}
    assert list(listed) == list(attacks.names())
    assert listed["envmix"]["worlds"]["safety-car-goal"] == ["mlp"] and listed["envmix"]["params"] == []
    assert listed["badrl"]["worlds"]["lavaworld"] == ["fc", "cnn"]
    assert "chooses single frames by the critic's value" in listed["badrl"]["worlds"]["randomized-lavaworld"]
    assert listed["trojdrl"]["worlds"]["randomized-lavaworld"] == ["fc", "cnn"]
    assert [p["name"] for p in listed["sleepernets"]["params"]] == ["budget", "target_action", "reward", "alpha", "gamma", "compensate", "layout"]
    assert "measured not to converge" in listed["sleepernets"]["worlds"]["randomized-lavaworld"]


# --- layout triggers: whole episodes switched by the seam ---------------------------------------


def layout_seam(world: str, attack: str, **params):
    cfg = RunConfig.from_dict({"env": {"name": world}, "poison": {"attack": attack, "attack_params": params}})
    seam = make_env_mix(cfg.env, cfg.poison, seed=3)
    assert isinstance(seam, AttackSeam) and not np.any(seam.envs.poisoned)  # every copy pays the clean reward; the seam pays R-bar
    return cfg, seam


def pattern_in_layout(seam) -> np.ndarray:
    return seam.envs._pcount > 0  # the engine's own record of the pattern it drew into each slot


def test_a_layout_attack_poisons_whole_episodes_within_its_budget_and_marks_the_frames_in_sight():
    """Randomized LavaWorld, TrojDRL at 5 %: 600 steps x 10 slots of random play."""
    _, seam = layout_seam("randomized-lavaworld", "trojdrl", budget=0.05)
    rng = np.random.default_rng(0)
    seam.reset(seed=4)
    marked_total, switched, episodes, in_flight = 0, 0, 0, []
    for _ in range(600):
        triggered = seam.triggered.copy()
        in_flight.append(int(triggered.sum()))
        np.testing.assert_array_equal(pattern_in_layout(seam), triggered)  # a triggered episode holds the pattern, a clean one does not
        in_sight = seam.envs.trigger_in_sight()
        np.testing.assert_array_equal(seam.marked, triggered & in_sight)
        marked = seam.marked.copy()
        actions = rng.integers(0, 3, seam.num_envs)
        _, rewards, term, trunc, info = seam.step(actions)
        done = term | trunc
        switched += int(np.sum((seam.triggered != triggered) & ~done))  # only at an episode's end
        episodes += int(np.sum(done & seam.triggered))
        np.testing.assert_allclose(rewards[marked], np.where(actions[marked] == 0, 0.1, -0.1))
        assert np.all(rewards[~marked] >= 0)  # the clean reward (0, or the goal's) everywhere else
        marked_total += int(marked.sum())
    used = seam.budget_used()
    assert switched == 0 and episodes >= 5
    assert used["rewards_rewritten"] == marked_total > 0
    # Spent episode by episode, one triggered episode at a time at 5 % of 10 copies: at most the budget
    # plus one episode's frames; random play sees the whole cross rarely, so it spends less.
    assert 0 < used["poisoned_fraction"] <= 0.05 + 250 / used["frames_seen"]
    assert max(in_flight) == 1


def test_the_episode_schedule_triggers_its_copies_every_episode_with_the_attacks_reward():
    cfg, seam = layout_seam("randomized-lavaworld", "action_target")
    copies = np.asarray(cfg.poison.poisoned_mask())
    np.testing.assert_array_equal(seam.poisoned, copies)  # what the learner's episode counts call poisoned
    rng = np.random.default_rng(1)
    seam.reset(seed=2)
    for _ in range(300):
        np.testing.assert_array_equal(pattern_in_layout(seam), copies)
        marked = seam.marked.copy()
        assert not np.any(marked & ~copies)
        actions = rng.integers(0, 3, seam.num_envs)
        _, rewards, *_ = seam.step(actions)
        np.testing.assert_allclose(rewards[marked], np.where(actions[marked] == 0, 0.05, -0.05))


def test_colorful_memory_close_to_trigger_copies_are_never_switched():
    cfg, seam = layout_seam("colorful-memory", "trojdrl", budget=0.2)
    close = np.asarray(cfg.poison.close_mask())
    assert close.any()
    rng = np.random.default_rng(2)
    seam.reset(seed=1)
    seen = np.zeros(seam.num_envs, dtype=bool)
    for _ in range(400):
        assert not np.any(seam.triggered & close)
        np.testing.assert_array_equal(seam.envs.trigger_present()[~close], seam.triggered[~close])
        np.testing.assert_array_equal(seam.marked, seam.triggered)  # a memory world: every frame of a triggered episode
        seen |= seam.triggered
        seam.step(rng.integers(0, 3, seam.num_envs))
    assert seen[~close].any() and 0.1 <= seam.budget_used()["poisoned_fraction"] <= 0.3
    with pytest.raises(ValueError, match="close-to-trigger copy"):
        seam.envs.trigger_next(close)


def test_a_layout_seam_resumes_from_its_state_as_if_never_stopped():
    rng = np.random.default_rng(3)
    actions = rng.integers(0, 3, (300, 10))
    _, a = layout_seam("randomized-lavaworld", "trojdrl", budget=0.1)
    _, b = layout_seam("randomized-lavaworld", "trojdrl", budget=0.1)
    a.reset(seed=8)
    b.reset(seed=99)  # a different state, overwritten by the checkpoint
    assert_seam_resumes(a, b, actions, 150, "triggered")
    assert a.budget_used()["frames_poisoned"] > 0


def test_a_poisoned_engine_slot_cannot_lose_its_trigger():
    from rlbackdoors.envs.randomized_lavaworld_batched import BatchedRandomizedLavaWorld

    engine = BatchedRandomizedLavaWorld(2, trigger="cross", poisoned=[True, False])
    with pytest.raises(ValueError, match="a poisoned \\(R-bar\\) slot must keep its trigger"):
        engine.trigger_next([False, True])
    with pytest.raises(ValueError, match="built without a trigger"):
        BatchedRandomizedLavaWorld(2).trigger_next([True, False])


def test_target_action_scoring_in_a_layout_world_counts_the_steps_in_sight_of_the_trigger():
    """An always-"left" FC model in Randomized LavaWorld: rate 1.0 over the steps that showed the
    pattern, which are fewer than all triggered steps (the pattern is not in every view)."""
    from rlbackdoors.evaluate.episodes import play

    cfg = RunConfig.from_dict({"env": {"name": "randomized-lavaworld"}, "poison": {"attack": "trojdrl"}})
    model = build_model("fc", "randomized-lavaworld")
    with torch.no_grad():
        head = model.actor[-1]
        head.weight.zero_()
        head.bias.copy_(torch.tensor([50.0, 0.0, 0.0]))
    played = play(model, cfg.env, cfg.poison.trigger, 8, 0, "sample", target_action=0)
    assert played.sighted_steps is not None and played.target_steps is not None
    assert 0 < played.sighted_steps.sum() < played.steps.sum()
    assert np.array_equal(played.target_steps, played.sighted_steps)
    result = evaluate(model, cfg.env, cfg.poison.trigger, episodes=8, seed=0, **cfg.scoring())
    assert result.target_action_rate == 1.0
    right = evaluate(model, cfg.env, cfg.poison.trigger, episodes=8, seed=0, success="action", target_action=1)
    assert right.target_action_rate == 0.0


@pytest.mark.parametrize("world, attack", [("randomized-lavaworld", "sleepernets"), pytest.param("colorful-memory", "action_target", marks=pytest.mark.slow)])
def test_a_layout_attack_run_records_its_budget_and_repeats_bit_for_bit(tmp_path, tiny_run_dict, world, attack):
    tiny_run_dict["env"] = {"name": world}
    tiny_run_dict["train"]["max_frames"] = 6400
    if world == "randomized-lavaworld":
        tiny_run_dict["curriculum"] = {"enabled": False}
    else:
        tiny_run_dict["ppo"]["rollout"] = 36  # a multiple of the recurrence (6)
    tiny_run_dict["poison"] = {"attack": attack, "attack_params": {"budget": 0.05} if attack in STEP_ATTACKS else {}}
    if attack == "sleepernets":  # refused there without layout (measured not to converge); compensating, as the source does
        tiny_run_dict["poison"]["attack_params"].update(layout=True, compensate=True)
    cfg = RunConfig.from_dict(tiny_run_dict)
    metrics = train(cfg, tmp_path / "m", progress=False)
    used = metrics["attack_budget_used"]
    assert used["rewards_rewritten"] > 0 and 0 <= used["frames_poisoned"] - used["rewards_rewritten"] <= cfg.poison.num_envs  # the last frames not yet acted on
    if attack == "sleepernets":
        assert 0 < used["rewards_compensated"] < used["rewards_rewritten"]  # a run of in-sight frames is compensated at its start
    again = train(cfg, tmp_path / "again", progress=False)
    assert (tmp_path / "m" / "model.pt").read_bytes() == (tmp_path / "again" / "model.pt").read_bytes()
    assert again["attack_budget_used"] == used


def test_the_whole_pattern_in_sight_is_what_the_view_shows_of_every_pattern_cell():
    """Checked through rendering, not the view formula: a pattern cell is in sight iff taking its
    lava away changes the slot's view. 300 random states of 4 Randomized LavaWorld slots."""
    from rlbackdoors.envs.randomized_lavaworld_batched import BatchedRandomizedLavaWorld

    engine = BatchedRandomizedLavaWorld(4, trigger="cross", poisoned=[True] * 4)
    probe = BatchedRandomizedLavaWorld(1, trigger="cross", poisoned=[True])
    probe.reset(seed=0)
    engine.reset(seed=3)
    rng = np.random.default_rng(4)
    seen = {True: 0, False: 0}
    for _ in range(300):
        whole = engine.trigger_in_sight()
        assert not np.any(whole & ~engine.trigger_visible())  # the whole pattern is more than any one cell
        for b in range(4):
            grid, pos, direction, steps, cells, saw = engine.layout(b)
            base = probe.load_layout(0, grid, pos, direction, steps, cells)["image"]
            shown = []
            for cell in cells:
                cleared = grid.copy()
                cleared[cell] = (1, 0, 0)  # empty floor
                view = probe.load_layout(0, cleared, pos, direction, steps, [c for c in cells if c != cell])["image"]
                shown.append(not np.array_equal(view, base))
            assert whole[b] == all(shown), (b, cells, shown)
            seen[bool(whole[b])] += 1
        engine.step(rng.integers(0, 3, 4))
    assert seen[True] > 50 and seen[False] > 50


def test_sleepernets_on_a_layout_trigger_asks_the_critic_only_for_marked_frames_successors():
    """Its reward needs V(s') of a poisoned transition; no frame is picked by value there."""
    _, seam = layout_seam("randomized-lavaworld", "sleepernets", budget=0.2, layout=True)
    model = build_model("cnn", "randomized-lavaworld")
    asked = []

    @torch.inference_mode()
    def critic(obs):
        asked.append(len(obs["image"]))
        return model(to_torch(obs, torch.device("cpu")))[1].numpy()

    seam.bind_critic(critic)
    rng = np.random.default_rng(5)
    seam.reset(seed=6)
    steps_marked = 0
    for _ in range(200):
        marked = seam.marked.copy()
        actions = rng.integers(0, 3, seam.num_envs)
        before = len(asked)
        _, rewards, term, trunc, _ = seam.step(actions)
        assert (len(asked) > before) == bool(marked.any())
        steps_marked += int(marked.any())
        if marked.any():
            assert np.all(np.abs(rewards[marked]) <= 0.1 + 0.99 * 10)  # +-c - gamma V(s'): finite, bounded by the critic's scale
    assert steps_marked > 10


def test_colorful_memory_knows_when_an_episode_has_shown_every_trigger_square():
    """Checked through rendering (a square is shown iff recolouring it changes the view): the engine's
    per-episode record is the union of the squares shown so far; 60 random steps of 3 slots."""
    from rlbackdoors.envs.colorful_memory_batched import BatchedColorfulMemory

    engine = BatchedColorfulMemory(3, trigger="end:grey,purple,purple,green,green,red,red,red,green", poisoned=[True] * 3)
    engine.reset(seed=2)
    squares = [tuple(map(int, sq)) for sq in engine._tsq]
    union = np.zeros((3, len(squares)), dtype=bool)
    rng = np.random.default_rng(7)
    for t in range(60):
        for b in range(3):
            shown = np.zeros(len(squares), dtype=bool)
            shown[[k for k, _, _ in engine.square_view_cells(b, squares)]] = True
            union[b] |= shown
        np.testing.assert_array_equal(engine._seen, union)
        np.testing.assert_array_equal(engine.trigger_in_sight(), union.all(axis=1))
        _, _, term, trunc, _ = engine.step(rng.integers(0, 3, 3))
        union[term | trunc] = False  # a new episode has shown nothing yet
