"""Many agents per process (the group trainer): stacked forward, batched PPO, the group loop, and
zoos run with ``--group-size``.

What must hold: a stacked agent computes what it computes alone (up to float rounding: batched
kernels sum in another order), its numbers do not depend on its group-mates or the group size
(so a group-trained model is reproducible from its config), a group of one is today's lone path
(same bytes), every agent ends as an ordinary model folder, and a killed group resumes.
Equivalence of *trained outcomes* over many seeds is a measurement (experiments/group_equivalence/group_equivalence.py),
not a unit test.
"""

from __future__ import annotations

import collections
import copy
import csv
import hashlib
import io
import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import torch
from torch.utils._python_dispatch import TorchDispatchMode

from rlbackdoors.algos import group
from rlbackdoors.algos.ppo import PPO
from rlbackdoors.config import RunConfig
from rlbackdoors.models import build_model, minigrid
from rlbackdoors.poison.mix import make_env_mix
from rlbackdoors.train import train
from rlbackdoors.train.group import train_group
from rlbackdoors.validate import ConfigError
from rlbackdoors.zoo.index import read_metadata
from rlbackdoors.zoo.plan import plan
from rlbackdoors.zoo.run import run as zoo_run
from rlbackdoors.zoo.spec import parse_spec
from cli_helpers import cli

FEED_FORWARD = [("lavaworld", "fc"), ("lavaworld", "cnn"), ("randomized-lavaworld", "fc"), ("randomized-lavaworld", "cnn")]
TINY = {"ppo": {"rollout": 32}, "train": {"max_frames": 3200, "eval_interval": 1600, "eval_episodes": 4, "final_eval_episodes": 4, "video": False}}


def tiny(seed: int, env: str = "lavaworld", **extra) -> RunConfig:
    data = copy.deepcopy(TINY)
    data["train"]["seed"] = seed
    data["env"] = {"name": env}
    data.update(extra)
    return RunConfig.from_dict(data)


def learner(env: str, arch: str | None, seed: int, poison: dict | None = None, device: torch.device | None = None, **sections):
    """A PPO learner of ``env`` (``arch`` None: the world's default) on ``device`` (default CPU), its env mix reset."""
    data = {"env": {"name": env}, **({"model": {"arch": arch}} if arch else {}), "train": {"seed": seed}, **sections, **({"poison": poison} if poison else {})}
    cfg = RunConfig.from_dict(data)
    device = device or torch.device("cpu")
    torch.manual_seed(seed)
    ppo = PPO(build_model(cfg.model.arch, env).to(device), cfg.ppo, device, torch.Generator().manual_seed(seed))
    envs = make_env_mix(cfg.env, cfg.poison, seed)
    return ppo, envs, envs.reset(seed=seed * 1000)[0]


def weights_digest(model: torch.nn.Module) -> str:
    return hashlib.sha256(b"".join(p.detach().numpy().tobytes() for p in model.parameters())).hexdigest()


def convolutions(monkeypatch, conv: str) -> None:
    """A group's convolutions on this CPU as ``conv`` says (``models.minigrid.STACKED_CONV``: "each",
    one conv2d per agent, every device's default; "gemm", one batched product for all agents;
    "grouped", one conv2d with a group of channels per agent)."""
    monkeypatch.setitem(minigrid.STACKED_CONV, "cpu", conv)


CNN_GEMM = [(env, "cnn", conv) for env in ("lavaworld", "randomized-lavaworld") for conv in ("gemm", "grouped")]


@pytest.mark.parametrize("env,arch,conv", [(e, a, "each") for e, a in FEED_FORWARD] + CNN_GEMM)
def test_stacked_forward_is_each_agents_forward(env, arch, conv, monkeypatch):
    """K agents' stacked forward computes each agent's own (to float rounding), the CNNs' with
    their convolutions one per agent (a CPU group), unfolded into one batched product (STACKED_CONV's
    "gemm") or one grouped conv2d ("grouped")."""
    convolutions(monkeypatch, conv)
    torch.manual_seed(0)
    models = [build_model(arch, env) for _ in range(3)]
    params = {name: torch.stack([m.get_parameter(name).detach() for m in models]) for name, _ in models[0].named_parameters()}
    image = torch.randint(0, 11, (3, 6, 7, 7, 3), dtype=torch.uint8)
    if env == "randomized-lavaworld":
        direction = torch.randint(0, 4, (3, 6))
        logits, values = models[0].forward_stacked(params, {"image": image, "direction": direction})
        alone = [m({"image": image[k], "direction": direction[k]}) for k, m in enumerate(models)]
    else:
        logits, values = models[0].forward_stacked(params, image)
        alone = [m(image[k]) for k, m in enumerate(models)]
    assert logits.shape == (3, 6, 3) and values.shape == (3, 6)
    for k, (lk, vk) in enumerate(alone):
        torch.testing.assert_close(logits[k], lk, rtol=1e-5, atol=1e-5)
        torch.testing.assert_close(values[k], vk, rtol=1e-5, atol=1e-5)


def step_both(alone: list, grouped: list) -> tuple[list, list, list]:
    """One rollout and update for each lone learner and for the group (both lists updated in place):
    the lone (rollout, stats) pairs, the group's (rollout, obs) results and its stats."""
    lone = []
    for k, (ppo, envs, obs) in enumerate(alone):
        rollout, obs = ppo.collect(envs, obs)
        lone.append((rollout, ppo.update(rollout)))
        alone[k] = (ppo, envs, obs)
    ppos = [g[0] for g in grouped]
    results = group.collect(ppos, [g[1] for g in grouped], [g[2] for g in grouped])
    stats = group.update(ppos, [r for r, _ in results])
    grouped[:] = [(g[0], g[1], obs) for g, (_, obs) in zip(grouped, results)]
    return lone, results, stats


# Log-probabilities of a rollout, group vs lone (experiments/kernel_spread/kernel_spread.json, avx512, avx2 and
# no-SIMD kernels): the first rollout is played by identical weights (measured 1.2e-7 at most: fp32
# rounding of one forward); the second by weights one update apart in rounding, which Adam turns
# into steps of up to its learning rate in weights whose gradient is near 0 (measured 2.1e-4): 5x.
LOGP_ATOL = (1e-6, 1e-3)


