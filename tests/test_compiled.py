"""The compiled PPO iteration (algos/compiled.py) piece by piece against the torch trainer's
algorithm, and whole: reproducible, and learning LavaWorld.

Each piece (forward, sampling, GAE, loss and its gradient, clipping and Adam) is run on the same
inputs as the torch code it stands for. XLA and torch round differently (the order of a dot
product's sums), so floats are compared within 1e-5 of the array's largest magnitude (float32
carries 6e-8: the raw bytes of an observation, up to 120 through a trigger, sum through 147 inputs, so an output
near zero inherits the rounding of its large partial sums); the sampled actions, a function of
those floats at thresholds a random uniform almost never meets, exactly.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

import jax  # a core dependency: the compiled trainer's

from rlbackdoors.algos import ppo as torch_ppo  # noqa: E402
from rlbackdoors.algos.compiled import Hyper, Learner, init_agents, iterate, network, parts, state_dicts  # noqa: E402
from rlbackdoors.config import PPOConfig, RunConfig  # noqa: E402
from rlbackdoors.envs.lavaworld_jax import lavaworld_jax  # noqa: E402
from rlbackdoors.models import build_model  # noqa: E402
from rlbackdoors.poison.mix import make_env_mix  # noqa: E402

RTOL = 1e-5


def close(got, want, rtol: float = RTOL) -> None:
    """Within ``rtol`` of the largest magnitude of ``want`` (see the module doc)."""
    want = np.asarray(want, dtype=np.float64)
    np.testing.assert_allclose(np.asarray(got, dtype=np.float64), want, rtol=0, atol=rtol * max(np.abs(want).max(), 1e-30))


def fc():
    return build_model("fc", "lavaworld")


def cnn():
    return build_model("cnn", "lavaworld")


def direction_fc():
    return build_model("fc", "randomized-lavaworld")


def direction_cnn():
    return build_model("cnn", "randomized-lavaworld")


# LavaWorld's networks, and Randomized LavaWorld's (a leading Flatten; the direction appended to the embedding)
ARCHS = pytest.mark.parametrize("make", [fc, cnn, direction_fc, direction_cnn], ids=["fc", "cnn", "direction-fc", "direction-cnn"])


def torch_input(model, obs, dirs):
    """What the torch model reads: the views, with their directions where it appends them."""
    image = torch.from_numpy(obs)
    return {"image": image, "direction": torch.from_numpy(dirs.astype(np.int64))} if getattr(model, "appends_direction", False) else image


def random_obs(rng, n):
    """Views of grid codes (objects to 10, colours to 5, states to 2), a quarter of them through a
    multiplicative trigger's table (x12 mod 256), as a poisoned copy sees them."""
    obs = rng.integers(0, 11, (n, 7, 7, 3)).astype(np.uint8)
    obs[: n // 4] = (obs[: n // 4].astype(np.int64) * 12 % 256).astype(np.uint8)
    return obs


def torch_params(agents, k=0):
    return {name: torch.from_numpy(np.array(value[k])) for name, value in agents.params.items()}


@ARCHS
def test_init_is_the_torch_models_and_the_weights_go_back_as_its_state_dict(make):
    agents, model = init_agents(make, [3, 4])
    torch.manual_seed(4)
    want = make().state_dict()
    got = state_dicts(agents)[1]
    assert list(got) == list(want) and all(torch.equal(got[k], want[k]) for k in want)
    rng = np.random.default_rng(0)
    obs, dirs = random_obs(rng, 64), rng.integers(0, 4, 64).astype(np.int32)
    p = parts(network(model), Hyper())
    logits, values = p.forward({k: v[1] for k, v in agents.params.items()}, obs, dirs)
    m = make()
    m.load_state_dict(got)
    with torch.no_grad():
        t_logits, t_values = m(torch_input(m, obs, dirs))
    close(logits, t_logits.numpy())
    close(values, t_values.numpy())


@ARCHS
def test_sampling_gae_loss_and_adam_are_the_torch_trainers(make):
    rng = np.random.default_rng(1)
    cfg = PPOConfig()
    hyper = Hyper.of(cfg)
    agents, model = init_agents(make, [0])
    p = parts(network(model), hyper)
    params = {k: v[0] for k, v in agents.params.items()}
    # sampling: the same uniform, the same action
    logits = rng.normal(0, 2, (4096, 3)).astype(np.float32)
    u = rng.random(4096).astype(np.float32)
    want = torch_ppo.sample_actions(torch.from_numpy(logits), u=torch.from_numpy(u)).numpy()
    assert np.array_equal(np.asarray(p.sample(logits, u)), want)
    assert set(want.tolist()) == {0, 1, 2}
    # GAE over 128 steps of 10 envs with episode ends
    rewards = (rng.random((128, 10)) < 0.05).astype(np.float32) * rng.random((128, 10)).astype(np.float32)
    dones = rng.random((128, 10)) < 0.05
    values, next_value = rng.normal(0, 1, (128, 10)).astype(np.float32), rng.normal(0, 1, 10).astype(np.float32)
    want = torch_ppo.gae(torch.from_numpy(rewards), torch.from_numpy(dones), torch.from_numpy(values), torch.from_numpy(next_value), cfg.gamma, cfg.gae_lambda)
    close(p.gae(rewards, dones, values, next_value), want.numpy())
    # the loss, its gradient, the clipping and Adam: three optimiser steps on one minibatch
    n = 256
    obs, dirs = random_obs(rng, n), rng.integers(0, 4, n).astype(np.int32)
    actions = rng.integers(0, 3, n)
    old_logp = np.log(rng.uniform(0.2, 0.6, n)).astype(np.float32)
    old_values = rng.normal(0, 1, n).astype(np.float32)
    adv = rng.normal(0, 1, n).astype(np.float32)
    returns = (old_values + adv).astype(np.float32)
    batch = (p.inputs(obs), dirs, actions.astype(np.int32), old_logp, old_values, adv, returns)
    m = make()
    m.load_state_dict(state_dicts(agents)[0])
    opt = torch.optim.Adam(m.parameters(), lr=cfg.lr, eps=cfg.adam_eps)
    kinks: dict[str, torch.Tensor] = {}  # a head's units whose output came within rounding of a ReLU's kink (torch's side)
    avg = {k: np.zeros_like(v) for k, v in params.items()}
    sq = {k: np.zeros_like(v) for k, v in params.items()}
    step = np.float32(0)
    t_batch = [torch.from_numpy(x) for x in (actions, old_logp, old_values, adv, returns)]
    for _ in range(3):
        for name, near in heads_near_kinks(m, obs, dirs).items():
            kinks[name] = kinks.get(name, near) | near
        (value, (pl, vl, ent)), grad = jax.value_and_grad(p.loss, has_aux=True)(params, *batch)
        params, avg, sq, step, norm = p.adam(params, avg, sq, step, grad)
        t_logits, t_values = m(torch_input(m, obs, dirs))
        t_loss, t_parts = torch_ppo.ppo_loss(cfg, t_logits, t_values, *t_batch)
        opt.zero_grad()
        t_loss.backward()
        t_norm = torch.nn.utils.clip_grad_norm_(list(m.parameters()), cfg.max_grad_norm)
        opt.step()
        # the losses (means of squares and products of those outputs) and the norm after Adam steps:
        # measured 1.1e-5 at most on an AMD EPYC (the forward 5e-7), hence 4e-5
        close(float(value), float(t_loss.detach()), 4 * RTOL)
        for got, key in zip((pl, vl, ent), ("policy_loss", "value_loss", "entropy")):
            close(float(got), float(t_parts[key].detach()), 4 * RTOL)
        close(float(norm), float(t_norm), 4 * RTOL)
        assert float(t_norm) > cfg.max_grad_norm  # the clipping was exercised
    for name, weight in m.named_parameters():
        # after three Adam steps: within 1e-4 of the largest weight (measured 4.3e-5), or, for a
        # part whose weights are all small (a bias that started at zero), within 1e-3 of the
        # three steps' reach (3 lr): Adam moves each weight by about lr whatever its gradient, so
        # a gradient near zero moves it by a rounding-driven fraction of lr (measured 1.9e-4 of
        # 3 lr on the direction FC's first bias). A unit at a ReLU's kink on some frame (its
        # output within 1e-5 of zero: measured 2.5e-7 on the direction CNN's actor, third step) is
        # on or off by rounding, so that frame's share of its row's gradient is in or out: those
        # rows are left out (at most a few of a layer's units)
        want, got = weight.detach().numpy(), np.asarray(params[name])
        rows = ~kinks.get(name.rsplit(".", 1)[0], torch.zeros(want.shape[0], dtype=torch.bool)).numpy()
        assert rows.mean() > 0.95
        atol = max(1e-4 * np.abs(want).max(), 1e-3 * 3 * cfg.lr)
        np.testing.assert_allclose(got[rows], want[rows], rtol=0, atol=atol, err_msg=name)


def heads_near_kinks(m, obs, dirs) -> dict[str, torch.Tensor]:
    """Per Linear layer of the heads (``actor.0``, ...), its units whose output is within 1e-5 of
    zero on some frame (the layers run one by one: the model's forward does not call them)."""
    with torch.no_grad():
        if getattr(m, "appends_direction", False):
            e = m.image_embedding(torch.from_numpy(obs).permute(0, 3, 1, 2).float()).reshape(len(obs), -1)
            e = torch.cat([e, torch.from_numpy(dirs).float()[:, None]], 1)
        else:
            e = m.embed(torch.from_numpy(obs))
        out = {}
        for part in ("actor", "critic"):
            x = e
            for i, layer in enumerate(getattr(m, part)):
                x = layer(x)
                if isinstance(layer, torch.nn.Linear):
                    out[f"{part}.{i}"] = (x.abs() < 1e-5).any(0)
    return out


class Group:
    """K learners of LavaWorld FC with the env mix, iterated together (algos.compiled.iterate)."""

    def __init__(self, seeds: list[int], clean: bool = False, depth: int = 4):
        cfg = RunConfig.from_dict({"env": {"name": "lavaworld"}, "poison": {"trigger": "multiplicative:12", "poisoned": not clean}})
        self.learners = []
        for seed in seeds:
            e = make_env_mix(cfg.env, cfg.poison, seed)
            obs, _ = e.reset(seed=seed * 1000)
            torch.manual_seed(seed)
            self.learners.append(Learner(fc(), e, Hyper.of(cfg.ppo), seed, obs, lavaworld_jax, depth=depth))
        self.frames = 0

    def iterate(self):
        out = iterate(self.learners)
        self.frames += out[0].num_frames
        return out

    def params(self, name: str) -> list[np.ndarray]:
        return [np.asarray(learner.state.params[name]) for learner in self.learners]


def test_an_iteration_is_reproducible_and_its_episodes_are_counted():
    """Two groups of the same seeds give the same bytes after two iterations (a shallow queue of 4
    layouts a slot, so some iteration runs again deeper), and the steps' rewards and episode ends
    come back per agent; the learners moved, each its own way."""
    sides = []
    for _ in range(2):
        g = Group([0, 1])
        stats = [g.iterate() for _ in range(2)]
        sides.append((g, stats))
    (a, sa), (b, sb) = sides
    for name in a.learners[0].state.params:
        assert all(np.array_equal(x, y) for x, y in zip(a.params(name), b.params(name)))
    assert all(np.array_equal(x.obs, y.obs) for x, y in zip(a.learners, b.learners))
    assert all(np.array_equal(x.rewards, y.rewards) and np.array_equal(x.dones, y.dones) and x.losses == y.losses for s, t in zip(sa, sb) for x, y in zip(s, t))
    first = sa[0][0]
    assert first.rewards.shape == first.dones.shape == (128, 10) and first.num_frames == 1280 and first.capacity == 2
    assert first.dones[:, :8].sum() > 0  # 8 clean copies end episodes in 128 random steps
    assert a.learners[0].depth > 4  # the shallow queue starved and ran again deeper
    assert a.frames == 2 * 128 * 10
    w = a.params("actor.2.weight")
    assert not np.array_equal(w[0], w[1])
    assert not np.array_equal(w[0], init_agents(fc, [0])[0].params["actor.2.weight"][0])


@pytest.mark.slow
def test_the_compiled_iteration_learns_the_clean_task():
    """4 clean agents, 250 iterations (320 k frames each): the torch trainer's clean LavaWorld FC
    model is at clean SR 0.94 by 300 k frames (the demo's run); here the training episodes of the
    last iteration (sampled actions, about 20 an agent) must reach the goal at least half the time,
    where a random policy's reach it about 2 % of the time (the first iteration's)."""
    g = Group([0, 1, 2, 3], clean=True)

    def reach(out):  # per agent: ended episodes that paid (a grid episode pays only at the goal here)
        return np.array([(o.rewards[o.dones] > 0).mean() for o in out])

    start = reach(g.iterate())
    for _ in range(248):
        g.iterate()
    end = reach(g.iterate())
    assert (start < 0.1).all() and (end >= 0.5).all(), (start, end)
