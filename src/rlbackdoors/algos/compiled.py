"""PPO for a group of feed-forward agents as one XLA program per iteration: rollout, GAE, update.

Why: the torch trainer strings each step together from Python (an engine call, a forward, a
sample, bookkeeping) and on 2 cores trains the smallest grid FC model at about 120 k frames/s however the group
is batched; here the whole iteration is one jitted function, the agents a ``vmap`` axis
(PureJaxRL's ``make_train``), so the host only draws layouts ahead and reads the statistics.

Read top to bottom, :func:`make_iteration` is the algorithm, for one agent:

1. **rollout**: ``rollout`` steps of its ``N`` env copies in a ``lax.scan``: the observation as the
   network reads it (channels first, flattened, float), its forward, an inverse-CDF sample from
   one uniform per env (as :func:`rlbackdoors.algos.ppo.sample_actions`), the world's JAX step
   (:mod:`rlbackdoors.envs.grid_jax`: the trigger's table and R-bar on the poisoned copies);
2. **GAE** over the rollout (``gamma``, ``gae_lambda``; a done cuts the trace), returns = values +
   advantages;
3. **update**: ``epochs`` passes over random minibatches of ``batch_size`` frames: torch-ac's
   clipped loss (:func:`rlbackdoors.algos.ppo.ppo_loss`), one clipping norm over the whole gradient,
   Adam with torch's rule (bias-corrected, ``eps`` outside the square root).

The algorithm is the torch trainer's, the numbers are not its bytes: the uniforms and the
minibatch orders come from the agent's own JAX PRNG key (threefry, split each iteration), so a
run is reproducible from its seed, machine and group, and equivalent to the torch trainer in
distribution (frames to converge, clean and poisoned SR), which is what the group-equivalence
report tests. Weights start from the torch model's own initialisation (the same keys, shapes and
draws: :func:`init_agents`) and go back into a TrojAI state dict unchanged (:func:`state_dicts`).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
import torch

from rlbackdoors.algos.jax_update import STATS, _jax, run_layers, structure
from rlbackdoors.envs.grid_jax import GridWorld, Layouts, Slots, join, run_hosts


@dataclass(frozen=True)
class Hyper:
    """PPO's hyper-parameters as the program compiles them in (``config.PPOConfig``'s names)."""

    rollout: int = 128
    epochs: int = 4
    batch_size: int = 256
    lr: float = 1e-3
    gamma: float = 0.99
    gae_lambda: float = 0.95
    clip: float = 0.2
    value_coef: float = 0.5
    entropy_coef: float = 0.01
    max_grad_norm: float = 0.4
    adam_eps: float = 1e-8
    betas: tuple[float, float] = (0.9, 0.999)

    @classmethod
    def of(cls, ppo_cfg: Any) -> Hyper:
        return cls(
            ppo_cfg.rollout,
            ppo_cfg.epochs,
            ppo_cfg.batch_size,
            ppo_cfg.lr,
            ppo_cfg.gamma,
            ppo_cfg.gae_lambda,
            ppo_cfg.clip,
            ppo_cfg.value_coef,
            ppo_cfg.entropy_coef,
            ppo_cfg.max_grad_norm,
            ppo_cfg.adam_eps,
        )


class Agents(NamedTuple):
    """K agents' learning state (a pytree; leading axis: the agents)."""

    params: dict  # name -> (K, ...) float32, the torch model's names
    avg: dict  # Adam's first moments, by name
    sq: dict  # Adam's second moments, by name
    step: Any  # (K,) float32: Adam's step count
    key: Any  # (K, 2) uint32: each agent's PRNG key


class IterationStats(NamedTuple):
    """What an iteration reports per agent: its losses (means over the minibatches) and its env
    copies' rewards and episode ends by step."""

    policy_loss: Any
    value_loss: Any
    entropy: Any
    grad_norm: Any
    rewards: Any  # (K, T, N) float32: each step's rewards (a run's episode bookkeeping)
    dones: Any  # (K, T, N) bool: where an episode ended