def test_group_collect_and_update_match_each_agent_alone():
    """Three agents (one poisoned by an attack that forces actions through the seam): the same
    rollouts (uniforms and env steps are each agent's own) and, after two updates, the same
    weights and Adam state as three lone learners, to float rounding."""
    poisons = [None, {"trigger": "additive:135", "attack": "trojdrl", "attack_params": {"budget": 0.05}}, None]
    alone = [learner("lavaworld", "fc", s, p) for s, p in enumerate(poisons)]
    grouped = [learner("lavaworld", "fc", s, p) for s, p in enumerate(poisons)]
    forced_seen = 0
    for update in range(2):
        lone_pairs, results, stats = step_both(alone, grouped)
        for k in range(3):
            (lone, lone_stats), ours = lone_pairs[k], results[k][0]
            assert torch.equal(lone.actions, ours.actions)
            np.testing.assert_array_equal(lone.rewards, ours.rewards)
            torch.testing.assert_close(lone.logprobs, ours.logprobs, rtol=0, atol=LOGP_ATOL[update])
            # measured 5.6e-5 at most (update 2, kernel_spread.json; 8.9e-5 lone vs lone across kernels)
            assert stats[k]["grad_norm"] == pytest.approx(lone_stats["grad_norm"], rel=1e-3)
            forced_seen += int((ours.logprobs == 0).sum())
    assert forced_seen > 0  # the poisoned agent's forced actions went through the group's collect
    for (lone_ppo, _, _), (ppo, envs, _) in zip(alone, grouped):
        for (name, a), b in zip(lone_ppo.model.named_parameters(), ppo.model.parameters()):
            # within one Adam step (lr): measured 0.43 lr at most over three kernel sets (kernel_spread.json)
            torch.testing.assert_close(a, b, rtol=1e-3, atol=ppo.cfg.lr, msg=name)
            sa, sb = lone_ppo.optimizer.state[a], ppo.optimizer.state[b]
            assert float(sa["step"]) == float(sb["step"]) == 2 * ppo.cfg.epochs * -(-ppo.cfg.rollout * envs.num_envs // ppo.cfg.batch_size)
            # on the moment's own scale: its last minibatches' gradients, which differ as the weights do
            # (measured 3.7e-2 of the largest at most over three kernel sets, kernel_spread.json; another
            # agent's moments or a missed step differ by the moment itself)
            for moment in ("exp_avg", "exp_avg_sq"):
                assert float((sa[moment] - sb[moment]).abs().max()) <= 1e-1 * float(sa[moment].abs().max())


def rollout_digest(rollout) -> str:
    """SHA-256 of every tensor and array of a rollout (obs, actions, log-probabilities, values,
    advantages, returns, rewards, ends, outcomes, steps)."""
    h = hashlib.sha256()
    for name, value in sorted(vars(rollout).items()):
        if isinstance(value, torch.Tensor):
            value = value.cpu().numpy()
        if isinstance(value, np.ndarray):
            h.update(name.encode() + value.tobytes())
    return h.hexdigest()


def engine_cycles(device_engine: bool, device: torch.device | None = None) -> tuple[list, int]:
    """Three rollouts and updates of four LavaWorld FC agents (clean and env mix) on ``device``:
    per agent and cycle the digests of its rollout, next observations, weights and engines' whole
    state; and how many episodes ended in the last rollout."""
    learners = [learner("lavaworld", "fc", s, poison={"poisoned": False} if s % 2 else None, device=device, ppo={"rollout": 64}) for s in range(4)]
    digests = []
    for _ in range(3):
        ppos = [g[0] for g in learners]
        results = group.collect(ppos, [g[1] for g in learners], [g[2] for g in learners], device_engine=device_engine)
        group.update(ppos, [r for r, _ in results])
        learners = [(g[0], g[1], obs) for g, (_, obs) in zip(learners, results)]
        for (ppo, envs, obs), (rollout, _) in zip(learners, results):
            state = json.dumps(envs.state_dict(), sort_keys=True, default=str)
            digests.append((rollout_digest(rollout), obs.tobytes(), weights_digest(copy.deepcopy(ppo.model).cpu()), state))
    return digests, sum(int(r.dones.sum()) for r, _ in results)


def test_a_group_on_the_device_engine_trains_the_bytes_of_the_numba_engine():
    """Three rollouts and updates with the slots stepped by the device engine
    (envs/lavaworld_device.py, here on the CPU) give the bytes of the numba engine's: rollouts,
    next observations, weights, and the engines' whole state after each rollout (handed back:
    layouts, positions, and the RNG words where the next autoreset draws)."""
    (numba, _), (device, ends) = engine_cycles(False), engine_cycles(True)
    assert len(numba) == 12 and numba == device
    assert ends > 0  # episodes ended (and autoresets took queued layouts) in the last rollout


def test_a_groups_idle_seams_skip_their_steps_and_poison_as_alone(monkeypatch):
    """The seams of a group at TrojDRL's default 1 % budget have nothing to do in most steps
    (:class:`rlbackdoors.attacks.seam.SeamGroup` counts their frames for them): they still pick,
    stamp, force and pay as lone seams do, over rollouts that carry their counts on. Beside them a
    clean agent, one whose budget works every step, and near-trigger negatives (a seam that never idles)."""
    from rlbackdoors.attacks.seam import AttackSeam

    stamp = {"trigger": "additive:135", "attack": "trojdrl"}
    poisons = [
        {**stamp, "attack_params": {"budget": 0.01}},
        None,
        {**stamp, "attack_params": {"budget": 0.01, "force_action": True}},
        {**stamp, "attack_params": {"budget": 0.2}},
        {**stamp, "attack_params": {"budget": 0.01}, "evasion": {"near": 1.0}},
    ]
    alone = [learner("lavaworld", "fc", s, p) for s, p in enumerate(poisons)]
    grouped = [learner("lavaworld", "fc", s, p) for s, p in enumerate(poisons)]
    prepared: collections.Counter = collections.Counter()
    real = AttackSeam.prepare

    def counted(self, actions):
        prepared[id(self)] += 1
        return real(self, actions)

    monkeypatch.setattr(AttackSeam, "prepare", counted)
    T = grouped[0][0].cfg.rollout
    for rollout in range(2):  # the second starts from the counts the first left in the seams
        lone_pairs, results, _ = step_both(alone, grouped)
        for k in range(len(poisons)):
            lone, ours = lone_pairs[k][0], results[k][0]
            assert torch.equal(lone.actions, ours.actions)
            np.testing.assert_array_equal(lone.rewards, ours.rewards)
            assert torch.equal(lone.logprobs == 0, ours.logprobs == 0)  # the forced actions (probability 1)
            np.testing.assert_array_equal(alone[k][2], grouped[k][2])  # the next frames, stamped as alone
            if poisons[k] is not None:
                lone_seam, seam = alone[k][1], grouped[k][1]
                assert seam.budget_used() == lone_seam.budget_used()
                assert json.dumps(seam.state_dict(), sort_keys=True, default=str) == json.dumps(lone_seam.state_dict(), sort_keys=True, default=str)
    used = [grouped[k][1].budget_used() for k in (0, 2, 4)]
    assert all(u["frames_poisoned"] > 0 for u in used) and used[1]["actions_forced"] > 0 and used[2]["frames_near_trigger"] > 0
    works = [prepared[id(grouped[k][1])] for k in (0, 2, 3, 4)]
    # 1 %: a pick about every 10 steps of 10 frames and the marked step after it; 20 %: 2 frames a step
    assert works[0] < T and works[1] < T, works
    assert works[2] == works[3] == 2 * T, works  # a budget spent every step, and a seam that never idles


def cm_learner(seed: int, poison: dict | None = None):
    """A Colorful Memory learner: recurrent CNN-GRU with the auxiliary memory head, short rollouts."""
    data = {"env": {"name": "colorful-memory"}, "ppo": {"rollout": 24, "batch_size": 120, "aux_memory_coef": 0.5}, "train": {"seed": seed}}
    cfg = RunConfig.from_dict({**data, **({"poison": poison} if poison else {})})
    torch.manual_seed(seed)
    ppo = PPO(build_model(cfg.model.arch, "colorful-memory"), cfg.ppo, torch.device("cpu"), torch.Generator().manual_seed(seed))
    envs = make_env_mix(cfg.env, cfg.poison, seed)
    return ppo, envs, envs.reset(seed=seed * 1000)[0]


@pytest.mark.parametrize("conv", ["each", "gemm", "grouped"])
def test_recurrent_group_with_the_memory_head_matches_each_agent_alone(conv, monkeypatch):
    """Colorful Memory (CNN-GRU, truncated BPTT, auxiliary memory loss): the group's rollouts carry
    the same actions, memory targets and (to rounding) memories, its losses and weights match;
    also with STACKED_CONV's "gemm" and "grouped" convolutions (one call for all agents)."""
    convolutions(monkeypatch, conv)
    alone, grouped = [cm_learner(s) for s in range(3)], [cm_learner(s) for s in range(3)]
    for _ in range(2):
        lone, results, stats = step_both(alone, grouped)
        for k in range(3):
            ours = results[k][0]
            assert torch.equal(lone[k][0].actions, ours.actions) and torch.equal(lone[k][0].memory_targets, ours.memory_targets)
            torch.testing.assert_close(lone[k][0].memories, ours.memories, rtol=1e-4, atol=1e-4)
            assert stats[k]["aux_memory_loss"] == pytest.approx(lone[k][1]["aux_memory_loss"], rel=1e-4)
            assert stats[k]["grad_norm"] == pytest.approx(lone[k][1]["grad_norm"], rel=1e-3)
    for (lone_ppo, _, _), (ppo, _, _) in zip(alone, grouped):
        for a, b in zip([*lone_ppo.model.parameters(), *lone_ppo.aux.parameters()], [*ppo.model.parameters(), *ppo.aux.parameters()]):
            torch.testing.assert_close(a, b, rtol=1e-3, atol=1e-4)


@pytest.mark.parametrize(
    "env,arch,conv",
    [("lavaworld", "fc", "each"), ("lavaworld", "cnn", "each"), ("randomized-lavaworld", "fc", "each"), ("colorful-memory", None, "each")]
    + [
        pytest.param(env, arch, conv, marks=pytest.mark.slow) if env == "randomized-lavaworld" else (env, arch, conv)  # (over 20 s each: make test-slow)
        for env, arch in (("randomized-lavaworld", "cnn"), ("colorful-memory", None))
        for conv in ("gemm", "grouped")
    ],
)
def test_an_agents_bytes_do_not_depend_on_its_group(env, arch, conv, monkeypatch):
    """Agent 0 trained alone through the stacked path, or beside 1, 2 or 7 others: the same
    weights, byte for byte (Colorful Memory: its auxiliary memory head's too); the CNNs also with
    STACKED_CONV's "gemm" convolutions (one batched product for all agents). With "grouped" (one
    grouped conv2d) the library may pick its kernel by the group's width (measured: the
    Randomized LavaWorld CNN's bytes differ across widths on this CPU), so the bytes may hang on
    the width (fixed on CUDA), never on the mates: beside other mates at the same width, the same."""
    convolutions(monkeypatch, conv)
    digests: dict[int | None, set[str]] = collections.defaultdict(set)
    compositions = ([0], [0, 1], [0, 2, 3], [0, 5, 6, 7, 8, 9, 10, 11]) + (([0, 4], [0, 6, 7]) if conv == "grouped" else ())
    for seeds in compositions:
        learners = [learner(env, arch, s) if arch else cm_learner(s) for s in seeds]
        ppos, envs, obs = [x[0] for x in learners], [x[1] for x in learners], [x[2] for x in learners]
        for _ in range(2):
            results = group.collect(ppos, envs, obs)
            group.update(ppos, [r for r, _ in results])
            obs = [o for _, o in results]
        width = group.group_width(len(seeds), ppos[0].device) if conv == "grouped" else None
        digests[width].add(weights_digest(ppos[0].model) + (weights_digest(ppos[0].aux) if ppos[0].aux is not None else ""))
    assert all(len(d) == 1 for d in digests.values()), {w: len(d) for w, d in digests.items()}


def opac2_learner(seed: int, device: torch.device | str = "cpu"):
    """A small OPAC² agent on ``device`` with its own replay filled from its own random transitions."""
    from rlbackdoors.algos.opac2 import OPAC2, MultitaskReplay
    from rlbackdoors.config import OPAC2Config

    agent = OPAC2(6, 2, OPAC2Config(depth=2, width=32, batch_size=64, obs_norm=True), torch.Generator().manual_seed(seed), device)
    rng = np.random.default_rng(seed)
    replay = MultitaskReplay.create({"clean": 0.8, "poisoned": 0.2}, 1000, 6, 2)
    for kind in ("clean", "poisoned"):
        replay[kind].add_batch(rng.normal(size=(500, 6)), rng.uniform(-1, 1, (500, 2)), rng.normal(size=500), rng.normal(size=(500, 6)), rng.random(500) < 0.05)
    agent.observe(rng.normal(size=(50, 6)))
    return agent, replay


def test_opac2_group_acts_and_updates_as_each_agent_alone():
    """Three OPAC² agents, five updates batched against five lone updates each: the same losses,
    weights, target network and Adam state to float rounding, every generator in the same place
    (the same replay indices and noise were drawn), and the same sampled actions before and after
    (after: from the updated policies, not the group's cached stack)."""
    from rlbackdoors.algos import group_opac2

    alone, grouped = [opac2_learner(s) for s in range(3)], [opac2_learner(s) for s in range(3)]
    lone_rngs, group_rngs = ([np.random.default_rng([s, 1]) for s in range(3)] for _ in range(2))
    obs = [np.random.default_rng(s).normal(size=(10, 6)) for s in range(3)]
    before = group_opac2.act([a for a, _ in grouped], obs)  # the group's stacked policy is now cached
    for x, y in zip([a.act(o) for (a, _), o in zip(alone, obs)], before):
        np.testing.assert_allclose(y, x, rtol=1e-4, atol=1e-5)
    lone = [[a.update(r, g) for _ in range(5)] for (a, r), g in zip(alone, lone_rngs)]
    ours = group_opac2.update([a for a, _ in grouped], [r for _, r in grouped], group_rngs, 5)
    for k in range(3):
        for mine, theirs in zip(ours[k], lone[k]):
            assert mine.keys() == theirs.keys() and all(mine[key] == pytest.approx(theirs[key], rel=1e-4, abs=1e-5) for key in mine)
        (a, _), (b, _) = alone[k], grouped[k]
        for net in ("policy", "q", "v", "v_target"):
            for (name, x), y in zip(getattr(a, net).named_parameters(), getattr(b, net).parameters()):
                torch.testing.assert_close(y.detach(), x.detach(), rtol=1e-4, atol=1e-5, msg=f"{net}.{name}")
        for net in ("policy", "q", "v"):
            opt_a, opt_b = getattr(a, f"{net}_opt"), getattr(b, f"{net}_opt")
            for x, y in zip(opt_a.param_groups[0]["params"], opt_b.param_groups[0]["params"]):
                sa, sb = opt_a.state[x], opt_b.state[y]
                assert float(sa["step"]) == float(sb["step"]) == 5 and (sa["step"].dtype, sa["step"].device) == (sb["step"].dtype, sb["step"].device)
                torch.testing.assert_close(sb["exp_avg"], sa["exp_avg"], rtol=1e-3, atol=1e-6)
        assert torch.equal(a.generator.get_state(), b.generator.get_state()) and lone_rngs[k].random() == group_rngs[k].random()
    for x, y in zip([a.act(o) for (a, _), o in zip(alone, obs)], group_opac2.act([a for a, _ in grouped], obs)):  # the updated policies, not the cache
        np.testing.assert_allclose(y, x, rtol=1e-4, atol=1e-5)


EVAL_CASES = {
    "lavaworld": [{"poisoned": False}, {"trigger": "multiplicative:3"}, {"attack": "action_target"}],
    "colorful-memory": [{"poisoned": False}, {}, {"attack": "action_target"}],
}


@pytest.mark.parametrize("env", sorted(EVAL_CASES))
def test_group_evaluations_play_each_agent_as_it_plays_alone(env):
    """Three untrained agents' evaluations in lockstep (one batched forward a step, ``stacked_act``;
    Colorful Memory recurrent, with its close-to-trigger layouts): a clean model, an env-mix one
    under another trigger and an action-target one (its target-action count) read the same
    numbers as each evaluated alone, 12 episodes per condition; agent 1 alone in the lockstep
    path reads them too, so an evaluation does not depend on its group-mates. (LavaWorld's
    engines of the three are stepped by one call, ``EngineGroup``: the same numbers.)"""
    from rlbackdoors.train.driver import Evaluate, evaluate_run, evaluate_runs
    from rlbackdoors.train.group import batch_key

    cfgs = [RunConfig.from_dict({"env": {"name": env}, "poison": poison, "train": {"seed": s}}) for s, poison in enumerate(EVAL_CASES[env])]
    models = []
    for cfg in cfgs:
        torch.manual_seed(cfg.train.seed)
        models.append(build_model(cfg.model.arch, env))
    alone = [evaluate_run(m, c, 12).to_dict() for m, c in zip(models, cfgs)]
    together = [r.to_dict() for r in evaluate_runs(models, cfgs, [12] * 3, group.stacked_act)]
    assert together == alone
    assert not np.isnan(alone[2]["target_action_rate"]) and len({a["clean_mean_steps"] for a in alone}) == 3  # three different agents
    assert evaluate_runs(models[1:2], cfgs[1:2], [12], group.stacked_act)[0].to_dict() == alone[1]
    # a group trainer batches these requests together (and another episode count apart)
    keys = {batch_key(Evaluate(m, c, 12)) for m, c in zip(models, cfgs)}
    assert len(keys) == 1 and None not in keys and batch_key(Evaluate(models[0], cfgs[0], 13)) not in keys


@pytest.mark.parametrize("env", sorted(EVAL_CASES))
def test_agents_stepped_after_their_episodes_ended_read_the_same_episodes(env):
    """On a GPU a lockstep evaluation drops the agents whose episodes have all ended only once
    fewer than half are live (regrouping the engines costs more there than stepping them); until
    then they are stepped and drawn for like the others, on their own slots and generators. Four
    untrained agents (two clean, two env mix; sampled episodes, 12 each in LavaWorld, 3 in
    Colorful Memory, where more all end at its 250-step limit; the agents' last episodes end at
    different steps): every agent's episodes are the same whether the group regroups at once (the CPU's
    rule), at half, or never, and the same as played alone."""
    from rlbackdoors.agent import Agent
    from rlbackdoors.evaluate.episodes import _vector_envs, play_episodes, play_lockstep

    cfgs = [RunConfig.from_dict({"env": {"name": env}, "poison": {"poisoned": k % 2 == 1}, "train": {"seed": k}}) for k in range(4)]
    episodes = 3 if env == "colorful-memory" else 12
    agents = []
    for cfg in cfgs:
        torch.manual_seed(cfg.train.seed)
        agents.append(Agent(cfg.world, cfg, build_model(cfg.model.arch, env)))

    def envs():
        return [_vector_envs(c.env, c.poison.trigger if c.poison.poisoned else None, episodes, None) for c in cfgs]

    seeds = [1000 + k for k in range(4)]
    alone = [play_episodes(a, e, s) for a, e, s in zip(agents, envs(), seeds)]
    assert len({int(p.steps.max()) for p in alone}) > 1  # the agents' last episodes end at different steps: the live set shrinks
    for regroup in (1.0, 0.5, 0.0):
        together = play_lockstep(agents, envs(), seeds, "sample", act=group.stacked_act(agents), regroup=regroup)
        for a, b in zip(together, alone):
            for x, y in zip(a, b):
                assert (x is None and y is None) or np.array_equal(x, y)


def test_a_groups_adam_state_is_each_agents_own_and_written_in_place():
    """The group writes each agent's Adam state back in torch's format with one multi-tensor copy:
    after two updates of three agents every moment is the agent's own tensor (its own storage of
    the parameter's size, so a checkpoint holds that agent's moments and no one else's), the step
    a float32 scalar, and the second update wrote into the first's tensors (no new ones)."""
    grouped = [learner("lavaworld", "fc", s) for s in range(3)]
    ppos, envs, obs = (list(x) for x in zip(*grouped))
    first: dict = {}
    for update in range(2):
        results = group.collect(ppos, envs, obs)
        group.update(ppos, [r for r, _ in results])
        obs = [o for _, o in results]
        for k, ppo in enumerate(ppos):
            for name, param in ppo.model.named_parameters():
                state = ppo.optimizer.state[param]
                assert list(state) == ["step", "exp_avg", "exp_avg_sq"]
                assert state["step"].dtype == torch.float32 and state["step"].dim() == 0
                assert float(state["step"]) == (update + 1) * ppo.cfg.epochs * -(-ppo.cfg.rollout * envs[k].num_envs // ppo.cfg.batch_size)
                for key in ("exp_avg", "exp_avg_sq"):
                    moment = state[key]
                    assert moment.untyped_storage().nbytes() == param.numel() * param.element_size()
                    if update == 0:
                        first[(k, name, key)] = moment
                    else:
                        assert moment is first[(k, name, key)]
    pointers = [ppo.optimizer.state[p]["exp_avg"].data_ptr() for ppo in ppos for p in ppo.model.parameters()]
    assert len(set(pointers)) == len(pointers)


def run_in_chunks_or_whole(monkeypatch, chunked: bool) -> list[bytes]:
    """What a group computes (bytes): 5 LavaWorld FC agents with TrojDRL, clean teachers and
    anchors, two rollouts and updates; 3 Colorful Memory agents (recurrent, memory head), one; the
    lockstep evaluation of 5 LavaWorld agents (sampled); 5 OPAC² agents' act and two updates.
    ``chunked``: computed 2 agents at a time (what a CUDA group does CUDA_WIDTH at a time)."""
    from rlbackdoors.algos import group_opac2
    from rlbackdoors.train.driver import evaluate_runs

    if chunked:
        monkeypatch.setattr(group, "chunk_width", lambda device: 2)
    out: list[bytes] = []

    def state(ppo) -> bytes:
        buffer = io.BytesIO()
        torch.save({"model": ppo.model.state_dict(), "optimizer": ppo.optimizer.state_dict()}, buffer)
        return buffer.getvalue()

    poison = {"trigger": "additive:135", "attack": "trojdrl", "attack_params": {"budget": 0.2}}
    learners = with_anchors(with_teachers([learner("lavaworld", "fc", s, poison, ppo={"rollout": 16}) for s in range(5)], [0.5] * 5), [0.1] * 5)
    for batch, cycles in ((learners, 2), ([cm_learner(s) for s in range(3)], 1)):
        ppos, envs, obs = (list(x) for x in zip(*batch))
        for _ in range(cycles):
            results = group.collect(ppos, envs, obs)
            out.append(json.dumps(group.update(ppos, [r for r, _ in results])).encode())
            out.append(b"".join(r.actions.numpy().tobytes() + r.logprobs.numpy().tobytes() for r, _ in results))
            obs = [o for _, o in results]
        out += [state(ppo) for ppo in ppos]
    cfgs = [RunConfig.from_dict({"env": {"name": "lavaworld"}, "poison": {"poisoned": k % 2 == 1}, "train": {"seed": k}}) for k in range(5)]
    models = []
    for cfg in cfgs:
        torch.manual_seed(cfg.train.seed)
        models.append(build_model(cfg.model.arch, "lavaworld"))
    out.append(json.dumps([r.to_dict() for r in evaluate_runs(models, cfgs, [6] * 5, group.stacked_act)], sort_keys=True, default=str).encode())
    agents, replays = (list(x) for x in zip(*[opac2_learner(s) for s in range(5)]))
    out += [a.tobytes() for a in group_opac2.act(agents, [np.random.default_rng(s).normal(size=(4, 6)) for s in range(5)])]
    out.append(json.dumps(group_opac2.update(agents, replays, [np.random.default_rng(s) for s in range(5)], 2)).encode())
    out += [b"".join(p.detach().numpy().tobytes() for p in a.policy.parameters()) for a in agents]
    return out


def test_a_group_computed_in_chunks_computes_what_it_computes_whole(monkeypatch):
    """A CUDA group computes ``CUDA_WIDTH`` agents at a time (``algos.group.chunks``), so that an
    agent always computes at that width: its bytes then do not hang on how many runs share its
    group as it trains. The chunks' plumbing (forward, teachers, recurrent memory, update, lockstep
    evaluation, OPAC²'s act and update) is checked here on the CPU, 2 agents a chunk, where an
    agent's numbers do not depend on the width from 2 up: the same bytes as computed whole."""
    whole = run_in_chunks_or_whole(monkeypatch, False)
    chunked = run_in_chunks_or_whole(monkeypatch, True)
    assert len(whole) == len(chunked) and all(a == b for a, b in zip(whole, chunked))
    assert group.chunks(5, torch.device("cpu")) == [slice(0, 2), slice(2, 4), slice(4, 5)]  # (chunked above)


class KernelCount(TorchDispatchMode):
    """ATen operations that compute (not views: on a GPU, each a kernel launch or a host op), by name."""

    def __init__(self) -> None:
        super().__init__()
        self.ops: collections.Counter = collections.Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        if not func.is_view and func.overloadpacket not in (torch.ops.aten.lift_fresh, torch.ops.aten.detach):
            self.ops[str(func.overloadpacket)] += 1
        return func(*args, **(kwargs or {}))


# What an agent adds to a group's step by itself: draws from its own host generator (its rollout's
# uniforms, its minibatch orders, one per epoch), which keep its numbers those it draws alone
OWN_DRAWS = {"aten.rand", "aten.randperm"}


def group_cycle_ops(k: int, teachers: bool, device: torch.device | None = None, arch: str = "fc") -> collections.Counter:
    """Operations of a group's second rollout and update (the first fills its Adam state): K
    LavaWorld agents (``arch``), every other one poisoned through the seam (TrojDRL, forced actions);
    ``teachers``: every one poisoned, with a clean teacher and a weight anchor."""
    poison = {"trigger": "additive:135", "attack": "trojdrl", "attack_params": {"budget": 0.2}}
    learners = [learner("lavaworld", arch, s, poison if s % 2 or teachers else None, device=device, ppo={"rollout": 16}) for s in range(k)]
    if teachers:
        learners = with_anchors(with_teachers(learners, [0.5] * k), [0.1] * k)
    ppos, envs, obs = (list(x) for x in zip(*learners))
    for cycle in range(2):
        with KernelCount() as count:
            results = group.collect(ppos, envs, obs)
            group.update(ppos, [r for r, _ in results])
        obs = [o for _, o in results]
    return count.ops


@pytest.mark.parametrize("teachers", [False, True], ids=["plain", "teachers"])
def test_a_groups_device_work_does_not_grow_with_its_agents(teachers):
    """Issue 55, one step for the whole group: a group's rollout and update run the same operations
    for 2 agents as for 6, bar each agent's own draws (``OWN_DRAWS``: its rollout's uniforms, one
    minibatch order per epoch). No walk over the agents per step or per parameter: with an attack's
    seam (its executed and forced actions go to the device once a rollout), clean teachers and
    weight anchors, and the Adam state read and written back by a stack per name and one
    multi-tensor copy (before: 108 operations more per agent an update on LavaWorld FC, K x P
    copies, each a kernel on a GPU). The feed-forward FC model; a CNN's convolutions are still one
    per agent (models.minigrid._conv_stacked)."""
    two, six = group_cycle_ops(2, teachers), group_cycle_ops(6, teachers)
    grown = {op: six[op] - two[op] for op in six.keys() | two.keys() if six[op] != two[op]}
    epochs = RunConfig.from_dict({"env": {"name": "lavaworld"}}).ppo.epochs
    assert grown == {"aten.rand": 4, "aten.randperm": 4 * epochs}, grown
    assert sum(six.values()) > 1000  # (the count saw the group's work)


# Colorful Memory's CNN-GRU: its three convolutions are still one per agent (models.minigrid._conv_stacked,
# same bytes whatever the group), so 6 agents run 4 x 3 more than 2
CONV_PER_AGENT = {"colorful-memory": {"aten.conv2d": 4 * 3}}


@pytest.mark.parametrize("env,conv", [(env, "each") for env in sorted(EVAL_CASES)] + [("colorful-memory", "gemm"), ("colorful-memory", "grouped")])
def test_a_lockstep_evaluation_step_does_not_grow_with_its_agents(env, conv, monkeypatch):
    """A group's evaluation step (``stacked_act``) runs the same operations for 2 agents as for 6:
    their weights stacked once and picked by an index, their uniforms drawn a block of
    ``DRAW_BLOCK`` steps at a time from each agent's own generator (before: one draw per agent and
    step). Sampled play, the live set kept whole (regroup 0), 3 episodes per agent; every step but
    the first (which picks the weights) and those that refill the block counted, each the same.
    LavaWorld FC and Colorful Memory's recurrent CNN-GRU, whose convolutions are one per agent on a
    device by default and one call for all agents with STACKED_CONV's "gemm" or "grouped"."""
    convolutions(monkeypatch, conv)
    from rlbackdoors.agent import Agent
    from rlbackdoors.evaluate.episodes import _vector_envs, play_lockstep

    def step_ops(k: int) -> set[tuple]:
        cfgs = [RunConfig.from_dict({"env": {"name": env}, "poison": {"poisoned": s % 2 == 1}, "train": {"seed": s}}) for s in range(k)]
        agents = [Agent(c.world, c, build_model(c.model.arch, env)) for c in cfgs]
        act = group.stacked_act(agents)
        seen: list[collections.Counter] = []

        def counted(*args):
            with KernelCount() as count:
                out = act(*args)
            seen.append(count.ops)
            return out

        envs = [_vector_envs(c.env, c.poison.trigger if c.poison.poisoned else None, 3, None) for c in cfgs]
        play_lockstep(agents, envs, list(range(k)), "sample", act=counted, regroup=0.0)
        steady = [ops for t, ops in enumerate(seen) if t > 0 and t % group.DRAW_BLOCK]
        assert len(steady) > 5 and all(ops == steady[0] for ops in steady)
        return steady[0]

    two, six = step_ops(2), step_ops(6)
    grown = {op: six[op] - two[op] for op in six.keys() | two.keys() if six[op] != two[op]}
    assert grown == (CONV_PER_AGENT.get(env, {}) if conv == "each" else {}), grown


def with_teachers(learners: list, coefs: list[float]) -> list:
    """Each learner given a clean teacher (a fresh network of its architecture, seeded apart) and its own coefficient."""
    for k, ((ppo, _, _), coef) in enumerate(zip(learners, coefs)):
        torch.manual_seed(100 + k)
        teacher = copy.deepcopy(ppo.model)
        for p in teacher.parameters():
            torch.nn.init.normal_(p, std=0.1)
        ppo.set_teacher(teacher, coef)
    return learners


def with_anchors(learners: list, coefs: list[float]) -> list:
    """Each learner pulled toward its own anchor (its own weights, shifted by seeded noise) by its own coefficient."""
    for k, ((ppo, _, _), coef) in enumerate(zip(learners, coefs)):
        noise = torch.Generator().manual_seed(200 + k)
        ppo.set_anchor({n: p.detach() + 0.05 * torch.randn(p.shape, generator=noise).to(p.device) for n, p in ppo.model.named_parameters()}, coef)
    return learners


# Relative tolerance of the teachers test per update, from experiments/kernel_spread/kernel_spread.json (largest
# relative difference over grad_norm, teacher_kl and anchor_distance, the group against lone learners
# and lone learners against themselves under avx512, avx2 and no-SIMD kernels). Update 1 is rounding
# of fp32 sums (measured <= 1e-5 everywhere): 1e-4. Update 2 of LavaWorld is not: a random teacher
# at coefficient 1 gives gradients of norm ~1e3 that are clipped to 0.4 and Adam-normalised, so a
# 1e-7 difference after update 1 becomes 1.5e-2 (group vs lone, no SIMD) and 3.1e-3 (the lone learner
# alone, only its kernels changed; 2.0e-3 on an AVX-512/AMX Xeon): 5e-2, three times the largest.
# Colorful Memory's learning rate (1e-5) keeps its update 2 at rounding (<= 7e-6): 1e-4.
TEACHER_REL = {"lavaworld": (1e-4, 5e-2), "colorful-memory": (1e-4, 1e-4)}


@pytest.mark.parametrize("world", ["lavaworld", "colorful-memory"])
def test_group_with_clean_teachers_matches_each_agent_alone(world):
    """Three agents regularised towards their own clean teachers (coefficients 0.1, 1 and 0.5;
    only untriggered frames count) and pulled to their own weight anchors (0.05, 0.2, 0.1): the
    group's rollouts carry the same teacher log-probabilities and untriggered masks, and after two
    updates the same KL, gradient norms, anchor distances and weights as three lone learners, to
    float rounding as measured (``TEACHER_REL``; LavaWorld FC; Colorful Memory's CNN-GRU with its
    teacher's memory)."""
    coefs, pulls = [0.1, 1.0, 0.5], [0.05, 0.2, 0.1]
    if world == "lavaworld":
        poisons = [{"trigger": t, "attack": "trojdrl", "attack_params": {"budget": 0.2}} for t in ("additive:135", "multiplicative:12", "additive:60")]

        def make(k):
            return learner("lavaworld", "fc", k, poisons[k])
    else:

        def make(k):
            return cm_learner(k, {"attack": "action_target"})

    alone = with_anchors(with_teachers([make(k) for k in range(3)], coefs), pulls)
    grouped = with_anchors(with_teachers([make(k) for k in range(3)], coefs), pulls)
    triggered_seen = 0
    for update in range(2):
        lone, results, stats = step_both(alone, grouped)
        for k in range(3):
            ours = results[k][0]
            assert torch.equal(lone[k][0].actions, ours.actions) and torch.equal(lone[k][0].untriggered, ours.untriggered)
            torch.testing.assert_close(lone[k][0].teacher_logp, ours.teacher_logp, rtol=1e-4, atol=1e-5)
            for key in ("teacher_kl", "grad_norm", "anchor_distance"):
                assert stats[k][key] == pytest.approx(lone[k][1][key], rel=TEACHER_REL[world][update]), (update, k, key)
            # both start at 0.0 in PPO.update's stats and stay exactly 0 only if the term is not computed
            assert stats[k]["teacher_kl"] > 0 and stats[k]["anchor_distance"] > 0
            triggered_seen += int((~ours.untriggered).sum())
    assert triggered_seen > 0  # some frames carried the trigger and were left out of the KL
    for (lone_ppo, _, _), (ppo, _, _) in zip(alone, grouped):
        for a, b in zip(lone_ppo.model.parameters(), ppo.model.parameters()):
            # within two Adam steps (2 lr): an Adam step moves a weight by about lr at most, and one
            # whose gradient is near 0 may step the other way on rounding; measured 0.41 lr at most
            # over three kernel sets (kernel_spread.json) with per-parameter clipping norms, 1.14 lr
            # once the group clips by one norm over each agent's whole row (another summation order)
            torch.testing.assert_close(a, b, rtol=1e-3, atol=2 * ppo.cfg.lr)
        if lone_ppo.teacher_memory is not None:
            torch.testing.assert_close(lone_ppo.teacher_memory, ppo.teacher_memory, rtol=1e-4, atol=1e-5)


def test_group_refuses_what_it_cannot_batch():
    a, b = learner("lavaworld", "fc", 0), learner("lavaworld", "cnn", 1)
    with pytest.raises(ValueError, match="one architecture"):
        group.collect([a[0], b[0]], [a[1], b[1]], [a[2], b[2]])
    c = with_teachers([learner("lavaworld", "fc", 2, {"attack": "trojdrl"})], [0.5])[0]
    with pytest.raises(ValueError, match="a clean teacher for every agent or for none"):
        group.collect([a[0], c[0]], [a[1], c[1]], [a[2], c[2]])
    d = with_anchors([learner("lavaworld", "fc", 3)], [0.1])[0]
    with pytest.raises(ValueError, match="a weight anchor for every agent or for none"):
        group.collect([a[0], d[0]], [a[1], d[1]], [a[2], d[2]])


@pytest.mark.slow  # (over 20 s on 2 cores: out of the default run, `make test-slow`)
def test_group_of_one_is_todays_bytes_and_groups_finish_every_folder(tmp_path):
    """group_size=1 gives the lone run's model.pt bytes; group_size=2 over three runs (one slot
    refilled) leaves three complete folders with ``trainer: group`` whose bytes do not depend on
    which runs shared the group; an OPAC² (Safety Car Goal) run beside them is batched with its
    own kind only (it is alone of its kind here: its bytes are those of any group, not the lone run's)."""
    lone = train(tiny(4), tmp_path / "lone", progress=False)
    result = train_group([("one", tiny(4), tmp_path / "one")], 1)
    assert (tmp_path / "lone" / "model.pt").read_bytes() == (tmp_path / "one" / "model.pt").read_bytes()
    assert result.metrics["one"]["frames"] == lone["frames"] and "trainer" not in result.metrics["one"]

    safety = RunConfig.from_dict(
        {
            "env": {"name": "safety-car-goal", "max_steps": 40},
            "poison": {"trigger": "formation:0.5:1.0:2.5", "num_clean_envs": 2, "num_poisoned_envs": 1},
            "opac2": {"depth": 2, "width": 16, "batch_size": 32, "learning_starts": 120, "updates_per_step": 0.25},
            "train": {"max_frames": 480, "eval_interval": 240, "eval_episodes": 3, "final_eval_episodes": 4, "checkpoint_minutes": 0, "video": False},
        }
    )
    runs = [(s, tiny(s), tmp_path / f"g{s}") for s in (4, 5, 6)] + [("cm", safety, tmp_path / "cm")]
    cpu = time.process_time()
    result = train_group(runs, 2)
    cpu = time.process_time() - cpu
    assert not result.errors and set(result.metrics) == {4, 5, 6, "cm"}
    # Each run's CPU is its share, not the process's total: the shares (setup and finish included)
    # and the group's own bookkeeping (overhead_s) add up to the process's CPU (0.01 s: this test's
    # clock calls around the call), and each run's training part (cpu_time_s) is within its share.
    # No ratio of the two: how much of a call is bookkeeping depends on the CPU and its load.
    assert set(result.cpu_s) == set(result.metrics)
    assert result.overhead_s >= 0.0 and sum(result.cpu_s.values()) + result.overhead_s == pytest.approx(cpu, abs=0.01)
    for key, m in result.metrics.items():
        assert 0 < m["cpu_time_s"] <= result.cpu_s[key] + 0.01
    for key, _, folder in runs:
        assert (folder / "metrics.json").is_file() and (folder / "model.pt").is_file() and not (folder / "checkpoint.pt").exists()
        assert result.metrics[key]["trainer"] == "group"
    # the OPAC² run again, in a group of two OPAC² runs: the same bytes as beside the PPO runs
    other = RunConfig.from_dict({**safety.to_dict(), "train": {**safety.to_dict()["train"], "seed": 9}})
    train_group([("cm", safety, tmp_path / "cm2"), ("other", other, tmp_path / "other")], 2)
    assert (tmp_path / "cm" / "model.pt").read_bytes() == (tmp_path / "cm2" / "model.pt").read_bytes()
    train(safety, tmp_path / "cm-lone", progress=False)
    assert (tmp_path / "cm" / "model.pt").read_bytes() != (tmp_path / "cm-lone" / "model.pt").read_bytes()
    # seed 4 again beside other mates, in a group of 3: the same bytes as in the first group
    train_group([(s, tiny(s), tmp_path / f"h{s}") for s in (7, 4, 8)], 3)
    assert (tmp_path / "g4" / "model.pt").read_bytes() == (tmp_path / "h4" / "model.pt").read_bytes()
    # and the same evaluations (played in lockstep with other mates), its log's and its final one
    numbers = ("clean_sr", "poisoned_sr", "clean_reward", "poisoned_reward", "clean_mean_steps")

    def evaluations(name: str) -> list:
        with open(tmp_path / name / "log.csv", newline="") as f:
            rows = [[row[k] for k in numbers] for row in csv.DictReader(f)]
        final = json.loads((tmp_path / name / "metrics.json").read_text())
        return rows + [[final[k] for k in numbers]]

    assert len(evaluations("g4")) == 3 and evaluations("g4") == evaluations("h4")
    # and not the lone bytes (batched kernels round differently): the trainer is part of the recipe
    assert (tmp_path / "g4" / "model.pt").read_bytes() != (tmp_path / "lone" / "model.pt").read_bytes()


def test_a_group_trained_on_the_device_engine_ends_as_with_numba(tmp_path, monkeypatch):
    """Whole trainings (three LavaWorld FC runs in a group of 3: rollouts, updates, lockstep
    evaluations, final evaluation) with the rollouts' slots on the device engine (allowed on the
    CPU for the test: ``RLBACKDOORS_DEVICE_ENGINE=cpu``) end with numba's model.pt, log and metrics."""
    runs = lambda tag: [(s, tiny(s), tmp_path / f"{tag}{s}") for s in (4, 5, 6)]  # noqa: E731
    train_group(runs("numba"), 3)
    monkeypatch.setenv(group.DEVICE_ENGINE_ENV, "cpu")
    used = []
    real = group.device_engine_for
    monkeypatch.setattr(group, "device_engine_for", lambda *a, **k: used.append(1) or real(*a, **k))
    train_group(runs("device"), 3)
    assert len(used) == 3200 // (32 * 10)  # every rollout (32 steps of 10 copies an agent) on the device engine
    clocks = ("wall_time_s", "fps", "cpu_time_s", "frames_per_s")
    for s in (4, 5, 6):
        assert (tmp_path / f"device{s}" / "model.pt").read_bytes() == (tmp_path / f"numba{s}" / "model.pt").read_bytes()
        logs, metrics = [], []
        for tag in ("numba", "device"):
            with open(tmp_path / f"{tag}{s}" / "log.csv", newline="") as f:
                logs.append([{k: v for k, v in row.items() if k not in clocks} for row in csv.DictReader(f)])
            metrics.append({k: v for k, v in json.loads((tmp_path / f"{tag}{s}" / "metrics.json").read_text()).items() if k not in clocks})
        assert len(logs[0]) == 2 and logs[0] == logs[1] and metrics[0] == metrics[1]


def test_a_failing_run_leaves_the_group_going(tmp_path):
    bad = tiny(2)
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "checkpoint.pt").write_bytes(b"not a checkpoint")
    (tmp_path / "bad" / "config.json").write_text(bad.to_json())
    result = train_group([("bad", bad, tmp_path / "bad"), ("good", tiny(3), tmp_path / "good")], 2)
    assert set(result.errors) == {"bad"} and set(result.metrics) == {"good"}


def zoo_spec() -> dict:
    return {
        "name": "group",
        "seed": 5,
        "examples": {"episodes": 1},
        "overrides": {
            "ppo": {"rollout": 32},
            "train": {"max_frames": 9600, "eval_interval": 1600, "eval_episodes": 4, "final_eval_episodes": 4, "video": False},
        },
        "cells": [
            {
                "world": "lavaworld",
                "archs": ["fc"],
                "triggers": ["multiplicative"],
                "clean": 2,
                "poisoned": 2,
                "max_attempts": 2,  # nothing converges (thresholds 1.0): no top-up, every run 6 evaluations long
                "overrides": {"train": {"clean_threshold": 1.0, "poisoned_threshold": 1.0, "checkpoint_minutes": 0}},
            }
        ],
    }


@pytest.mark.slow  # covered by parts in the default run: zoo kill -9 (test_zoo), a pooled group resumed after SIGTERM (test_env_pool), group folders (test_group_of_one_...)
def test_zoo_run_with_a_group_size_finishes_and_resumes_after_a_kill(tmp_path):
    """``zoo run --group-size 3`` on one worker: SIGTERM once a checkpoint is on disk stops the
    group job with every run's checkpoint; a second run finishes every model as ordinary,
    verified dataset entries, with the same bytes as an uninterrupted run in one group of four
    (``--group-size auto``): an agent's bytes depend on its config, not on its group."""
    whole, cut = tmp_path / "whole", tmp_path / "cut"
    for path in (whole, cut):
        plan(parse_spec(zoo_spec()), path)
    log = io.StringIO()
    summary = zoo_run(whole, workers=1, group_size="auto", progress_interval=5.0, out=log)  # 8 on a CPU: all four in one group
    assert "--group-size auto: by each model's algorithm and train.device (PPO 8 on cpu, 64 on cuda; OPAC² 1 on cpu, 64 on cuda" in log.getvalue()
    logs = [(f / "train.log").read_text() for f in sorted((whole / "models").iterdir())]
    assert all("=== zoo group job:" in text for text in logs) and sum("(output in id-" in text for text in logs) == 3
    assert summary["done"] == 4 and summary["failed"] == 0 and summary["converged"] == 0
    cmd = [sys.executable, "-m", "rlbackdoors.zoo.cli", "run", str(cut), "--workers", "1", "--group-size", "3"]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 240
    while time.time() < deadline and proc.poll() is None and not list((cut / "models").glob("*/checkpoint.pt")):
        time.sleep(0.05)
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(timeout=240) != 0
    assert list((cut / "models").glob("*/checkpoint.pt")), "the group job stopped without checkpoints"
    assert not list((cut / "models").glob("*/metrics.json"))
    log = io.StringIO()
    summary = zoo_run(cut, workers=1, group_size=3, progress_interval=5.0, out=log)
    assert summary["done"] == 4 and summary["failed"] == 0 and summary["trained"] == 4
    named = [line.split()[0] for line in log.getvalue().splitlines() if " attempt " in line]
    assert sorted(named) == sorted(f.name for f in (cut / "models").iterdir()), log.getvalue()  # each finished model said once
    # Three slots for four models: each entry is written as its run ends, not when the whole job
    # does, so the first entries exist before the last model's training has finished.
    marks = [(f / "reduced-config.json").stat().st_mtime_ns for f in (cut / "models").iterdir()]
    trained = [(f / "metrics.json").stat().st_mtime_ns for f in (cut / "models").iterdir()]
    assert min(marks) < max(trained)
    rows = read_metadata(cut / "METADATA.csv")
    assert len(rows) == 4
    for folder in sorted((whole / "models").iterdir()):
        metrics = json.loads((folder / "metrics.json").read_text())
        assert metrics["trainer"] == "group" and (folder / "reduced-config.json").is_file()
        assert (folder / "model.pt").read_bytes() == (cut / "models" / folder.name / "model.pt").read_bytes()
    verify = subprocess.run([sys.executable, "-m", "rlbackdoors.zoo.cli", "verify", str(cut)], capture_output=True, text=True, timeout=300)
    assert verify.returncode == 0, verify.stdout + verify.stderr
    # Killed after a run had trained but before its entry was written: the next run writes the
    # entry without training it again.
    folder = sorted((whole / "models").iterdir())[1]
    (folder / "reduced-config.json").unlink()
    before = (folder / "model.pt").stat().st_mtime_ns
    summary = zoo_run(whole, workers=1, group_size=3, progress_interval=5.0)
    assert summary["done"] == 4 and summary["trained"] == 0 and (folder / "reduced-config.json").is_file()
    assert (folder / "model.pt").stat().st_mtime_ns == before


@pytest.mark.slow  # (over 20 s on 2 cores: out of the default run, `make test-slow`)
def test_zoo_run_device_trains_the_planned_models_elsewhere_and_records_it(tmp_path):
    """``zoo run --device cpu --group-size auto`` on a zoo planned for CUDA (``train.device =
    "cuda"``): every model trains on the CPU, in the CPU's auto groups, to the same bytes as the
    same zoo planned for the CPU; config.json stays the plan's, metrics.json records the device,
    and the zoo verifies. ``--device cuda`` where there is no CUDA is refused with one line, and
    the Ray back-end refuses ``--device`` (its tasks' resources are Ray's)."""
    from rlbackdoors.zoo.run import make_executor

    planned = {}
    for device in ("cuda", "cpu"):
        spec = zoo_spec()
        spec["overrides"]["train"]["device"] = device
        planned[device] = tmp_path / device
        plan(parse_spec(spec), planned[device])
    if not torch.cuda.is_available():
        refused = subprocess.run(
            [sys.executable, "-m", "rlbackdoors.zoo.cli", "run", str(planned["cuda"]), "--device", "cuda"], capture_output=True, text=True, timeout=300
        )
        assert refused.returncode == 2 and refused.stderr.strip().splitlines() == [
            "rlbackdoors: error: --device cuda: no CUDA device is available here (use cpu or auto)"
        ]
        assert not list((planned["cuda"] / "models").glob("*/metrics.json"))
    with pytest.raises(ConfigError, match="--device applies to --backend local only"):
        make_executor("ray", None, None, 0, device="cpu")
    log = io.StringIO()
    summary = zoo_run(planned["cuda"], workers=1, group_size="auto", progress_interval=5.0, out=log, device="cpu")
    assert "--group-size auto: by each model's algorithm and --device cpu (PPO 8 on cpu" in log.getvalue()
    assert summary["done"] == 4 and summary["failed"] == 0
    zoo_run(planned["cpu"], workers=1, group_size=8, progress_interval=5.0, out=io.StringIO())
    for folder in sorted((planned["cuda"] / "models").iterdir()):
        metrics = json.loads((folder / "metrics.json").read_text())
        assert metrics["device"] == "cpu" and "gpu" not in metrics and metrics["trainer"] == "group"
        assert json.loads((folder / "config.json").read_text())["train"]["device"] == "cuda"  # the plan's
        assert (folder / "model.pt").read_bytes() == (planned["cpu"] / "models" / folder.name / "model.pt").read_bytes()
    verify = subprocess.run([sys.executable, "-m", "rlbackdoors.zoo.cli", "verify", str(planned["cuda"])], capture_output=True, text=True, timeout=300)
    assert verify.returncode == 0, verify.stdout + verify.stderr


def test_auto_group_size_goes_by_the_models_device_not_the_machines():
    """A CPU model on a GPU machine trains in CPU groups of 8: measured on an H200 machine, a GPU
    group of 64 ran at x0.35 of them (docs/results/zoos.md). ``auto`` is CUDA where there is one."""
    from rlbackdoors.train.group import auto_group_size

    assert (auto_group_size("ppo", "cpu"), auto_group_size("opac2", "cpu")) == (8, 1)
    assert (auto_group_size("ppo", "cuda"), auto_group_size("opac2", "cuda")) == (64, 64)
    assert auto_group_size("ppo", "auto") == (64 if torch.cuda.is_available() else 8)
    from rlbackdoors import worlds

    rlw, lava, cm = worlds.get("randomized-lavaworld"), worlds.get("lavaworld"), worlds.get("colorful-memory")
    # on the compiled trainer on a CPU a world's own measured K (Randomized LavaWorld, Colorful Memory: one agent a program)
    assert (auto_group_size("ppo", "cpu", rlw, "compiled"), auto_group_size("ppo", "cpu", lava, "compiled")) == (1, 8)
    assert (auto_group_size("ppo", "cpu", cm, "compiled"), auto_group_size("ppo", "cpu", cm, "torch")) == (1, 8)
    assert (auto_group_size("ppo", "cpu", rlw, "torch"), auto_group_size("ppo", "cuda", rlw, "compiled")) == (8, 64)


def test_group_size_auto_trains_ppo_worlds_in_groups_and_opac2_worlds_alone_on_a_cpu(tmp_path):
    """``--group-size auto`` applies the measured rule per world's algorithm: the PPO world's
    models train in a group (``trainer: group``), the OPAC² world's alone (today's lone bytes,
    with ``--env-workers 2`` its env copies in worker processes), in one zoo run."""
    safety_train = {"max_frames": 480, "eval_interval": 240, "eval_episodes": 3, "final_eval_episodes": 4, "checkpoint_minutes": 0, "video": False}
    spec = zoo_spec()
    spec["cells"][0]["overrides"]["ppo"] = spec["overrides"].pop("ppo")  # a PPO setting: the PPO world's cell only
    spec["cells"][0].update(clean=1, poisoned=1, max_attempts=1)
    spec["overrides"]["train"]["max_frames"] = 3200
    spec["cells"].append(
        {
            "world": "safety-car-goal",
            "triggers": ["formation:0.5:1.0:2.5"],
            "clean": 0,
            "poisoned": 1,
            "max_attempts": 1,
            "overrides": {
                "env": {"max_steps": 40},
                "poison": {"num_clean_envs": 2, "num_poisoned_envs": 1},
                "opac2": {"depth": 2, "width": 16, "batch_size": 32, "learning_starts": 120, "updates_per_step": 0.25},
                "train": {**safety_train, "clean_threshold": 1.0, "poisoned_threshold": 1.0},
            },
        }
    )
    plan(parse_spec(spec), tmp_path / "z")
    log = io.StringIO()
    summary = zoo_run(tmp_path / "z", workers=2, group_size="auto", progress_interval=5.0, out=log, env_workers=2)
    assert (
        "--group-size auto: by each model's algorithm and train.device (PPO 8 on cpu, 64 on cuda; OPAC² 1 on cpu, 64 on cuda" in log.getvalue()
        and summary["done"] == 3
        and summary["failed"] == 0
    )
    trainers = {}
    for folder in sorted((tmp_path / "z" / "models").iterdir()):
        cfg = RunConfig.load(folder / "config.json")
        trainers.setdefault(cfg.env.name, set()).add(json.loads((folder / "metrics.json").read_text()).get("trainer"))
        if cfg.env.name == "safety-car-goal":  # alone, its env copies in 2 workers: the bytes of a lone run of its config
            assert "env copies of single-env worlds in 2 worker processes" in (folder / "train.log").read_text()
            train(cfg, tmp_path / f"lone-{folder.name}", progress=False)
            assert (folder / "model.pt").read_bytes() == (tmp_path / f"lone-{folder.name}" / "model.pt").read_bytes()
    assert trainers == {"lavaworld": {"group"}, "safety-car-goal": {None}}


def test_group_size_is_validated(tmp_path):
    plan(parse_spec(zoo_spec()), tmp_path / "z")
    with pytest.raises(ConfigError, match="--group-size must be >= 1"):
        zoo_run(tmp_path / "z", group_size=0)
    with pytest.raises(ConfigError, match="--group-size applies to --backend local only"):
        zoo_run(tmp_path / "z", group_size=2, backend="ray")
    with pytest.raises(ConfigError, match="--env-workers applies to --backend local only"):
        zoo_run(tmp_path / "z", env_workers=2, backend="ray")
    with pytest.raises(ConfigError, match="--env-workers must be an integer >= 0, got -1"):
        zoo_run(tmp_path / "z", env_workers=-1)
    out = cli("run", tmp_path / "z", "--group-size", "0", module="rlbackdoors.zoo.cli")
    assert out.returncode == 2 and "--group-size: must be auto or an integer >= 1, got '0'" in out.stderr
    for flags, message in (
        (["--models", "0"], "--models: must be >= 1, got 0"),
        (["--group-size", "4", "x"], "--group-size: must be an integer >= 1, got 'x'"),
        (
            ["--side", "1:gpu"],
            "--side '1:gpu': expected K[:DEVICE[:WORKERS[:ENV_WORKERS[:BACKEND[:ENGINE[:CONV]]]]]], K a positive integer or auto, WORKERS a positive integer (empty: the run's), "
            "ENV_WORKERS >= 0, DEVICE one of cpu, cuda, auto, BACKEND one of torch, jax, compiled, compiled-eval, ENGINE one of numba, device (device: with DEVICE cpu or cuda), "
            "CONV one of each, gemm, grouped (with DEVICE cpu or cuda)",
        ),
        (["--side", "8:cpu:0"], "--side '8:cpu:0': expected K[:DEVICE[:WORKERS[:ENV_WORKERS[:BACKEND[:ENGINE[:CONV]]]]]]"),
        (["--side", "8:cpu:2:-1"], "--side '8:cpu:2:-1': expected K[:DEVICE[:WORKERS[:ENV_WORKERS[:BACKEND[:ENGINE[:CONV]]]]]]"),
        (["--side", "8:cpu::0:xla"], "--side '8:cpu::0:xla': expected K[:DEVICE[:WORKERS[:ENV_WORKERS[:BACKEND[:ENGINE[:CONV]]]]]]"),
        (["--side", "8:cuda:1:::gpu"], "--side '8:cuda:1:::gpu': expected K[:DEVICE[:WORKERS[:ENV_WORKERS[:BACKEND[:ENGINE[:CONV]]]]]]"),
        (["--side", "8:cuda:1::::fft"], "--side '8:cuda:1::::fft': expected K[:DEVICE[:WORKERS[:ENV_WORKERS[:BACKEND[:ENGINE[:CONV]]]]]]"),
        (["--side", "1", "--group-size", "2"], "bench zoo: --side names each side's group size and device; leave out --group-size and --device"),
    ):
        out = cli("bench", "zoo", *flags)
        assert out.returncode == 2 and out.stderr.count("\n") == 1 and message in out.stderr, out.stderr


@pytest.mark.slow  # (14 s on 2 cores: three sides of real zoos; bench zoo's other tests train their sides in the default run)
def test_bench_zoo_measures_both_sides_on_the_same_configs(tmp_path):
    from rlbackdoors.bench.zoo import bench_zoo

    saved = []
    result = bench_zoo(
        "lavaworld",
        models=2,
        frames=3200,
        sides=[(1, "cpu", 1, 0, "torch", ""), ("auto", "cpu", None, 0, "torch", ""), (2, "cpu", None, 0, "jax", "")],
        workers=1,
        keep=str(tmp_path),
        on_side=lambda r: saved.append(len(r["sides"])),
        eval_episodes=4,  # the mechanics, not the figures: the world's 100 episodes would take most of the time
    )
    alone, grouped, jax_side = result["sides"]
    assert saved == [1, 2, 3]  # written after each side: a run cut short keeps what it measured
    assert [(s["group_size"], s["device"], s["workers"], s["update_backend"]) for s in result["sides"]] == [
        (1, "cpu", 1, "torch"),
        (8, "cpu", 1, "torch"),  # auto: PPO on a CPU, the measured K (two models: one group of two, computed as 8 would be)
        (2, "cpu", 1, "jax"),
    ] and result["device"] == ["cpu"]
    assert grouped["group_size_from"] == "auto" and "group_size_from" not in alone
    assert jax_side["models"] == 2 and jax_side["failed"] == 0
    for p in (tmp_path / "side2-k2-cpu-w1-jax" / "models").glob("*/config.json"):
        assert json.loads(p.read_text())["ppo"]["update_backend"] == "jax"
    assert alone["models"] == grouped["models"] == 2
    # frames: what the models trained (at least max_frames each: whole rollouts)
    per_model = [json.loads(p.read_text())["frames"] for p in (tmp_path / "side0-k1-cpu-w1" / "models").glob("*/metrics.json")]
    assert len(per_model) == 2 and all(f >= 3200 for f in per_model) and alone["frames"] == sum(per_model)
    assert alone["frames_per_s"] == pytest.approx(alone["frames"] / alone["wall_s"], rel=1e-2)
    # and the env steps its evaluations took: a model's log.csv rows (eval_episodes = 4 a condition at
    # the mean lengths logged) and its final evaluation (metrics.json), summed over the models
    expected = 0.0
    for folder in (tmp_path / "side0-k1-cpu-w1" / "models").glob("*"):
        rows = list(csv.DictReader((folder / "log.csv").open()))
        final = json.loads((folder / "metrics.json").read_text())
        assert len(rows) >= 1 and final["episodes"] == 4
        for row, n in [(r, 4) for r in rows] + [(final, final["episodes"])]:
            expected += n * (float(row["clean_mean_steps"]) + float(row["poisoned_mean_steps"]))
    assert alone["eval_steps"] == round(expected) and alone["eval_steps"] >= 2 * 2 * 4 * 2  # two models, two conditions, at least two evaluations of 4 episodes
    assert alone["env_steps_per_s"] == pytest.approx((alone["frames"] + alone["eval_steps"]) / alone["wall_s"], rel=1e-2)
    assert alone["eval_share"] == pytest.approx(alone["eval_steps"] / (alone["frames"] + alone["eval_steps"]), abs=1e-3)
    assert alone["ratio"] == 1.0 and grouped["ratio"] == pytest.approx(grouped["models_per_hour"] / alone["models_per_hour"], rel=1e-2)
    assert result["machine"]["cores"] >= 1 and len(alone["loadavg_before"]) == 3
    configs = [sorted(p.read_text() for p in (tmp_path / side / "models").glob("*/config.json")) for side in ("side0-k1-cpu-w1", "side1-kauto-cpu-w1")]
    assert configs[0] == configs[1]  # the same planned models on both sides
    assert all(json.loads(p.read_text())["trainer"] == "group" for p in (tmp_path / "side1-kauto-cpu-w1" / "models").glob("*/metrics.json"))


@pytest.mark.slow  # the env pool itself is in the default run (test_env_pool); this is the bench side that uses it
def test_bench_zoo_side_with_env_workers_trains_in_an_env_pool(tmp_path):
    """``--side 1:cpu:1:2``: the Safety Car Goal model's job steps its env copies in 2 workers."""
    from rlbackdoors.bench.zoo import bench_zoo

    result = bench_zoo("safety-car-goal", models=1, frames=400, sides=[(1, "cpu", 1, 2, "torch", "")], keep=str(tmp_path), eval_episodes=2)
    (side,) = result["sides"]
    assert side["env_workers"] == 2 and side["models"] == 1 and side["failed"] == 0
    (log,) = (tmp_path / "side0-k1-cpu-w1-e2" / "models").glob("*/train.log")
    assert "env copies of single-env worlds in 2 worker processes" in log.read_text()


def test_bench_zoo_sides_default_to_one_process_per_model_then_each_group_size():
    from rlbackdoors.bench.zoo import parse_side, side_plan

    assert side_plan((4, 8), 2, "cuda", None) == [(1, "cuda", 2, 0, "torch", "", ""), (4, "cuda", 2, 0, "torch", "", ""), (8, "cuda", 2, 0, "torch", "", "")]
    sides = [parse_side("1:cpu:16"), parse_side("64:cuda"), parse_side("8"), parse_side("64:cuda:1:15"), parse_side("8:cpu::0:jax"), parse_side("auto:cpu:16")]
    sides += [parse_side("256:cuda:1:::numba"), parse_side("256:cuda:1:0:jax:device"), parse_side("64:cuda:1::::grouped"), parse_side("8:cpu:::::gemm")]
    assert side_plan((8,), 2, "cpu", sides) == [
        (1, "cpu", 16, 0, "torch", "", ""),
        (64, "cuda", 2, 0, "torch", "", ""),
        (8, "cpu", 2, 0, "torch", "", ""),
        (64, "cuda", 1, 15, "torch", "", ""),
        (8, "cpu", 2, 0, "jax", "", ""),
        ("auto", "cpu", 16, 0, "torch", "", ""),
        (256, "cuda", 1, 0, "torch", "numba", ""),
        (256, "cuda", 1, 0, "jax", "device", ""),
        (64, "cuda", 1, 0, "torch", "", "grouped"),
        (8, "cpu", 2, 0, "torch", "", "gemm"),
    ]
    for bad in (
        "0",
        "auto:cpu:0",
        "Auto",
        "8:tpu",
        "8:cpu:0",
        "8:cpu:2:-1",
        "8:cpu:2:1:xla",
        "8:cpu:2:1:jax:1",
        "8:auto:1:0:torch:device",
        "8:cpu:1:0:torch:numba:x",
        "8:auto:1:0:torch::grouped",
        "8:cpu:1:0:torch:numba:each:x",
        "x",
    ):
        with pytest.raises(ValueError, match="expected K\\[:DEVICE\\[:WORKERS\\[:ENV_WORKERS\\[:BACKEND\\[:ENGINE\\[:CONV\\]\\]\\]\\]\\]\\]"):
            parse_side(bad)


def test_bench_zoo_engine_sides_train_the_same_bytes_with_either_engine(tmp_path, monkeypatch):
    """``--side K:cpu:1:::numba`` against ``...:device`` (the device engine, here on the CPU): the
    sides' jobs step their slots as told (``RLBACKDOORS_DEVICE_ENGINE``, restored after each side)
    and train the same model.pt bytes."""
    import rlbackdoors.zoo.run as zoo_run_module
    from rlbackdoors.algos.group import DEVICE_ENGINE_ENV
    from rlbackdoors.bench.zoo import bench_zoo

    monkeypatch.setenv(DEVICE_ENGINE_ENV, "cuda")
    seen, real = [], zoo_run_module.run
    monkeypatch.setattr(zoo_run_module, "run", lambda *a, **k: seen.append(os.environ[DEVICE_ENGINE_ENV]) or real(*a, **k))  # what the jobs inherit
    result = bench_zoo(
        "lavaworld", models=2, frames=3200, sides=[(2, "cpu", 1, 0, "torch", "numba"), (2, "cpu", 1, 0, "torch", "device")], keep=str(tmp_path), eval_episodes=4
    )
    assert [s["engine"] for s in result["sides"]] == ["numba", "device"] and all(s["models"] == 2 for s in result["sides"])
    assert seen == ["", "cpu"] and os.environ[DEVICE_ENGINE_ENV] == "cuda"
    models = [
        sorted((p.parent.name, p.read_bytes()) for p in (tmp_path / f"side{i}-k2-cpu-w1-{e}" / "models").glob("*/model.pt"))
        for i, e in enumerate(("numba", "device"))
    ]
    assert len(models[0]) == 2 and models[0] == models[1]
    monkeypatch.setenv(DEVICE_ENGINE_ENV, "tpu")
    with pytest.raises(ValueError, match="RLBACKDOORS_DEVICE_ENGINE='tpu' is not allowed"):
        group.device_engine_types()


def test_bench_zoo_conv_sides_set_their_jobs_convolutions_and_each_model_records_it(tmp_path, monkeypatch):
    """``--side 2:cpu:1::::grouped`` (one grouped conv2d for a group's agents) against the default:
    the side's jobs compute as told (``RLBACKDOORS_STACKED_CONV``, restored after each side) and
    each of its CNN models records the way in metrics.json; the default side's record nothing."""
    import rlbackdoors.zoo.run as zoo_run_module
    from rlbackdoors.bench.zoo import bench_zoo
    from rlbackdoors.models.minigrid import STACKED_CONV_ENV

    monkeypatch.setenv(STACKED_CONV_ENV, "cuda:gemm")
    seen, real = [], zoo_run_module.run
    monkeypatch.setattr(zoo_run_module, "run", lambda *a, **k: seen.append(os.environ[STACKED_CONV_ENV]) or real(*a, **k))  # what the jobs inherit
    result = bench_zoo(
        "lavaworld",
        "cnn",
        models=2,
        frames=3200,
        sides=[(2, "cpu", 1, 0, "torch", "", ""), (2, "cpu", 1, 0, "torch", "", "grouped")],
        keep=str(tmp_path),
        eval_episodes=4,
    )
    assert [s.get("conv") for s in result["sides"]] == [None, "grouped"] and all(s["models"] == 2 for s in result["sides"])
    assert seen == ["cuda:gemm", "cpu:grouped"] and os.environ[STACKED_CONV_ENV] == "cuda:gemm"
    records = [
        [json.loads(p.read_text()).get("conv") for p in sorted((tmp_path / name / "models").glob("*/metrics.json"))]
        for name in ("side0-k2-cpu-w1", "side1-k2-cpu-w1-conv-grouped")
    ]
    assert records == [[None, None], ["grouped", "grouped"]]


def test_ready_models_are_shared_out_in_capped_chunks():
    from rlbackdoors.zoo.run import _chunks

    assert [len(c) for c in _chunks(list(range(78)), 2, 8)] == [32, 32]  # at most 4 K per job: results keep coming
    assert [len(c) for c in _chunks(list(range(5)), 2, 8)] == [3, 2]
    assert _chunks(list(range(5)), 2, 1) == [[0], [1]]  # group size 1: a job per model, as before
    assert _chunks(list(range(5)), 0, 8) == [] and _chunks([], 2, 8) == []
    # like models share a job: the ones that start now, dealt out by kind, in order within one
    assert _chunks(list(range(8)), 2, 8, like=lambda x: x % 2) == [[0, 2, 4, 6], [1, 3, 5, 7]]
    assert _chunks(list(range(78)), 2, 8, like=lambda x: x % 2) == [list(range(0, 64, 2)), list(range(1, 64, 2))]


def test_bench_zoo_trains_the_attack_it_is_given(tmp_path):
    """``--attack``: the poisoned models of every side train it (config and budget used), clean ones clean; a
    name the registry does not have is refused in one line naming the field."""
    from rlbackdoors.bench.zoo import bench_spec, bench_zoo

    result = bench_zoo(
        "lavaworld", models=2, frames=1280, sides=[(1, "cpu", 1, 0, "torch", "")], workers=1, keep=str(tmp_path), eval_episodes=2, attack="trojdrl"
    )
    assert result["attack"] == "trojdrl" and result["sides"][0]["failed"] == 0
    metrics = [json.loads(p.read_text()) for p in (tmp_path / "side0-k1-cpu-w1" / "models").glob("*/metrics.json")]
    assert sorted(m.get("attack", "envmix") for m in metrics if m["poisoned"]) == ["trojdrl"]
    assert all(m["attack_budget_used"]["frames_poisoned"] > 0 for m in metrics if m["poisoned"])
    with pytest.raises(ConfigError, match=r"cells\[0\]\.attacks\[0\]\.attack='nope' is not allowed") as err:
        from rlbackdoors.zoo.spec import parse_spec

        parse_spec(bench_spec("lavaworld", None, 2, 1280, "cpu", attack="nope"))
    assert "\n" not in str(err.value)


def test_bench_zoo_compiled_eval_sides_set_both_backends():
    """``--side K:cpu:W:0:compiled-eval``: the compiled trainer with ``train.eval_backend`` compiled;
    ``compiled`` alone keeps torch's evaluations."""
    from rlbackdoors.bench.zoo import bench_spec, parse_side
    from rlbackdoors.zoo.spec import parse_spec

    assert parse_side("8:cpu:2:0:compiled-eval").backend == "compiled-eval"
    assert bench_spec("lavaworld", None, 2, 1280, "cpu", update_backend="compiled")["overrides"]["train"].get("eval_backend") is None
    spec = bench_spec("lavaworld", None, 2, 1280, "cpu", update_backend="compiled-eval")
    assert spec["overrides"]["train"]["eval_backend"] == "compiled" and spec["overrides"]["ppo"]["update_backend"] == "compiled"
    parse_spec(spec)  # (a spec the zoo plans)


@pytest.mark.slow  # (over 20 s on 2 cores: out of the default run, `make test-slow`)
def test_bench_zoo_compiled_eval_sides_play_their_evaluations_in_the_program(tmp_path):
    """A ``compiled-eval`` side trains so, recorded in the side's result and in each model's config."""
    from rlbackdoors.bench.zoo import bench_zoo

    result = bench_zoo("lavaworld", models=2, frames=1280, sides=[(2, "cpu", 1, 0, "compiled-eval")], keep=str(tmp_path), eval_episodes=4)
    side = result["sides"][0]
    assert side["update_backend"] == "compiled" and side["eval_backend"] == "compiled" and side["models"] == 2 and side["failed"] == 0
    configs = [json.loads(p.read_text()) for p in (tmp_path / "side0-k2-cpu-w1-compiled-eval" / "models").glob("*/config.json")]
    assert len(configs) == 2 and all(c["train"]["eval_backend"] == "compiled" and c["ppo"]["update_backend"] == "compiled" for c in configs)
