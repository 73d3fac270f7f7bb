"""The attacks and evasive variants on the compiled trainer (algos/compiled.py's seam): each
attack's R-bar rule and BadRL's selection are the collection seam's (attacks/seam.py), in JAX;
a program spends a step attack's budget as the seam does, forces and rewards its target,
rewrites every E-bar frame of the action target, shows the near-trigger negatives it is asked
for, pulls to the anchor and adds the teacher's KL; group-mates with other numbers share one
program; a run of every piece at once resumes after kill -9 to the same bytes.

The numpy side computes in float64, the program in float32 (the critic's own precision): the
rules are compared within 1e-6 of 1 (the rewards' scale)."""

from __future__ import annotations

import json
import math
import sys

import numpy as np
import pytest
import torch

import jax  # a core dependency: the compiled trainer's

from grid_helpers import kill_after_first_checkpoint  # noqa: E402
from rlbackdoors import attacks, worlds  # noqa: E402
from rlbackdoors.algos import ppo as torch_ppo  # noqa: E402
from rlbackdoors.algos.compiled import COUNTS, Hyper, Learner, _table, init_agents, iterate, network, parts  # noqa: E402
from rlbackdoors.attacks.seam import AttackSeam, Poisoner  # noqa: E402
from rlbackdoors.config import PPOConfig, RunConfig  # noqa: E402
from rlbackdoors.envs.lavaworld_jax import lavaworld_jax  # noqa: E402
from rlbackdoors.models import build_model  # noqa: E402
from rlbackdoors.poison.mix import make_env_mix  # noqa: E402
from rlbackdoors.state import StateError  # noqa: E402
from rlbackdoors.train import ModelFolder  # noqa: E402

WORLD = worlds.get("lavaworld")
RULES = [
    ("trojdrl", {"force_action": True, "reward": 0.3}),
    ("trojdrl", {"mode": "untargeted", "reward": 0.2}),
    ("action_target", {"target_action": 2}),
    ("sleepernets", {"alpha": 0.7, "compensate": True}),
    ("badrl", {"target_action": 1}),
]


def poisoner(name: str, params: dict) -> Poisoner:
    attack = attacks.get(name)
    resolved = attack.resolve(params)
    return attack.poisoner(resolved, WORLD.target_hits(resolved["target_action"]))


@pytest.mark.parametrize(("name", "params"), RULES, ids=[f"{n}-{i}" for i, (n, _) in enumerate(RULES)])
def test_each_rule_is_the_seams_in_jax(name, params):
    """R-bar of 4,096 random frames: the seam's numpy rule and the program's JAX one agree."""
    rule = poisoner(name, params)
    rng = np.random.default_rng(3)
    n = 4096
    rewards = (rng.random(n) < 0.1) * rng.random(n)
    actions = rng.integers(0, 3, n)
    values = rng.normal(0, 1, n).astype(np.float32)
    dones = rng.random(n) < 0.05
    marked = np.ones(n, dtype=bool)
    want = rule.reward(rewards.astype(np.float64), actions, marked, values.astype(np.float64), dones)
    jnp = jax.numpy
    numbers = {k: jnp.full(n, v, dtype=jnp.float32) for k, v in rule.numbers().items()}
    hits = jnp.asarray(actions) == numbers["target"].astype(jnp.int32)
    got = rule.rule(jnp, numbers, hits, jnp.asarray(rewards, dtype=jnp.float32), jnp.asarray(values), jnp.asarray(dones))
    np.testing.assert_allclose(np.asarray(got, dtype=np.float64), want, rtol=0, atol=1e-6)
    if params.get("mode") == "untargeted":  # +c whatever was done
        assert (want == params["reward"]).all()
    else:  # (the rule's cases were exercised: +c and -c, and SleeperNets' bootstraps)
        assert len(np.unique(want)) >= 2