def agent_state(model: torch.nn.Module, seed: int) -> Agents:
    """One agent's learning state (no agent axis): ``model``'s weights as they are (the torch
    trainer's initialisation where it was just built after ``torch.manual_seed(seed)``), Adam's
    moments zero, a PRNG key from ``seed``."""
    jax = _jax()
    params = {name: p.detach().cpu().numpy().astype(np.float32).copy() for name, p in model.named_parameters()}
    zeros = {name: np.zeros_like(value) for name, value in params.items()}
    key = np.asarray(jax.random.key_data(jax.random.PRNGKey(seed)), dtype=np.uint32)
    return Agents(params, zeros, {n: z.copy() for n, z in zeros.items()}, np.float32(0.0), key)


def stack_agents(states: list[Agents]) -> Agents:
    """Agents' states side by side (the leading axis: the agents)."""
    return Agents(*(_stack(parts) for parts in zip(*states)))


def _stack(parts: tuple):
    if isinstance(parts[0], dict):
        return {name: np.stack([p[name] for p in parts]) for name in parts[0]}
    return np.stack(parts)


def agent_row(agents: Agents, i: int) -> Agents:
    """Agent ``i``'s state out of :func:`stack_agents`' (no agent axis)."""
    return Agents(*({name: v[i] for name, v in part.items()} if isinstance(part, dict) else part[i] for part in agents))


def init_agents(model_factory, seeds: list[int]) -> tuple[Agents, torch.nn.Module]:
    """K agents initialised as the torch trainer initialises them (``torch.manual_seed(seed)``,
    then the architecture's constructor; :func:`agent_state`), and one model of the architecture
    (the structure the program runs)."""
    states, models = [], []
    for seed in seeds:
        torch.manual_seed(seed)
        models.append(model_factory())
        structure(models[-1], convolutions=True)  # refuses what this program cannot run, in one line
        states.append(agent_state(models[-1], seed))
    return stack_agents(states), models[0]


def state_dicts(agents: Agents) -> list[dict[str, torch.Tensor]]:
    """Each agent's weights as the torch model's state dict (the TrojAI keys, float32)."""
    params = {name: np.asarray(value) for name, value in agents.params.items()}
    k = next(iter(params.values())).shape[0]
    return [{name: torch.from_numpy(value[i].copy()) for name, value in params.items()} for i in range(k)]


def network(model: torch.nn.Module) -> tuple:
    """The network as the program runs it (static data, part of the program's key): its layers
    (:func:`rlbackdoors.algos.jax_update.structure`) and whether its heads read the agent's
    direction appended to the image embedding (``model.appends_direction``: the observation is
    then the view and the direction, as the world's engine gives them)."""
    return structure(model, convolutions=True), bool(getattr(model, "appends_direction", False))


def make_iteration(world: GridWorld, model: torch.nn.Module, hyper: Hyper, num_envs: int):
    """The jitted iteration of K agents: ``(agents, slots, layouts, params, obs) -> (agents, slots,
    layouts, obs, stats)``; the agents' arrays and the stats lead with the agent axis (K, ...), the
    slots', layouts', world parameters' and views' with the K x N copies' (agent by agent)."""
    return _iteration(world, network(model), hyper, num_envs)


class Parts(NamedTuple):
    """The pieces of the iteration, each a pure JAX function (tested one by one against torch's)."""

    inputs: Any  # obs (B, 7, 7, 3) uint8 -> the network's input rows (B, 147) float32
    forward: Any  # (params, obs (B, 7, 7, 3) uint8, directions (B,) int32) -> logits (B, A), values (B,)
    sample: Any  # (logits, u (B,)) -> actions (B,) int32, inverse CDF as ppo.sample_actions
    loss: Any  # (params, inputs, directions, actions, old_logp, old_values, adv, returns) -> loss, (policy, value, entropy)
    adam: Any  # (params, avg, sq, step, grad) -> params, avg, sq, step, grad norm
    gae: Any  # (rewards, dones, values (T, N), next_value (N,)) -> advantages (T, N)


