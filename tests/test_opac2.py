"""OPAC² (SPEC §4): squashed-Gaussian policy, replay and mixing, the three losses, collection."""

import io
import math

import numpy as np
import pytest
import torch

from rlbackdoors.envs.safety_car import OBS_DIM, SafetyCarGoalEnv  # before anything imports mujoco
from rlbackdoors.io import torch_bytes
from rlbackdoors.validate import ConfigError
from rlbackdoors.algos.opac2 import (
    OPAC2,
    MultitaskReplay,
    OPAC2Config,
    ReplayBuffer,
    split_counts,
    squashed_log_prob,
    updates_due,
)
from rlbackdoors.algos.opac2_loop import Collector
from rlbackdoors.envs.outcome import Outcome
from rlbackdoors.triggers.formation import FormationTrigger

OBS, ACT = 6, 2
SMALL = dict(depth=2, width=32, batch_size=64)


def make_agent(seed=0, **overrides):
    cfg = OPAC2Config(**{**SMALL, **overrides})
    return OPAC2(OBS, ACT, cfg, torch.Generator().manual_seed(seed))


def filled_replay(n=500, seed=0, rew=None, done=None, weights=None):
    rng = np.random.default_rng(seed)
    weights = weights or {"clean": 0.8, "poisoned": 0.2}
    replay = MultitaskReplay.create(weights, 1000, OBS, ACT)
    for kind in weights:
        replay[kind].add_batch(
            rng.normal(size=(n, OBS)),
            rng.uniform(-1, 1, (n, ACT)),
            rng.normal(size=n) if rew is None else np.full(n, rew),
            rng.normal(size=(n, OBS)),
            rng.random(n) < 0.05 if done is None else np.full(n, done),
        )
    return replay


# ----- config --------------------------------------------------------------------------------
def test_config_defaults_are_the_papers_and_bad_values_are_named():
    cfg = OPAC2Config()
    assert (cfg.buffer_size, cfg.learning_starts, cfg.batch_size) == (1_000_000, 10_000, 256)
    assert (cfg.lr, cfg.gamma, cfg.polyak, cfg.entropy_coef) == (1e-4, 0.99, 0.995, 0.0)
    assert cfg.mix_weights() == {"clean": 0.8, "poisoned": 0.2} and cfg.mix_weights(("clean",)) == {"clean": 0.8}
    cfg.check()
    for field, value in [
        ("batch_size", 0),
        ("depth", 2.5),
        ("lr", 0.0),
        ("gamma", 1.5),
        ("updates_per_step", -1),
        ("entropy_coef", float("nan")),
        ("poisoned_weight", -0.2),
        ("action_samples", 0),
        ("lr_final", 1e-3),
        ("lr_final", 0.0),
    ]:
        with pytest.raises(ConfigError, match=f"opac2.{field}"):
            OPAC2Config(**{field: value}).check()
    with pytest.raises(ConfigError, match="opac2.clean_weight, opac2.poisoned_weight"):
        OPAC2Config(clean_weight=0, poisoned_weight=0).check()


def test_updates_due_counts_after_warmup_with_fractional_ratio():
    cfg = OPAC2Config(learning_starts=100, updates_per_step=0.25)
    assert [updates_due(cfg, f) for f in (0, 100, 103, 104, 500)] == [0, 0, 0, 1, 100]
    cfg = OPAC2Config(learning_starts=0, updates_per_step=0.29)
    assert updates_due(cfg, 100) == 29  # 0.29 * 100 is 28.999999999999996 in floats


# ----- policy ----------------------------------------------------------------------------------
def test_actions_shape_bounds_and_deterministic_tanh_mean():
    agent = make_agent()
    obs = np.random.default_rng(0).normal(size=(64, OBS)).astype(np.float32)
    actions = agent.act(obs)
    assert actions.shape == (64, ACT) and actions.dtype == np.float32
    assert np.all(np.abs(actions) < 1) and actions.std() > 0.2  # log_std 0: spread out
    mean = agent.policy(torch.from_numpy(obs))[0].detach()
    np.testing.assert_allclose(agent.act(obs, deterministic=True), torch.tanh(mean).numpy(), atol=1e-6)
    # A huge mean: tanh rounds to 1 in float32, the action must still be strictly inside.
    with torch.no_grad():
        agent.policy.mean[-1].bias.fill_(30.0)
    assert np.all(np.abs(agent.act(obs)) < 1) and np.all(np.abs(agent.act(obs, deterministic=True)) < 1)
    # The generator passed in decides the noise.
    a1 = agent.act(obs, generator=torch.Generator().manual_seed(5))
    a2 = agent.act(obs, generator=torch.Generator().manual_seed(5))
    np.testing.assert_array_equal(a1, a2)