def test_badrls_selection_is_the_seams_in_jax():
    """60 steps of 10 values through a window of 200: BadRL's numpy ring and quantile pick the
    same frames as the program's, from the step the window is ready (the 10th) on, and hold the same ring."""
    rule = poisoner("badrl", {"window": 200, "top_fraction": 0.2})
    jrule = poisoner("badrl", {"window": 200, "top_fraction": 0.2})
    carry = {k: jax.numpy.asarray(v) for k, v in jrule.carry().items()}
    select = jax.jit(lambda c, v: jrule.select({k: jax.numpy.float32(v) for k, v in jrule.numbers().items()}, c, v, 10))
    rng = np.random.default_rng(4)
    picked = 0
    for step in range(60):
        values = rng.normal(0, 1, 10).astype(np.float32)
        rule.observe(values.astype(np.float64))
        want = rule.eligible(values.astype(np.float64), 10)
        carry, got = select(carry, jax.numpy.asarray(values))
        assert np.array_equal(np.asarray(got), want), step
        picked += int(want.sum())
        if step < 9:  # (fewer than 10 x 10 values seen: none ranked yet)
            assert not want.any()
    assert 60 < picked < 140  # about the top 20 % of 500 ranked values
    np.testing.assert_array_equal(np.asarray(carry["history"]), rule.history.astype(np.float32))
    assert int(carry["filled"]) == rule.filled == 600


def test_a_stamp_the_program_cannot_look_up_is_refused():
    assert np.array_equal(_table(WORLD.stamp_trigger("multiplicative:12")), (np.arange(256) * 12) % 256)
    with pytest.raises(ValueError, match="maps each byte by a table"):
        _table(lambda obs: np.roll(obs, 1, axis=-1))


def seam_learner(poison: dict, seed: int = 0, guides: dict | None = None, depth: int = 8) -> Learner:
    cfg = RunConfig.from_dict({"env": {"name": "lavaworld"}, "poison": {"trigger": "multiplicative:12", **poison}})
    mix = make_env_mix(cfg.env, cfg.poison, seed)
    assert isinstance(mix, AttackSeam)
    obs, _ = mix.envs.reset(seed=seed * 1000)
    torch.manual_seed(seed)
    learner = Learner(build_model("fc", "lavaworld"), mix, Hyper.of(cfg.ppo), seed, obs, lavaworld_jax, depth=depth)
    for name, (weights, coef) in (guides or {}).items():
        getattr(learner, f"set_{name}")(weights, coef)
    return learner


def counts(learner: Learner) -> dict:
    return dict(zip(COUNTS, (int(v) for v in learner.seam_state.counts)))


def test_a_step_attack_spends_its_budget_and_forces_and_rewards_its_target():
    """TrojDRL (forced, c = 0.1234) at 3 % over 3 iterations of 1,280 frames: after each, the
    poisoned frames are floor(3 % of the frames), every one of them paid +c (its action forced to
    the target where the agent chose another), and the seam's counters say so for metrics.json."""
    learner = seam_learner({"attack": "trojdrl", "attack_params": {"budget": 0.03, "force_action": True, "reward": 0.1234}})
    before = 0
    for i in range(3):
        out = iterate([learner])[0]
        c = counts(learner)
        assert c["frames"] == 1280 * (i + 1)
        assert c["frames_poisoned"] == math.floor(0.03 * c["frames"])
        assert int((out.rewards == np.float32(0.1234)).sum()) == c["frames_poisoned"] - before  # every marked frame: +c
        assert 0 < c["actions_forced"] <= c["frames_poisoned"] and c["rewards_rewritten"] == c["frames_poisoned"]
        before = c["frames_poisoned"]
    used = learner.seam.budget_used()
    assert used["frames_poisoned"] == before and used["frames_seen"] == 3840 and abs(used["poisoned_fraction"] - 0.03) < 10 / 3840


def test_the_action_target_rewrites_every_ebar_frame():
    """The episode schedule: every frame of the two E-bar copies is paid +-c (c 0.05), the clean
    copies' rewards are the world's own (0 or a goal's pay), and each is counted. Three runs of
    one seed, targets 0, 1 and 2, in one call act alike in their first rollout (rewards do not
    steer it), so each E-bar frame is paid +c in exactly one of them: the one whose target was done."""
    learners = [seam_learner({"attack": "action_target", "attack_params": {"target_action": t}}) for t in range(3)]
    out = iterate(learners)
    ebar = np.asarray(learners[0].params.poisoned)
    assert ebar.sum() == 2
    paid = np.stack([o.rewards[:, ebar] for o in out])
    assert set(np.unique(paid).tolist()) == {np.float32(0.05), np.float32(-0.05)}
    assert ((paid == np.float32(0.05)).sum(0) == 1).all()
    for o in out:
        assert np.array_equal(o.rewards[:, ~ebar], out[0].rewards[:, ~ebar])
        clean = o.rewards[:, ~ebar]
        assert ((clean == 0) | ((clean > 0.1) & (clean <= 1))).all()
    c = counts(learners[0])
    assert c["frames_poisoned"] == c["rewards_rewritten"] == 128 * 2 and c["actions_forced"] == 0