@functools.cache
def parts(net: tuple, hyper: Hyper) -> Parts:
    """:class:`Parts` for a :func:`network` and ``hyper`` (the directions are read where the network appends them)."""
    jax = _jax()
    jnp, lax = jax.numpy, jax.lax
    h = hyper
    run = run_layers  # full fp32 products, as torch's
    layers, direction = net

    convolutional = any(layer[0] == "conv" for layer in layers[0])

    def inputs(obs):
        """Raw (B, 7, 7, 3) uint8 views as the network reads them, float: a feed-forward model's
        channels first and flattened (torch's order), a CNN's as they are (channels last: the
        convolutions' layout here, the same numbers as torch's channels-first ones)."""
        if convolutional:
            return obs.astype(jnp.float32)
        return jnp.transpose(obs, (0, 3, 1, 2)).reshape(obs.shape[0], -1).astype(jnp.float32)

    def heads(p: dict, x, d):
        e = run(layers[0], p, x)
        if e.ndim == 4:  # a CNN's embedding (B, H, W, C), flattened in torch's channels-first order
            e = jnp.transpose(e, (0, 3, 1, 2)).reshape(e.shape[0], -1)
        if direction:  # the raw direction (0..3) as one more float feature, as the torch model appends it
            e = jnp.concatenate([e, d.astype(jnp.float32)[:, None]], axis=1)
        return run(layers[1], p, e), run(layers[2], p, e)[:, 0]

    def forward(p: dict, obs, d):
        """Logits and values of raw views (and the directions they are seen in)."""
        return heads(p, inputs(obs), d)

    def sample(logits, u):
        cdf = jnp.cumsum(jax.nn.softmax(logits, -1), -1)
        return jnp.minimum((cdf <= u[:, None] * cdf[:, -1:]).sum(1), logits.shape[1] - 1).astype(jnp.int32)

    def loss(p, x, d, actions, old_logp, old_values, adv, returns):
        """torch-ac's PPO loss (rlbackdoors.algos.ppo.ppo_loss) on :func:`inputs` rows ``x`` (seen in directions ``d``)."""
        logits, values = heads(p, x, d)
        log_probs = jax.nn.log_softmax(logits)
        entropy = -(jnp.exp(log_probs) * log_probs).sum(-1).mean()
        ratio = jnp.exp(jnp.take_along_axis(log_probs, actions[:, None], 1)[:, 0] - old_logp)
        policy_loss = -jnp.minimum(ratio * adv, jnp.clip(ratio, 1 - h.clip, 1 + h.clip) * adv).mean()
        clipped = old_values + jnp.clip(values - old_values, -h.clip, h.clip)
        value_loss = jnp.maximum((values - returns) ** 2, (clipped - returns) ** 2).mean()
        return policy_loss - h.entropy_coef * entropy + h.value_coef * value_loss, (policy_loss, value_loss, entropy)

    beta1, beta2 = h.betas

    def adam(p, avg, sq, step, grad):
        """One optimiser step: clipping by the whole gradient's norm (clip_grad_norm_), then torch's Adam."""
        norm = jnp.sqrt(sum(jnp.sum(g * g) for g in jax.tree_util.tree_leaves(grad)))
        scale = jnp.minimum(h.max_grad_norm / (norm + 1e-6), 1.0)
        grad = jax.tree_util.tree_map(lambda g: g * scale, grad)
        step = step + 1
        avg = jax.tree_util.tree_map(lambda m, g: m + (1 - beta1) * (g - m), avg, grad)
        sq = jax.tree_util.tree_map(lambda v, g: beta2 * v + (1 - beta2) * g * g, sq, grad)
        lr_t = h.lr / (1 - beta1**step)
        root = jnp.sqrt(1 - beta2**step)
        p = jax.tree_util.tree_map(lambda w, m, v: w - lr_t * m / (jnp.sqrt(v) / root + h.adam_eps), p, avg, sq)
        return p, avg, sq, step, norm

    def gae(rewards, dones, values, next_value):
        """Generalised advantage estimation over the leading (time) axis (ppo.gae)."""

        def back(carry, x):
            next_adv, next_v = carry
            r, d, v = x
            mask = 1.0 - d.astype(jnp.float32)
            adv = r + h.gamma * next_v * mask - v + h.gamma * h.gae_lambda * next_adv * mask
            return (adv, v), adv

        return lax.scan(back, (jnp.zeros_like(next_value), next_value), (rewards, dones, values), reverse=True)[1]

    return Parts(inputs, forward, sample, loss, adam, gae)


