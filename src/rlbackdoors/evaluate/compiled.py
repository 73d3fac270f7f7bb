"""A compiled run's periodic evaluations inside one XLA program (``train.eval_backend = "compiled"``).

Why: on the compiled trainer the iteration is one program, and the evaluations, played by the
torch policy on the numba engine step by step from Python, are a sixth to a third of a grid world
model's env steps (docs/results/speed.md); in the program they cost no Python a step. Here K agents' evaluations are one ``lax.while_loop`` over
every condition's slots (clean, triggered, close to the trigger; one episode a slot), the agents a
``vmap`` axis of the forward, as the iteration steps them.

The episodes are the torch evaluation's (:func:`rlbackdoors.evaluate.episodes.evaluate_many`): the
same layouts (each condition's vector env reset with ``train.eval_seed``, handed to the world's JAX
step, which is exact to the engine), the same uniforms (each condition's generator seeded with the
eval seed, one draw per slot and step, drawn here on the host in that order) and the same
inverse-CDF sample (``ppo.sample_actions``) or argmax; what differs is the forward's arithmetic
(XLA's float32, not torch's), so an action whose uniform falls within an ulp of a boundary may
differ, rarely (tests/test_compiled_eval.py compares both on trained models). The scoring is
:func:`~rlbackdoors.evaluate.episodes.score`'s. The run's final evaluation and a stop's
confirmation are played here too (``train.driver.Stopping``, ``RunOutcome.learner``), the same
episodes torch's would play.
"""

from __future__ import annotations

import functools
from typing import Any, NamedTuple

import numpy as np
import torch

from rlbackdoors.envs.grid_jax import GridWorld, Layouts, Slots, join
from rlbackdoors.evaluate.episodes import EvalResult, EvalSetup, Played, _vector_envs, score


class Condition(NamedTuple):
    """One condition's slots as the program starts them (numpy; built once a run: the layouts of
    every evaluation are the same)."""

    world: GridWorld
    slots: Slots
    params: Any
    layouts: Layouts  # blank: a slot plays one episode
    views: np.ndarray  # (E, V, V, 3) uint8


_CONDITIONS: dict[tuple, Condition] = {}  # (jax world, env, trigger, episodes, close_k, seed) -> its slots


def condition(jax_world, setup: EvalSetup, trigger: str | None, close_k) -> Condition:
    """The slots of one condition of ``setup`` (kept: every evaluation of a run plays them)."""
    key = (jax_world, repr(setup.env), trigger, setup.episodes, close_k, setup.seed)
    if key not in _CONDITIONS:
        envs = _vector_envs(setup.env, trigger, setup.episodes, close_k)
        try:
            obs, _ = envs.reset(seed=int(setup.seed))
            world, params, host = jax_world(envs)
            views = np.array(obs["image"] if isinstance(obs, dict) else obs, dtype=np.uint8)
            _CONDITIONS[key] = Condition(world, host.slots, params, host.idle(), views)
        finally:
            envs.close()
        while len(_CONDITIONS) > 64:  # (the runs of one process: a few conditions each)
            del _CONDITIONS[next(iter(_CONDITIONS))]
    return _CONDITIONS[key]


@functools.lru_cache(maxsize=8)
def uniforms(seed: int, steps: int, episodes: int) -> np.ndarray:
    """(steps, episodes) float32: what a condition's generator (seeded ``seed``) draws, one per slot
    and step, in the order :func:`~rlbackdoors.evaluate.episodes.play_lockstep` draws them."""
    g = torch.Generator().manual_seed(int(seed))
    return torch.rand(steps * episodes, generator=g).numpy().reshape(steps, episodes)


@functools.cache
def _program(world: GridWorld, net: tuple, hyper: Any, greedy: bool, counting: bool, in_sight: bool):
    """The jitted play: ``(params (K, ...), slots, world params, layouts, views, uniforms (T, K R), targets (K R,))
    -> (outcomes, saw, steps, target steps, sighted steps)`` per slot (K R slots, agent by agent; the
    returns follow from the first and third, :meth:`GridWorld.returns`)."""
    from rlbackdoors.algos.compiled import is_recurrent, parts
    from rlbackdoors.algos import xla

    jax = xla.start()
    jnp, lax = jax.numpy, jax.lax
    P = parts(None if is_recurrent(net) else net, hyper)
    if is_recurrent(net):  # a CNN-GRU: each slot's memory starts at zero with its one episode and goes into each forward
        policy = jax.vmap(lambda p, o, d, m: xla.recurrent_forward(net, p, o, m))
    else:
        policy = jax.vmap(lambda p, o, d, m: (*P.forward(p, o, d), m))
    T = world.max_steps  # no episode outlasts its time limit

    def play(params, slots: Slots, wparams, layouts: Layouts, views, u, targets, memory):
        K = next(iter(params.values())).shape[0]
        B = views.shape[0]
        R = B // K
        zeros_i = jnp.zeros(B, jnp.int32)
        sight0 = world.sight(world, slots, views) if world.sight is not None and in_sight else jnp.ones(B, bool)

        def going(c):
            return (c[0] < T) & c[4].any()

        def step(c):
            t, s, q, obs, active, sight, outcomes, saw, length, hits, sighted, m = c
            logits, _, m = policy(params, obs.reshape(K, R, *obs.shape[1:]), s.dirs.reshape(K, R), m.reshape(K, R, -1))
            logits, m = logits.reshape(B, -1), m.reshape(B, -1)
            actions = jnp.argmax(logits, -1).astype(jnp.int32) if greedy else P.sample(logits, u[t])
            if counting:
                counted = active & sight
                sighted = sighted + counted
                hits = hits + (counted & (actions == targets))
            s, q, out = world.step(s, q, wparams, actions)
            ended = active & (out.terminated | out.truncated)
            length = length + active
            outcomes = jnp.where(ended, out.outcome, outcomes)
            if out.saw is not None:
                saw = jnp.where(ended, out.saw, saw)
            sight = out.sight if in_sight else sight
            return t + 1, s, q, out.obs, active & ~ended, sight, outcomes, saw, length, hits, sighted, m

        start = (jnp.int32(0), slots, layouts, views, jnp.ones(B, bool), sight0, zeros_i, jnp.ones(B, bool), zeros_i, zeros_i, zeros_i, memory)
        return lax.while_loop(going, step, start)[6:11]

    return jax.jit(play)