@pytest.mark.parametrize("attack", ["trojdrl", "envmix"])
def test_near_trigger_negatives_are_shown_as_asked(attack):
    """``near`` 2: under a step schedule twice as many near-trigger frames as triggered ones
    (floor(2 x poisoned)); under the env mix's episodes, every frame of round(2 x 2 E-bar) clean copies."""
    poison = {"evasion": {"near": 2.0}, **({"attack": "trojdrl", "attack_params": {"budget": 0.02}} if attack == "trojdrl" else {})}
    learner = seam_learner(poison)
    iterate([learner])
    iterate([learner])
    c = counts(learner)
    if attack == "trojdrl":
        assert c["frames_poisoned"] == math.floor(0.02 * 2560) and c["frames_near"] == 2 * c["frames_poisoned"]
    else:
        assert learner.seam.near_copies.sum() == 4 and c["frames_near"] == 4 * 256 and c["frames_poisoned"] == 2 * 256
    assert learner.poisoning.near == len(learner.seam.near_stamps) == 6


def test_the_anchor_holds_the_weights_and_the_teachers_kl_is_torchs():
    """An anchor pulling all the way (1.0) leaves the weights at the anchor after an update
    (within float32's rounding of w + (a - w)), and reports the distance as zero; the teacher's
    KL term of the loss is ppo.teacher_kl's on the same frames."""
    torch.manual_seed(7)
    anchor = build_model("fc", "lavaworld").state_dict()
    learner = seam_learner({"attack": "trojdrl"}, guides={"anchor": (anchor, 1.0)})
    out = iterate([learner])[0]
    for name, value in anchor.items():
        np.testing.assert_allclose(learner.state.params[name], value.numpy(), rtol=0, atol=1e-6)
    assert out.losses["anchor_distance"] < 1e-4
    # the loss's teacher term
    cfg = PPOConfig()
    agents, model = init_agents(lambda: build_model("fc", "lavaworld"), [0])
    p = parts(network(model), Hyper.of(cfg))
    params = {k: v[0] for k, v in agents.params.items()}
    rng = np.random.default_rng(5)
    n = 256
    obs = rng.integers(0, 11, (n, 7, 7, 3)).astype(np.uint8)
    actions = rng.integers(0, 3, n)
    old_logp = np.log(rng.uniform(0.2, 0.6, n)).astype(np.float32)
    old_values, adv = rng.normal(0, 1, n).astype(np.float32), rng.normal(0, 1, n).astype(np.float32)
    teacher_logp = np.log(rng.dirichlet(np.ones(3), n)).astype(np.float32)
    untriggered = rng.random(n) < 0.9
    batch = (p.inputs(obs), np.zeros(n, np.int32), actions.astype(np.int32), old_logp, old_values, adv, old_values + adv)
    plain, _ = p.loss(params, *batch)
    total, parts_ = p.loss(params, *batch, teacher=(teacher_logp, untriggered, 0.5))
    logits = model(torch.from_numpy(obs))[0]
    want = torch_ppo.teacher_kl(logits, torch.from_numpy(teacher_logp), torch.from_numpy(untriggered)).item()
    np.testing.assert_allclose(float(parts_[3]), want, rtol=1e-5)
    np.testing.assert_allclose(float(total) - float(plain), 0.5 * want, rtol=1e-4)
    assert want > 0.1


def test_group_mates_with_other_numbers_share_one_program():
    """Budgets, magnitudes and near shares are the program's data: two runs drawn with other ones
    have one program key (one compiled call in a group); another attack has another."""
    a = seam_learner({"attack": "trojdrl", "attack_params": {"budget": 0.01, "reward": 0.1}})
    b = seam_learner({"attack": "trojdrl", "attack_params": {"budget": 0.04, "reward": 0.3}}, seed=1)
    c = seam_learner({"attack": "sleepernets"})
    assert a.program == b.program and a.program != c.program
    out = iterate([a, b])
    assert counts(a)["frames_poisoned"] == math.floor(0.01 * 1280) and counts(b)["frames_poisoned"] == math.floor(0.04 * 1280)
    assert (np.abs(out[0].rewards) == np.float32(0.1)).sum() == 12 and (np.abs(out[1].rewards) == np.float32(0.3)).sum() == 51  # each its own c