@functools.cache
def _iteration(world: GridWorld, net: tuple, hyper: Hyper, num_envs: int):
    jax = _jax()
    from jax.flatten_util import ravel_pytree

    jnp, lax = jax.numpy, jax.lax
    T, N, h = hyper.rollout, num_envs, hyper
    frames = T * N
    if frames % h.batch_size:
        raise ValueError(f"the compiled trainer needs ppo.batch_size={h.batch_size} to divide a rollout's {frames} frames (ppo.rollout x env copies)")
    minibatches = frames // h.batch_size
    P = parts(net, hyper)
    appends_direction = net[1]
    policy = jax.vmap(P.forward)  # K agents' networks, each on its own N copies

    def agents_minibatch(unravel):
        """K agents' optimiser steps on their minibatches, each agent's weights one flat vector
        (one fused pass of the clipping and Adam over all of them, not one a tensor)."""

        def agent(w, avg, sq, step, *batch):
            grad, losses = jax.grad(lambda w, *b: P.loss(unravel(w), *b), has_aux=True)(w, *batch)
            w, avg, sq, step, norm = P.adam(w, avg, sq, step, grad)
            return w, avg, sq, step, jnp.stack([*losses, norm])

        return jax.vmap(agent)

    def iteration(agents: Agents, slots: Slots, layouts: Layouts, params: Any, obs):
        """One iteration of K agents; the slots, layouts, world parameters and views are the K x N
        copies' (agent k's copies in rows k N .. k N + N - 1), stepped as one batch: the engine's
        gathers are then plain ones, where under ``vmap`` they were batched gathers, x0.3 the speed."""
        K = agents.step.shape[0]
        keys = jax.vmap(lambda k: jax.random.split(jax.random.wrap_key_data(k), 3))(agents.key)  # next, rollout, orders
        uniforms = jax.vmap(lambda k: jax.random.uniform(k, (T, N)))(keys[:, 1])
        uniforms = jnp.swapaxes(uniforms, 0, 1).reshape(T, K * N)

        def act(obs, dirs):  # dirs: the direction each view is seen in (the slots' own)
            logits, value = policy(agents.params, obs.reshape(K, N, *obs.shape[1:]), dirs.reshape(K, N))
            return logits.reshape(K * N, -1), value.reshape(K * N)

        # 1. rollout
        def env_step(carry, u):
            slots, layouts, obs = carry
            logits, value = act(obs, slots.dirs)
            action = P.sample(logits, u)
            dirs = slots.dirs if appends_direction else None  # (a network without it: nothing more in the program)
            slots, layouts, out = world.step(slots, layouts, params, action)
            done = out.terminated | out.truncated
            return (slots, layouts, out.obs), (obs, dirs, action, logits, value, out.reward, done)

        (slots, layouts, next_obs), (obs_t, dirs_t, actions, logits, values, rewards, dones) = lax.scan(env_step, (slots, layouts, obs), uniforms)
        next_value = act(next_obs, slots.dirs)[1]
        logp = jnp.take_along_axis(jax.nn.log_softmax(logits), actions[..., None], -1)[..., 0]

        # 2. GAE (each column an env copy: the agents' columns side by side)
        adv = P.gae(rewards, dones, values, next_value)

        # 3. update: each agent's epochs of minibatches, orders from its own key
        def per_agent(a):  # (T, K N, ...) -> (K T N, ...): agent k's frames in rows k F .. k F + F - 1, time-major
            a = a.reshape(T, K, N, *a.shape[2:])
            return jnp.moveaxis(a, 1, 0).reshape(K * frames, *a.shape[3:])

        x = P.inputs(obs_t.reshape(T * K * N, *obs_t.shape[2:]))  # the network's input, once
        x = x.reshape(T, K * N, *x.shape[1:])
        batch = [per_agent(a) if a is not None else None for a in (x, dirs_t, actions, logp, values, adv, values + adv)]
        orders = jax.vmap(lambda k: jax.vmap(lambda e: jax.random.permutation(e, frames))(jax.random.split(k, h.epochs)))(keys[:, 2])
        rows = orders.reshape(K, h.epochs * minibatches, h.batch_size) + (jnp.arange(K) * frames)[:, None, None]

        unravel = ravel_pytree(jax.tree_util.tree_map(lambda a: a[0], agents.params))[1]
        ravel = jax.vmap(lambda tree: ravel_pytree(tree)[0])
        step_agents = agents_minibatch(unravel)

        def minibatch(carry, idx):  # idx (K, batch_size): rows of the flat batch
            w, avg, sq, step, losses = step_agents(*carry, *(None if a is None else a[idx] for a in batch))
            return (w, avg, sq, step), losses

        start = (ravel(agents.params), ravel(agents.avg), ravel(agents.sq), agents.step)
        (w, avg, sq, step), losses = lax.scan(minibatch, start, jnp.swapaxes(rows, 0, 1))
        p, avg, sq = (jax.vmap(unravel)(a) for a in (w, avg, sq))
        means = losses.mean(0)  # (K, 4)

        # each step's rewards and episode ends, per agent (the runs' episode bookkeeping)
        rewards, dones = (jnp.moveaxis(a.reshape(T, K, N), 1, 0) for a in (rewards, dones))
        stats = IterationStats(means[:, 0], means[:, 1], means[:, 2], means[:, 3], rewards, dones)
        return Agents(p, avg, sq, step, jax.vmap(jax.random.key_data)(keys[:, 0])), slots, layouts, next_obs, stats

    return jax.jit(iteration)