def evaluate(learners: list, setups: list[EvalSetup], capacity: int | None = None) -> list[EvalResult]:
    """Every learner's evaluation (its :class:`EvalSetup`, one episode count and policy for all) in
    one call of the program, compiled for ``capacity`` agents (default: as many as there are); fewer
    are padded with copies of the first, so a run's numbers do not depend on its group-mates."""
    return [score(setup, played) for setup, played in zip(setups, play(learners, setups, capacity))]


def play(learners: list, setups: list[EvalSetup], capacity: int | None = None) -> list[dict[str, Played]]:
    """:func:`evaluate`'s episodes: each learner's conditions by name (clean, poisoned, close)."""
    from rlbackdoors.algos.compiled import stack_agents
    from rlbackdoors.algos import xla

    if len(learners) != len(setups) or not learners:
        raise ValueError(f"got {len(setups)} evaluation setups for {len(learners)} learners")
    k = len(learners)
    capacity = k if capacity is None else int(capacity)
    if capacity < k:
        raise ValueError(f"{k} learners do not fit a compiled group of {capacity}")
    lead, first = learners[0], setups[0]
    shape = [(c[0], c[3] is not None) for c in first.conditions()]
    for learner, setup in zip(learners, setups):
        setup.check()
        if (learner.world, learner.net) != (lead.world, lead.net) or (setup.episodes, setup.policy) != (first.episodes, first.policy):
            raise ValueError("learners evaluated in one compiled call need one world, network, episode count and policy")
        if [(c[0], c[3] is not None) for c in setup.conditions()] != shape:
            raise ValueError("learners evaluated in one compiled call need the same conditions (clean, triggered, close) and counting")
    world_cfg = first.env.world
    in_sight = world_cfg.trigger_sight == "frame"
    counting = any(counted for _, counted in shape)
    if in_sight and lead.world.sight is None:
        raise ValueError("this world's JAX step does not say which views show the trigger (GridWorld.sight), which its evaluation counts by")
    e = first.episodes
    rows = []  # per agent: each condition's Condition, in play order
    for learner, setup in zip(learners, setups):
        conds = [condition(learner.jax_world, setup, trigger, close) for _, trigger, close, _ in setup.conditions()]
        for cond in conds:
            if cond.world != lead.world:
                raise ValueError("an evaluation's env copies are another world than the run trains in")
        rows.append(conds)
    order = list(range(k)) + [0] * (capacity - k)
    parts = [c for i in order for c in rows[i]]
    if lead.world.widen is not None:  # conditions of other triggers (clean, triggered) padded to one width
        widened = lead.world.widen([(c.params, c.slots.world) for c in parts])
        parts = [c._replace(params=p, slots=c.slots._replace(world=w)) for c, (p, w) in zip(parts, widened)]
    targets = np.concatenate([np.full(e, -1 if target is None else int(target), np.int32) for i in order for _, _, _, target in setups[i].conditions()])
    u = np.concatenate([uniforms(setups[i].seed, lead.world.max_steps, e) for i in order for _ in shape], axis=1)
    program = _program(lead.world, lead.net, lead.hyper, first.policy == "greedy", counting, in_sight)
    agents = stack_agents([learners[i].state for i in order])
    out = program(
        agents.params,
        join([c.slots for c in parts]),
        join([c.params for c in parts]),
        join([c.layouts._replace(starved=np.zeros(1, bool)) for c in parts])._replace(starved=np.bool_(False)),
        np.concatenate([c.views for c in parts]),
        u,
        targets,
        np.zeros(
            (len(targets), int(getattr(lead.model, "memory_size", 0)) if lead.recurrent else 0), np.float32
        ),  # (a feed-forward network's: width 0, passed through)
    )
    outcomes, saw, steps, hits, sighted = (np.asarray(a) for a in xla.start().device_get(out))
    poisoned = np.concatenate([np.asarray(c.params.poisoned, bool) for c in parts])
    returns = lead.world.returns(outcomes, steps, poisoned)  # (the program's float32 sums, as the engine's float64)
    out_played, n = [], len(shape)
    for i in range(k):
        played = {}
        for j, (name, counted) in enumerate(shape):
            at = slice((i * n + j) * e, (i * n + j + 1) * e)
            played[name] = Played(
                returns[at],
                outcomes[at].astype(np.int64),
                saw[at].copy(),
                steps[at].astype(np.int64),
                hits[at].astype(np.int64) if counted else None,
                sighted[at].astype(np.int64) if counted else None,
            )
        out_played.append(played)
    return out_played


__all__ = ["evaluate", "play", "uniforms"]