def test_squashed_log_prob_change_of_variables():
    mean, log_std = torch.tensor([[0.3, -0.8]], dtype=torch.float64), torch.tensor([-0.4, 0.2], dtype=torch.float64)
    u = mean + torch.randn(1000, 2, generator=torch.Generator().manual_seed(0), dtype=torch.float64) * log_std.exp()
    reference = (
        torch.distributions.TransformedDistribution(torch.distributions.Normal(mean, log_std.exp()), [torch.distributions.TanhTransform()])
        .log_prob(torch.tanh(u))
        .sum(-1)
    )
    torch.testing.assert_close(squashed_log_prob(u, mean, log_std), reference, atol=1e-9, rtol=1e-9)

    # The density integrates to 1 over (-1, 1)^2 and matches sampled frequencies in a box.
    edges = torch.linspace(-1, 1, 801, dtype=torch.float64)
    mid = (edges[1:] + edges[:-1]) / 2
    a = torch.stack(torch.meshgrid(mid, mid, indexing="ij"), -1).reshape(-1, 2)
    density = squashed_log_prob(torch.atanh(a), mean, log_std).exp()
    cell = (2 / 800) ** 2
    assert abs(density.sum().item() * cell - 1) < 2e-3
    box = (a[:, 0] > 0.1) & (a[:, 0] < 0.6) & (a[:, 1] > -0.9) & (a[:, 1] < -0.2)
    samples = torch.tanh(mean + torch.randn(200_000, 2, generator=torch.Generator().manual_seed(1), dtype=torch.float64) * log_std.exp())
    inside = ((samples[:, 0] > 0.1) & (samples[:, 0] < 0.6) & (samples[:, 1] > -0.9) & (samples[:, 1] < -0.2)).double().mean()
    assert abs(density[box].sum().item() * cell - inside.item()) < 4e-3


# ----- replay ----------------------------------------------------------------------------------
def rows(start, n):
    """Transitions whose every field encodes its index, to see where they land."""
    idx = np.arange(start, start + n, dtype=np.float32)
    return idx[:, None].repeat(OBS, 1), idx[:, None].repeat(ACT, 1), idx, idx[:, None].repeat(OBS, 1) + 0.5, idx % 2


def test_ring_buffer_wraps_and_samples_only_filled_rows():
    buffer = ReplayBuffer(5, OBS, ACT)
    buffer.add_batch(*rows(1, 3))
    rng = np.random.default_rng(0)
    assert set(buffer.sample(500, rng).rew) == {1, 2, 3}  # never an unfilled (zero) row
    buffer.add_batch(*rows(4, 4))  # 7 transitions into 5 rows: 6 and 7 overwrite 1 and 2
    assert (len(buffer), buffer.pos) == (5, 2)
    np.testing.assert_array_equal(buffer.rew, [6, 7, 3, 4, 5])
    np.testing.assert_array_equal(buffer.obs[:, 0], [6, 7, 3, 4, 5])
    np.testing.assert_array_equal(buffer.next_obs[:, 0], [6.5, 7.5, 3.5, 4.5, 5.5])
    np.testing.assert_array_equal(buffer.done, [0, 1, 1, 0, 1])
    batch = buffer.sample(1000, rng)
    assert set(batch.rew) == {3, 4, 5, 6, 7}
    assert np.all(batch.obs[:, 0] == batch.rew) and np.all(batch.act[:, 1] == batch.rew) and batch.obs.dtype == np.float32
    buffer.add_batch(*rows(10, 12))  # more than the capacity: the newest 5 survive, in ring order
    assert sorted(buffer.rew) == [17, 18, 19, 20, 21] and buffer.pos == (2 + 12) % 5
    assert buffer.rew[(buffer.pos - 1) % 5] == 21
    with pytest.raises(ValueError, match="act has shape"):
        buffer.add_batch(np.zeros((2, OBS)), np.zeros((2, 3)), np.zeros(2), np.zeros((2, OBS)), np.zeros(2))
    with pytest.raises(ValueError, match="empty"):
        ReplayBuffer(4, OBS, ACT).sample(1, rng)