class Iterated(NamedTuple):
    """What one run's loop gets from an iteration: its env copies' rewards and episode ends by step
    (``(T, N)``, as a torch rollout's, for its episode bookkeeping), and its update's mean losses."""

    rewards: np.ndarray
    dones: np.ndarray
    losses: dict[str, float]
    capacity: int  # the agents the program was compiled for (part of what reproduces the bytes)

    @property
    def num_frames(self) -> int:
        return int(self.rewards.size)


class Learner:
    """One run's compiled PPO, held by its loop in place of :class:`rlbackdoors.algos.ppo.PPO`: its
    agent's learning state (:class:`Agents` without the agent axis, numpy), its env copies (a reset
    batched engine handed to the world's JAX step, ``jax_world``: engines -> (GridWorld, params,
    HostLayouts)) and their current views. :func:`iterate` steps any number of them at once.

    The torch ``model`` is the run's network for what is not compiled (evaluations, the GIF,
    model.pt): :meth:`sync` writes the agent's weights into it."""

    def __init__(self, model: torch.nn.Module, engine, hyper: Hyper, seed: int, obs, jax_world, depth: int = 64):
        self.model, self.hyper, self.net, self.jax_world = model, hyper, network(model), jax_world
        self.state, self.depth = agent_state(model, seed), int(depth)
        self.rebind(engine, obs)

    def rebind(self, engine, obs) -> None:
        """Train on from here in other env copies (a reset engine and its observations: the
        curriculum's switch to the full world), the agent's learning state as it is."""
        self.world, self.params, self.host = self.jax_world(engine)
        self.slots, self.dict_obs = self.host.slots, isinstance(obs, dict)
        self.views = np.asarray(obs["image"] if self.dict_obs else obs, dtype=np.uint8)
        if self.views.shape != (self.host.num_envs, self.world.view_size, self.world.view_size, 3):
            raise ValueError(f"views of shape {self.views.shape} do not fit {self.host.num_envs} env copies")
        if self.dict_obs and not np.array_equal(np.asarray(obs["direction"]), self.slots.dirs):
            raise ValueError("the observations' directions are not the env copies' own")

    @property
    def obs(self):
        """The env copies' current observations, as their engine gives them (the views, with the directions where it does)."""
        if self.dict_obs:
            return {"image": self.views, "direction": np.asarray(self.slots.dirs).astype(np.int64)}
        return self.views

    @property
    def program(self) -> tuple:
        """What picks the compiled program: learners with the same key share one call."""
        return (self.world, self.net, self.hyper, self.host.num_envs)

    def sync(self) -> torch.nn.Module:
        """The torch model with the agent's current weights (returned)."""
        with torch.no_grad():
            for name, p in self.model.named_parameters():
                p.copy_(torch.from_numpy(np.array(self.state.params[name])))
        return self.model

    def checkpoint(self) -> dict:
        """The agent's learning state as plain tensors and numbers; the env copies' state goes back
        into the engine (whose ``state_dict`` a checkpoint then holds beside it)."""
        self.host.hand_back(self.slots)
        a = self.state
        tensors = {part: {n: torch.from_numpy(np.array(v)) for n, v in getattr(a, part).items()} for part in ("params", "avg", "sq")}
        return {**tensors, "step": float(a.step), "key": [int(k) for k in np.asarray(a.key)]}

    def load(self, state: dict) -> None:
        """Put back a :meth:`checkpoint` (untrusted: every array must fit the model, or StateError)."""
        from rlbackdoors.state import StateError

        names = {n: tuple(p.shape) for n, p in self.model.named_parameters()}
        parts = {}
        for part in ("params", "avg", "sq"):
            value = state[part]
            if not isinstance(value, dict) or set(value) != set(names):
                raise StateError(f"compiled learner: {part} does not have the model's parameters")
            for name, shape in names.items():
                t = value[name]
                if not isinstance(t, torch.Tensor) or tuple(t.shape) != shape or t.dtype != torch.float32 or not bool(torch.isfinite(t).all()):
                    raise StateError(f"compiled learner: {part}.{name} does not fit the model (float32, shape {shape})")
            parts[part] = {name: value[name].numpy().copy() for name in names}
        step, key = state["step"], state["key"]
        if not isinstance(step, float) or not (0 <= step < 2**24) or step != int(step):
            raise StateError("compiled learner: step is not an optimiser step count")
        if not isinstance(key, list) or len(key) != 2 or not all(isinstance(k, int) and 0 <= k < 2**32 for k in key):
            raise StateError("compiled learner: key is not a PRNG key (two 32-bit words)")
        self.state = Agents(parts["params"], parts["avg"], parts["sq"], np.float32(step), np.asarray(key, dtype=np.uint32))