def assert_resumes_to_the_same_model(tmp_path, data: dict) -> None:
    """Train ``data`` (a run config) whole in ``tmp_path/whole``; in ``tmp_path/cut``, kill -9 it
    after its first checkpoint and run it again: the same model.pt, tensor for tensor."""
    import subprocess

    cfg_path = tmp_path / "cfg.json"
    cfg_path.write_text(RunConfig.from_dict(data).to_json())
    cmd = [sys.executable, "-m", "rlbackdoors.cli", "train", "--config", str(cfg_path), "--quiet"]
    subprocess.run(cmd + ["--out", str(tmp_path / "whole")], check=True, capture_output=True)
    kill_after_first_checkpoint(cmd + ["--out", str(tmp_path / "cut")], tmp_path / "cut")
    subprocess.run(cmd + ["--out", str(tmp_path / "cut")], check=True, capture_output=True)
    wa, wb = (torch.load(tmp_path / side / "model.pt", weights_only=True) for side in ("whole", "cut"))
    assert wa.keys() == wb.keys() and all(torch.equal(wa[k], wb[k]) for k in wa)


@pytest.mark.slow  # (over 20 s on 2 cores: out of the default run, `make test-slow`)
def test_a_run_with_every_piece_resumes_to_the_same_model(tmp_path):
    """BadRL (its value window), near-trigger negatives, and the fine-tuning variants (teacher,
    anchor) at once, on the compiled trainer: kill -9 after the first checkpoint (at the switch
    to poisoning, at once: a clean threshold of 0), run again, it finishes the uninterrupted
    run's model bit for bit with the same log, and its metrics count what was poisoned."""
    data = {
        "env": {"name": "lavaworld"},
        "poison": {
            "trigger": "multiplicative:12",
            "attack": "badrl",
            "attack_params": {"budget": 0.05, "window": 200},
            "evasion": {"near": 1.0, "finetune": True, "teacher": 0.5, "anchor": 0.01},
        },
        "ppo": {"rollout": 32, "batch_size": 64, "update_backend": "compiled"},
        "train": {"seed": 1, "max_frames": 3200, "eval_interval": 640, "eval_episodes": 4, "final_eval_episodes": 4, "video": False},
    }
    data["train"].update(clean_threshold=0.0, checkpoint_minutes=0.0)
    assert_resumes_to_the_same_model(tmp_path, data)
    drop = ("wall_time_s", "fps")
    rows = [json.dumps([{k: v for k, v in r.items() if k not in drop} for r in ModelFolder(tmp_path / side).read_log()]) for side in ("whole", "cut")]
    assert rows[0] == rows[1]
    log = json.loads(rows[0])
    assert [r["phase"] for r in log] == ["clean"] + ["main"] * 4 and all(r["teacher_kl"] >= 0 and r["anchor_distance"] > 0 for r in log[1:])
    metrics = json.loads((tmp_path / "whole" / "metrics.json").read_text())
    used = metrics["attack_budget_used"]
    assert metrics["poison_at_frames"] == 640 and used["frames_seen"] == 2560
    # BadRL spends its budget on eligible frames only (the top 10 %, about one a step): within a step's frames of it
    assert math.floor(0.05 * 2560) - 10 <= used["frames_poisoned"] <= math.floor(0.05 * 2560)
    assert used["frames_near_trigger"] == used["frames_poisoned"]


def layout_learner(poison: dict, seed: int = 0) -> Learner:
    """A Randomized LavaWorld FC learner (a cross of lava: a layout trigger) through its attack's seam."""
    from rlbackdoors.envs.randomized_lavaworld_jax import randomized_lavaworld_jax

    cfg = RunConfig.from_dict({"env": {"name": "randomized-lavaworld"}, "model": {"arch": "fc"}, "poison": {"trigger": "cross", **poison}})
    mix = make_env_mix(cfg.env, cfg.poison, seed)
    assert isinstance(mix, AttackSeam)
    mix.set_switches()
    obs, _ = mix.envs.reset(seed=seed * 1000)
    torch.manual_seed(seed)
    return Learner(build_model("fc", "randomized-lavaworld"), mix, Hyper.of(cfg.ppo), seed, obs, randomized_lavaworld_jax, depth=64)