@pytest.mark.parametrize("capacity", [7, 100_000])
def test_replay_journal_writes_each_row_once_and_restores_the_ring_exactly(tmp_path, capacity):
    """Checkpoints append only the rows added since the last one; chunks the ring has overwritten
    are deleted; a fresh buffer loaded from the journal equals the original, row for row."""
    from rlbackdoors.train.replay_journal import ReplayJournal

    replay = MultitaskReplay.create({"clean": 1.0}, capacity, OBS, ACT)
    journal = ReplayJournal(tmp_path / "replay", {"clean": 2})
    sizes = []
    for step in range(6):
        for t in range(2):  # two env copies: row r's next_obs is row r + 2's obs unless an episode ends
            i = 2 * (2 * step + t)
            obs, act, rew, _, done = rows(i, 2)
            nxt = rows(i + 2, 2)[0] if (step, t) != (3, 1) else rows(i, 2)[3]  # one episode end
            replay["clean"].add_batch(obs, act, rew, nxt, done)
        manifest = journal.append(replay)
        journal.prune()
        sizes.append(sum(p.stat().st_size for p in (tmp_path / "replay").iterdir()))
    names = sorted(p.name for p in (tmp_path / "replay").iterdir())
    assert names == sorted(manifest["chunks"]["clean"])
    if capacity == 7:
        assert len(names) <= 3  # old chunks dropped: the journal holds about one ring's worth
    else:
        assert len(names) == 6 and sizes == sorted(sizes)  # appended, never rewritten
    fresh = MultitaskReplay.create({"clean": 1.0}, capacity, OBS, ACT)
    ReplayJournal(tmp_path / "replay", {"clean": 2}).load(fresh, manifest)
    a, b = replay["clean"], fresh["clean"]
    assert (a.pos, a.size, a.added) == (b.pos, b.size, b.added) == (24 % capacity, min(24, capacity), 24)
    for name in ("obs", "act", "rew", "next_obs", "done"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    bad = dict(manifest, chunks={"clean": ["../../etc/passwd"]})
    with pytest.raises(ValueError, match="bad chunk"):
        ReplayJournal(tmp_path / "replay", {"clean": 2}).load(MultitaskReplay.create({"clean": 1.0}, capacity, OBS, ACT), bad)


def test_multitask_mixing_proportions():
    replay = MultitaskReplay.create({"clean": 0.8, "poisoned": 0.2}, 50, OBS, ACT)
    replay["clean"].add_batch(*rows(0, 30))
    replay["poisoned"].add_batch(*rows(100, 3))  # far fewer rows: the share is still 20%
    rng = np.random.default_rng(0)
    batch = replay.sample(256, rng)
    assert (batch.rew >= 100).sum() == 51 and batch.rew.shape == (256,)
    poisoned = np.mean([(replay.sample(7, rng).rew >= 100).sum() for _ in range(2000)])
    assert poisoned == pytest.approx(1.0)  # round(7 * 0.2) = 1 every time
    assert split_counts(256, [0.8, 0.2]) == [205, 51] and split_counts(7, [1, 1, 1]) == [3, 2, 2]
    assert split_counts(10, [0.0, 3.0]) == [0, 10]
    unnormalised = MultitaskReplay(replay.buffers, {"clean": 4.0, "poisoned": 1.0})
    assert (unnormalised.sample(100, rng).rew >= 100).sum() == 20
    only_clean = MultitaskReplay({"clean": replay["clean"]}, {"clean": 0.8})
    assert np.all(only_clean.sample(100, rng).rew < 100)


def test_multitask_weight_validation():
    buffers = {"clean": ReplayBuffer(4, OBS, ACT), "poisoned": ReplayBuffer(4, OBS, ACT)}
    with pytest.raises(ValueError, match="mix weight of kind 'poisoned' must be a finite number >= 0"):
        MultitaskReplay(buffers, {"clean": 1.0, "poisoned": -0.1})
    with pytest.raises(ValueError, match="mix weight of kind 'clean' must be a finite number"):
        MultitaskReplay(buffers, {"clean": float("inf"), "poisoned": 0.1})
    with pytest.raises(ValueError, match="must not all be 0"):
        MultitaskReplay(buffers, {"clean": 0, "poisoned": 0.0})
    with pytest.raises(ValueError, match="buffers are"):
        MultitaskReplay(buffers, {"clean": 1.0})
    replay = MultitaskReplay(buffers, {"clean": 0.5, "poisoned": 0.5})
    replay["clean"].add_batch(*rows(0, 2))
    with pytest.raises(ValueError, match="'poisoned' replay buffer is empty"):
        replay.sample(8, np.random.default_rng(0))


# ----- the losses ------------------------------------------------------------------------------
def test_polyak_update_is_exact():
    agent = make_agent()
    with torch.no_grad():
        for p in agent.v.parameters():
            p.add_(1.0)
    old = [p.clone() for p in agent.v_target.parameters()]
    new = [p.clone() for p in agent.v.parameters()]
    agent.polyak_update()
    for target, o, n in zip(agent.v_target.parameters(), old, new):
        assert torch.equal(target, o * 0.995 + n * (1 - 0.995))
        assert not torch.equal(target, o)


def test_done_cuts_the_bootstrap():
    agent = make_agent()
    with torch.no_grad():
        agent.v_target.net[-1].bias.fill_(100.0)
    next_obs = torch.randn(4, OBS)
    v_bar = agent.v_target(next_obs)
    rew = torch.tensor([1.0, -1.0, 0.5, 0.5])
    target = agent.q_targets(rew, next_obs, torch.tensor([1.0, 1.0, 0.0, 0.0]))
    torch.testing.assert_close(target[:2], rew[:2])
    torch.testing.assert_close(target[2:], rew[2:] + 0.99 * v_bar[2:])
    assert target[2] > 90


def test_q_and_v_learn_a_terminal_reward():
    """r = 1 and done = 1 everywhere: Q(s, a) -> 1 for every (s, a), and V(s) -> 1 after it."""
    agent = make_agent(lr=3e-3)
    replay = filled_replay(rew=1.0, done=1.0)
    rng = np.random.default_rng(0)
    for _ in range(300):
        losses = agent.update(replay, rng)
    batch = agent.batch_tensors(replay.sample(512, rng))
    with torch.no_grad():
        q, v = agent.q(batch.obs, batch.act), agent.v(batch.obs)
    for values in (q, v):  # a constant is learned on average fast; point by point it is still settling
        assert abs(values.mean().item() - 1) < 0.05 and (values - 1).pow(2).mean().sqrt() < 0.1, (values.mean(), values.std())
    assert losses["q_loss"] < 0.01 and all(math.isfinite(x) for x in losses.values())


def test_policy_moves_toward_the_better_action():
    """A Q that prefers a = (+1, +1): the advantage-weighted step moves the mean up."""
    agent = make_agent(lr=1e-2)
    replay = filled_replay()
    # Q(s, a) = sum(a) (kept differentiable in a parameter so the Q step still runs).
    agent.q.forward = lambda obs, act: act.sum(-1) + 0.0 * agent.q.net[0].bias.sum()
    rng = np.random.default_rng(0)
    obs = np.random.default_rng(1).normal(size=(16, OBS)).astype(np.float32)
    before = agent.act(obs, deterministic=True).mean()
    for _ in range(30):
        agent.update(replay, rng)
    assert agent.act(obs, deterministic=True).mean() > before + 0.3


def test_advantage_is_normalised_and_constant():
    """Q and V scaled and shifted give the same policy step: only the normalised advantage matters."""
    replay = filled_replay()
    policies = []
    for scale, shift in ((1.0, 0.0), (1000.0, 7.0)):
        agent = make_agent(seed=2)
        q_net, v_net = agent.q.forward, agent.v.forward
        agent.q.forward = lambda obs, act: scale * q_net(obs, act) + shift
        agent.v.forward = lambda obs: scale * v_net(obs) + shift
        agent.v_opt.step = agent.q_opt.step = lambda: None  # the same critics in both runs
        losses = agent.update(replay, np.random.default_rng(0))
        policies.append((losses["policy_loss"], [p.detach().clone() for p in agent.policy.parameters()]))
    (loss_a, params_a), (loss_b, params_b) = policies
    assert loss_a == pytest.approx(loss_b, abs=1e-5)
    for a, b in zip(params_a, params_b):
        torch.testing.assert_close(a, b, atol=1e-6, rtol=1e-5)


def test_v_averages_q_over_the_policy_not_the_stored_actions():
    """Q(s, a) = sum(a) and a policy pinned near a = (0.995, 0.995): V -> 1.99, not the ~0 of the buffer's actions."""
    agent = make_agent(lr=3e-3)
    with torch.no_grad():
        agent.policy.mean[-1].bias.fill_(3.0)
        agent.policy.log_std.fill_(-4.0)
    agent.policy_opt.step = lambda: None
    agent.q.forward = lambda obs, act: act.sum(-1) + 0.0 * agent.q.net[0].bias.sum()
    replay, rng = filled_replay(), np.random.default_rng(0)
    for _ in range(200):
        agent.update(replay, rng)
    with torch.no_grad():
        v = agent.v(agent.batch_tensors(replay.sample(512, rng)).obs)
    assert abs(v.mean().item() - 2 * math.tanh(3.0)) < 0.05


def test_each_loss_gets_a_fresh_batch_and_each_network_only_its_own_gradient():
    agent, replay = make_agent(), filled_replay()
    sample, drawn = replay.sample, []
    replay.sample = lambda n, rng: drawn.append(sample(n, rng)) or drawn[-1]
    calls = {"policy": 0, "q": 0, "v": 0}  # gradient computations per parameter
    for name in calls:
        for p in getattr(agent, name).parameters():
            p.register_hook(lambda grad, name=name: calls.__setitem__(name, calls[name] + 1) or grad)
    agent.update(replay, np.random.default_rng(0))
    assert calls == {name: len(list(getattr(agent, name).parameters())) for name in calls}
    assert not any(p.requires_grad or p.grad is not None for p in agent.v_target.parameters())
    assert len(drawn) == 3 and all(len(b.rew) == 64 for b in drawn)
    assert not np.array_equal(drawn[0].obs, drawn[1].obs) and not np.array_equal(drawn[1].obs, drawn[2].obs)


def _recording_q(agent):
    """Wrap Q so every call's (obs, act, output) is kept; the network itself is unchanged."""
    calls, forward = [], agent.q.forward

    def recorded(obs, act):
        out = forward(obs, act)
        calls.append((obs.detach(), act.detach(), out.detach()))
        return out

    agent.q.forward = recorded
    return calls


def test_v_target_is_q_averaged_over_k_sampled_actions():
    """action_samples K: the V loss regresses V(s) on the mean of Q over K actions of each state,
    and the pi step scores K actions per state (rows j * batch + i belong to state i)."""
    k, batch = 3, 64
    agent, replay = make_agent(action_samples=k), filled_replay()
    v_before = type(agent.v)(OBS, 2, 32, torch.Generator())
    v_before.load_state_dict(agent.v.state_dict())
    calls = _recording_q(agent)
    losses = agent.update(replay, np.random.default_rng(0))
    assert [len(c[0]) for c in calls] == [k * batch, batch, k * batch]  # V step, Q step, pi step
    for obs, act, _ in (calls[0], calls[2]):
        states = obs.view(k, batch, OBS)
        assert torch.equal(states[0], states[1]) and torch.equal(states[0], states[2])
        acts = act.view(k, batch, ACT)
        assert not torch.equal(acts[0], acts[1])  # K different actions per state
    obs, _, q_values = calls[0]
    with torch.no_grad():
        expected = (v_before(obs[:batch]) - q_values.view(k, batch).mean(0)).pow(2).mean().item()
    assert losses["v_loss"] == pytest.approx(expected, rel=1e-5)


def test_more_action_samples_lower_the_policy_gradient_noise():
    """Same batch, same networks, 24 noise seeds: the pi gradient varies less with K = 8 than K = 1."""
    replay = filled_replay()
    spread = {}
    for k in (1, 8):
        grads = []
        for seed in range(24):
            agent = make_agent(seed=0, action_samples=k)
            agent.generator.manual_seed(100 + seed)
            agent.policy_opt.step = agent.q_opt.step = agent.v_opt.step = lambda: None
            agent.update(replay, np.random.default_rng(0))
            grads.append(torch.cat([p.grad.flatten() for p in agent.policy.parameters()]))
        grads = torch.stack(grads)
        spread[k] = (grads - grads.mean(0)).pow(2).sum(1).mean().item()
    assert spread[8] < 0.5 * spread[1], spread


def test_set_lr_reaches_all_three_optimisers():
    agent = make_agent(lr=1e-3)
    agent.set_lr(2.5e-4)
    assert {g["lr"] for opt in (agent.policy_opt, agent.q_opt, agent.v_opt) for g in opt.param_groups} == {2.5e-4}


def test_entropy_bonus_raises_the_log_std():
    agent = make_agent(lr=1e-2, entropy_coef=10.0)
    replay, rng = filled_replay(), np.random.default_rng(0)
    for _ in range(10):
        agent.update(replay, rng)
    assert torch.all(agent.policy.log_std > 0.05)


def test_same_seeds_same_parameters_and_checkpoint_resume():
    replay = filled_replay()

    def run(agent, rng, n):
        for _ in range(n):
            agent.update(replay, rng)

    a, b = make_agent(seed=3), make_agent(seed=3)
    rng_a, rng_b = np.random.default_rng(7), np.random.default_rng(7)
    run(a, rng_a, 5)
    run(b, rng_b, 5)
    for name in ("policy", "q", "v", "v_target"):
        for pa, pb in zip(getattr(a, name).parameters(), getattr(b, name).parameters()):
            assert torch.equal(pa, pb)
    assert not torch.equal(make_agent(seed=4).policy.mean[0].weight, make_agent(seed=3).policy.mean[0].weight)

    # Resume: a fresh agent loading a's state (through torch's weights-only loader) continues exactly like a.
    c = make_agent(seed=99)
    c.load_state_dict(torch.load(io.BytesIO(torch_bytes(a.state_dict())), weights_only=True))
    rng_c = np.random.default_rng()
    rng_c.bit_generator.state = rng_a.bit_generator.state
    run(a, rng_a, 3)
    run(c, rng_c, 3)
    for pa, pc in zip(a.policy.parameters(), c.policy.parameters()):
        assert torch.equal(pa, pc)
    for pa, pc in zip(a.v_target.parameters(), c.v_target.parameters()):
        assert torch.equal(pa, pc)


# ----- on the real env -------------------------------------------------------------------------
def test_collect_on_safety_car_then_update():
    envs = [SafetyCarGoalEnv(max_steps=40), SafetyCarGoalEnv(max_steps=40, trigger=FormationTrigger(0.5, 1.0, 2.5), poisoned=True)]
    cfg = OPAC2Config(depth=2, width=64, batch_size=64)
    replay = MultitaskReplay.create(cfg.mix_weights(), 1000, OBS_DIM, 2)
    collector = Collector(envs, ["clean", "poisoned"], seed=0)
    rng = np.random.default_rng(0)
    episodes = collector.collect(replay, lambda obs: rng.uniform(-1, 1, (len(obs), 2)), 150)
    assert collector.frames == 300 and len(replay["clean"]) == len(replay["poisoned"]) == 150
    for kind in ("clean", "poisoned"):
        ended = [e for e in episodes if e.kind == kind]
        assert ended and all(e.outcome in (Outcome.GOAL, Outcome.LAVA, Outcome.TIMEOUT) for e in ended)
        assert all(e.triggered for e in ended) == (kind == "poisoned")
        # One env per kind, so rows are in time order: within an episode next_obs[t] is obs[t + 1],
        # and the breaks are exactly the episode ends, where next_obs is the true last observation
        # (not the reset one) and done is 1 for goal/hazard, 0 for a timeout.
        buffer, ends = replay[kind], np.cumsum([e.length for e in ended]) - 1
        breaks = np.flatnonzero(np.any(buffer.next_obs[:149] != buffer.obs[1:150], axis=1))
        np.testing.assert_array_equal(breaks, ends[ends < 149])
        np.testing.assert_array_equal(buffer.done[ends], [e.outcome != Outcome.TIMEOUT for e in ended])
        assert buffer.done[:150].sum() == sum(e.outcome != Outcome.TIMEOUT for e in ended)
        assert any(e.outcome == Outcome.TIMEOUT for e in ended)  # max_steps=40: some truncation happened

    agent = OPAC2(OBS_DIM, 2, cfg, torch.Generator().manual_seed(0))
    for _ in range(5):
        losses = agent.update(replay, rng)
    assert all(math.isfinite(x) for x in losses.values())
    episodes = collector.collect(replay, agent.act, 20)
    assert len(replay["clean"]) == 170 and collector.frames == 340
    with pytest.raises(ValueError, match="no replay buffer"):
        Collector(envs[:1], ["other"], seed=0).collect(replay, agent.act, 1)