def iterate(learners: list[Learner], capacity: int | None = None) -> list[Iterated]:
    """One iteration of every learner, all in one call of the compiled program: their agents side
    by side, their env copies one batch. The program is compiled for ``capacity`` agents (default:
    as many as there are); fewer are padded with copies of the first, whose results are dropped,
    so a run's numbers depend on its config and the capacity, not on its group-mates (tested)."""
    jax = _jax()
    lead, k = learners[0], len(learners)
    capacity = k if capacity is None else int(capacity)
    if capacity < k:
        raise ValueError(f"{k} learners do not fit a compiled group of {capacity}")
    if any(other.program != lead.program for other in learners[1:]):
        raise ValueError("learners of one compiled call need the same world, network, PPO settings and env copies")
    rows = learners + [lead] * (capacity - k)
    program = _iteration(*lead.program)
    agents = stack_agents([r.state for r in rows])
    slots, params, obs = join([r.slots for r in rows]), join([r.params for r in rows]), np.concatenate([r.views for r in rows])

    def block(layouts: Layouts):
        a, s, after, o, stats = program(agents, slots, layouts, params, obs)
        return (a, s, o), after, stats

    ((a, s, o), stats), depth = run_hosts([r.host for r in rows], block, max(r.depth for r in learners), takers=k)
    a, s, o, stats = jax.device_get((a, s, o, stats))
    n, out = lead.host.num_envs, []
    for i, learner in enumerate(learners):
        learner.state = agent_row(a, i)
        learner.slots = jax.tree_util.tree_map(lambda f, i=i: f[i * n : (i + 1) * n], s)
        learner.views, learner.depth = o[i * n : (i + 1) * n], depth
        losses = {key: float(getattr(stats, key)[i]) for key in STATS}
        out.append(Iterated(stats.rewards[i], stats.dones[i], losses, capacity))
    return out


__all__ = ["Agents", "Hyper", "IterationStats", "Iterated", "Learner", "agent_state", "init_agents", "iterate", "make_iteration", "state_dicts"]