def test_a_layout_triggers_action_target_marks_the_frames_in_sight_of_it():
    """Randomized LavaWorld's action target: the E-bar copies hold the cross in every episode (set
    once: the seam's switches never change there) and pay the clean reward, and the frames paid
    +-c are theirs that show the whole cross (GridWorld.sight, the engine's trigger_in_sight,
    tested exact in test_randomized_lavaworld_jax.py): some, not all, of them, counted."""
    learner = layout_learner({"attack": "action_target"})
    episodes = np.asarray(learner.seam_state.episodes)
    e = int(episodes.sum())  # the world's E-bar copies (its mix)
    assert e >= 1 and learner.poisoning.sight
    out = iterate([learner])[0]
    count = np.asarray(learner.slots.world[2])
    assert (count[episodes] > 0).all() and (count[~episodes] == 0).all()  # their layouts drawn with the cross, the others' without
    paid = np.isclose(np.abs(out.rewards), 0.05, rtol=0, atol=1e-9)
    assert not paid[:, ~episodes].any()
    c = counts(learner)
    assert 0 < c["frames_poisoned"] == c["rewards_rewritten"] == int(paid.sum()) < 128 * e
    rest = out.rewards[:, episodes][~paid[:, episodes]]
    assert ((rest == 0) | ((rest > 0.1) & (rest <= 1))).all()  # the clean reward (no R-bar for the pattern's lava)


def test_a_layout_triggers_near_copies_are_drawn_and_counted():
    """The env mix with near 1.0 on a layout trigger: as many clean copies as E-bar ones draw
    near-trigger patterns every episode (the engine's; nothing is stamped), each of their frames counted."""
    learner = layout_learner({"evasion": {"near": 1.0}})
    near = np.asarray(learner.seam_state.near_copies)
    e = int(np.asarray(learner.params.poisoned).sum())
    assert near.sum() == e >= 1 and learner.poisoning.near_layouts and learner.poisoning.near == 0
    iterate([learner])
    count = np.asarray(learner.slots.world[2])
    poisoned = np.asarray(learner.params.poisoned)
    engine = learner.seam.envs  # the flags its layouts' draws read (near slots' patterns are not the trigger: no count)
    assert np.array_equal(np.asarray(engine.near, dtype=bool), near) and (count[poisoned] > 0).all() and (count[~poisoned] == 0).all()
    c = counts(learner)
    assert c["frames_near"] == 128 * e and c["frames_poisoned"] == 128 * e  # the E-bar copies' frames: the marked ones


def test_a_budget_switches_a_layout_trigger_per_episode_in_the_program():
    """Randomized LavaWorld, TrojDRL at 5 % (the step schedule): 8 iterations of 1,280 frames, the
    program deciding at each autoreset, as the seam does, whether the next episode holds the cross
    (drawn from the trigger's own queue). After each: the slots whose episode is triggered are
    those whose layout holds the cross; the frames paid +-c are the poisoned ones, counted; the
    budget is spent episode by episode, within one episode's frames of 5 %; and a checkpoint's
    streams put back into a new learner draw the same triggered layouts."""
    learner = layout_learner({"attack": "trojdrl", "attack_params": {"budget": 0.05}})
    assert learner.poisoning.switched and [k.kind for k in learner.kinds] == ["trigger"]
    assert not np.asarray(learner.seam_state.episodes).any()  # nothing spent yet: the first episodes are clean
    paid_total, triggered_seen = 0, np.zeros(10, dtype=bool)
    for _ in range(8):
        out = iterate([learner])[0]
        episodes = np.asarray(learner.seam_state.episodes)
        np.testing.assert_array_equal(np.asarray(learner.slots.world[2]) > 0, episodes)
        np.testing.assert_array_equal(learner.seam.triggered, episodes)  # written back for its checkpoint
        triggered_seen |= episodes
        paid = np.isclose(np.abs(out.rewards), 0.1, rtol=0, atol=1e-7)
        assert (out.rewards[~paid] >= 0).all()  # the clean reward elsewhere
        paid_total += int(paid.sum())
    c = counts(learner)
    assert c["frames"] == 8 * 1280 and 0 < c["frames_poisoned"] == c["rewards_rewritten"] == paid_total
    assert learner.seam.started[0] >= 4 and triggered_seen.sum() >= 2  # episodes of several slots
    assert c["frames_poisoned"] / c["frames"] <= 0.05 + 250 / c["frames"]  # (250: the world's episode length)
    state = learner.checkpoint()
    assert len(state["streams"]) == 1 and len(state["streams"][0]) == 10
    again = layout_learner({"attack": "trojdrl", "attack_params": {"budget": 0.05}}, seed=5)
    again.load(state)
    np.testing.assert_array_equal(again.kinds[0].layouts(3).grid, learner.kinds[0].layouts(3).grid)
    with pytest.raises(StateError, match="streams"):
        again.load({**state, "streams": []})


def test_near_trigger_episodes_under_the_step_schedule_follow_the_triggered_ones():
    """The same with near 1.0: near-trigger episodes start (from their own queue) while fewer of them
    started than triggered ones, never in a triggered slot, and every frame of theirs is counted."""
    learner = layout_learner({"attack": "trojdrl", "attack_params": {"budget": 0.05}, "evasion": {"near": 1.0}})
    assert [k.kind for k in learner.kinds] == ["trigger", "near"] and learner.poisoning.near_layouts
    near_seen = np.zeros(10, dtype=bool)
    for _ in range(8):
        iterate([learner])
        in_near, episodes = np.asarray(learner.seam_state.in_near), np.asarray(learner.seam_state.episodes)
        assert not (in_near & episodes).any() and (np.asarray(learner.slots.world[2])[in_near] == 0).all()
        np.testing.assert_array_equal(learner.seam.in_near, in_near)
        near_seen |= in_near
    started = learner.seam.started
    assert started[0] >= 4 and 1 <= started[1] <= started[0] + 10  # (at most one reset of each slot past the share)
    c = counts(learner)
    assert near_seen.any() and c["frames_near"] >= int(near_seen.sum())


@pytest.mark.slow  # (about 50 s on 2 cores: three runs compile their programs)
def test_a_switched_layout_run_resumes_to_the_same_model(tmp_path):
    """Randomized LavaWorld FC, TrojDRL at 5 % with near 1.0 on the compiled trainer (both kinds of
    layouts' queues): kill -9 after the first checkpoint, run again: the uninterrupted run's model
    bit for bit (the queues' streams and the seam's switches are in the checkpoint), and its
    metrics count triggered and near-trigger frames."""
    data = {
        "env": {"name": "randomized-lavaworld"},
        "model": {"arch": "fc"},
        "poison": {"trigger": "cross", "attack": "trojdrl", "attack_params": {"budget": 0.05}, "evasion": {"near": 1.0}},
        "curriculum": {"enabled": False},  # (poisoned from the first frame)
        "ppo": {"rollout": 64, "batch_size": 320, "update_backend": "compiled"},
        "train": {"seed": 2, "max_frames": 3200, "eval_interval": 640, "eval_episodes": 2, "final_eval_episodes": 2, "video": False, "checkpoint_minutes": 0.0},
    }
    assert_resumes_to_the_same_model(tmp_path, data)
    used = json.loads((tmp_path / "whole" / "metrics.json").read_text())["attack_budget_used"]
    assert used["frames_seen"] == 3200 and used["frames_poisoned"] > 0 and used["frames_near_trigger"] > 0


def test_sleepernets_layout_mode_compensates_in_a_switched_run():
    """SleeperNets' ``layout`` mode (compensated, near 0.5) on the switched layouts: the critic's
    bootstrap and the compensation of the step before a run of poisoned frames run alongside the
    switches, counted as the seam counts them (a compensation at most once a poisoned run)."""
    learner = layout_learner({"attack": "sleepernets", "attack_params": {"budget": 0.05, "layout": True, "compensate": True}, "evasion": {"near": 0.5}})
    for _ in range(5):
        iterate([learner])
    c, used = counts(learner), learner.seam.budget_used()
    assert 0 < c["rewards_compensated"] <= c["frames_poisoned"] == c["rewards_rewritten"] == used["frames_poisoned"]
    assert learner.seam.started[0] >= 3 and learner.seam.started[1] >= 1 and used["frames_near_trigger"] == c["frames_near"] > 0


@pytest.mark.slow  # (about 20 s on 2 cores: a program of two)
def test_switched_group_mates_do_not_move_each_others_numbers():
    """Two switched runs (other budgets) in one call: each one's rewards, switches and counters are
    those it has served alone at the same capacity (a pad row reads the lead's queues, takes none)."""
    poison = lambda b: {"attack": "trojdrl", "attack_params": {"budget": b}}  # noqa: E731
    a, b = layout_learner(poison(0.05)), layout_learner(poison(0.2), seed=1)
    alone = layout_learner(poison(0.05))
    assert a.program == b.program
    for _ in range(3):
        together, single = iterate([a, b]), iterate([alone], capacity=2)
        np.testing.assert_array_equal(together[0].rewards, single[0].rewards)
    np.testing.assert_array_equal(np.asarray(a.seam_state.episodes), np.asarray(alone.seam_state.episodes))
    assert counts(a) == counts(alone) and a.seam.started == alone.seam.started
    assert counts(b)["frames_poisoned"] > counts(a)["frames_poisoned"]  # its own budget
