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

from rlbackdoors.algos.jax_update import _jax, run_layers, structure
from rlbackdoors.envs import grid_engine as ge
from rlbackdoors.envs.grid_jax import GridWorld, Layouts, Slots


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
    """What an iteration reports per agent: its losses (means over the minibatches) and the
    episodes its env copies ended, by kind (clean or poisoned copy) and success."""

    policy_loss: Any
    value_loss: Any
    entropy: Any
    grad_norm: Any
    episodes: Any  # (K, 2): episodes ended on clean, on poisoned copies
    successes: Any  # (K, 2): of which paid (the goal on clean copies, the trojan outcome on poisoned)
    returns: Any  # (K, 2): the sum of their returns


def init_agents(model_factory, seeds: list[int]) -> tuple[Agents, torch.nn.Module]:
    """K agents initialised as the torch trainer initialises them (``torch.manual_seed(seed)``,
    then the architecture's constructor), Adam's moments zero, each a PRNG key from its seed;
    and one model of the architecture (the structure the program runs)."""
    jax = _jax()
    models = []
    for seed in seeds:
        torch.manual_seed(seed)
        models.append(model_factory())
    structure(models[0])  # refuses what this program cannot run, in one line
    names = [name for name, _ in models[0].named_parameters()]
    params = {name: np.stack([dict(m.named_parameters())[name].detach().numpy() for m in models]).astype(np.float32) for name in names}
    zeros = {name: np.zeros_like(value) for name, value in params.items()}
    keys = np.stack([np.asarray(jax.random.key_data(jax.random.PRNGKey(seed))) for seed in seeds])
    return Agents(params, zeros, {n: z.copy() for n, z in zeros.items()}, np.zeros(len(seeds), np.float32), keys), models[0]


def state_dicts(agents: Agents) -> list[dict[str, torch.Tensor]]:
    """Each agent's weights as the torch model's state dict (the TrojAI keys, float32)."""
    params = {name: np.asarray(value) for name, value in agents.params.items()}
    k = next(iter(params.values())).shape[0]
    return [{name: torch.from_numpy(value[i].copy()) for name, value in params.items()} for i in range(k)]


def make_iteration(world: GridWorld, model: torch.nn.Module, hyper: Hyper, num_envs: int):
    """The jitted iteration of K agents: ``(agents, slots, layouts, params, obs) -> (agents, slots,
    layouts, obs, stats)``; the agents' arrays and the stats lead with the agent axis (K, ...), the
    slots', layouts', world parameters' and views' with the K x N copies' (agent by agent)."""
    return _iteration(world, structure(model), hyper, num_envs)


class Parts(NamedTuple):
    """The pieces of the iteration, each a pure JAX function (tested one by one against torch's)."""

    inputs: Any  # obs (B, 7, 7, 3) uint8 -> the network's input rows (B, 147) float32
    forward: Any  # (params, obs (B, 7, 7, 3) uint8) -> logits (B, A), values (B,)
    sample: Any  # (logits, u (B,)) -> actions (B,) int32, inverse CDF as ppo.sample_actions
    loss: Any  # (params, inputs, actions, old_logp, old_values, adv, returns) -> loss, (policy, value, entropy)
    adam: Any  # (params, avg, sq, step, grad) -> params, avg, sq, step, grad norm
    gae: Any  # (rewards, dones, values (T, N), next_value (N,)) -> advantages (T, N)


@functools.cache
def parts(layers: tuple, hyper: Hyper) -> Parts:
    """:class:`Parts` for a network :func:`rlbackdoors.algos.jax_update.structure` and ``hyper``."""
    jax = _jax()
    jnp, lax = jax.numpy, jax.lax
    h = hyper
    run = run_layers  # full fp32 products, as torch's

    def inputs(obs):
        """Raw (B, 7, 7, 3) uint8 views as a feed-forward grid model reads them: channels first, flattened, float."""
        return jnp.transpose(obs, (0, 3, 1, 2)).reshape(obs.shape[0], -1).astype(jnp.float32)

    def heads(p: dict, x):
        e = run(layers[0], p, x)
        return run(layers[1], p, e), run(layers[2], p, e)[:, 0]

    def forward(p: dict, obs):
        """Logits and values of raw views."""
        return heads(p, inputs(obs))

    def sample(logits, u):
        cdf = jnp.cumsum(jax.nn.softmax(logits, -1), -1)
        return jnp.minimum((cdf <= u[:, None] * cdf[:, -1:]).sum(1), logits.shape[1] - 1).astype(jnp.int32)

    def loss(p, x, actions, old_logp, old_values, adv, returns):
        """torch-ac's PPO loss (rlbackdoors.algos.ppo.ppo_loss) on :func:`inputs` rows ``x``."""
        logits, values = heads(p, x)
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
def _iteration(world: GridWorld, layers: tuple, hyper: Hyper, num_envs: int):
    jax = _jax()
    from jax.flatten_util import ravel_pytree

    jnp, lax = jax.numpy, jax.lax
    T, N, h = hyper.rollout, num_envs, hyper
    frames = T * N
    if frames % h.batch_size:
        raise ValueError(f"the compiled trainer needs ppo.batch_size={h.batch_size} to divide a rollout's {frames} frames (ppo.rollout x env copies)")
    minibatches = frames // h.batch_size
    P = parts(layers, hyper)
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

        def act(obs):
            logits, value = policy(agents.params, obs.reshape(K, N, *obs.shape[1:]))
            return logits.reshape(K * N, -1), value.reshape(K * N)

        # 1. rollout
        def env_step(carry, u):
            slots, layouts, obs = carry
            logits, value = act(obs)
            action = P.sample(logits, u)
            slots, layouts, out = world.step(slots, layouts, params, action)
            done = out.terminated | out.truncated
            return (slots, layouts, out.obs), (obs, action, logits, value, out.reward, done, out.outcome)

        (slots, layouts, next_obs), (obs_t, actions, logits, values, rewards, dones, outcomes) = lax.scan(env_step, (slots, layouts, obs), uniforms)
        next_value = act(next_obs)[1]
        logp = jnp.take_along_axis(jax.nn.log_softmax(logits), actions[..., None], -1)[..., 0]

        # 2. GAE (each column an env copy: the agents' columns side by side)
        adv = P.gae(rewards, dones, values, next_value)

        # 3. update: each agent's epochs of minibatches, orders from its own key
        def per_agent(a):  # (T, K N, ...) -> (K T N, ...): agent k's frames in rows k F .. k F + F - 1, time-major
            a = a.reshape(T, K, N, *a.shape[2:])
            return jnp.moveaxis(a, 1, 0).reshape(K * frames, *a.shape[3:])

        x = P.inputs(obs_t.reshape(T * K * N, *obs_t.shape[2:])).reshape(T, K * N, -1)  # the network's input, once
        batch = [per_agent(a) for a in (x, actions, logp, values, adv, values + adv)]
        orders = jax.vmap(lambda k: jax.vmap(lambda e: jax.random.permutation(e, frames))(jax.random.split(k, h.epochs)))(keys[:, 2])
        rows = orders.reshape(K, h.epochs * minibatches, h.batch_size) + (jnp.arange(K) * frames)[:, None, None]

        unravel = ravel_pytree(jax.tree_util.tree_map(lambda a: a[0], agents.params))[1]
        ravel = jax.vmap(lambda tree: ravel_pytree(tree)[0])
        step_agents = agents_minibatch(unravel)

        def minibatch(carry, idx):  # idx (K, batch_size): rows of the flat batch
            w, avg, sq, step, losses = step_agents(*carry, *(a[idx] for a in batch))
            return (w, avg, sq, step), losses

        start = (ravel(agents.params), ravel(agents.avg), ravel(agents.sq), agents.step)
        (w, avg, sq, step), losses = lax.scan(minibatch, start, jnp.swapaxes(rows, 0, 1))
        p, avg, sq = (jax.vmap(unravel)(a) for a in (w, avg, sq))
        means = losses.mean(0)  # (K, 4)

        # what the copies' episodes did (for progress lines and the training returns)
        poisoned = params.poisoned.reshape(1, K, N)
        dones, outcomes, rewards = (a.reshape(T, K, N) for a in (dones, outcomes, rewards))
        paying = jnp.where(poisoned, world.trojan, ge.OUT_GOAL)
        kinds = jnp.stack([dones & ~poisoned, dones & poisoned], -1)  # (T, K, N, 2)
        success = kinds & (outcomes == paying)[..., None]
        episode_return = jnp.where(dones, rewards, 0.0)[..., None]  # a grid episode pays only at its end
        stats = IterationStats(means[:, 0], means[:, 1], means[:, 2], means[:, 3], kinds.sum((0, 2)), success.sum((0, 2)), (kinds * episode_return).sum((0, 2)))
        return Agents(p, avg, sq, step, jax.vmap(jax.random.key_data)(keys[:, 0])), slots, layouts, next_obs, stats

    return jax.jit(iteration)


__all__ = ["Agents", "Hyper", "IterationStats", "init_agents", "make_iteration", "state_dicts"]


class Group:
    """K agents of one world, architecture and PPO config trained together by the compiled
    iteration: their env copies (reset numba engines, one per agent, each N copies) handed to the
    world's JAX step as one batch of K x N slots, their learning state, and the host's part of an
    iteration, which is drawing layouts ahead (:class:`rlbackdoors.envs.grid_jax.HostLayouts`)."""

    def __init__(self, engines: list, jax_world, model: torch.nn.Module, agents: Agents, hyper: Hyper, depth: int = 16):
        from rlbackdoors.envs.batched_base import EngineGroup

        self.k, self.n = len(engines), engines[0].num_envs
        self.world, self.params, self.host = jax_world(EngineGroup.of(engines) if len(engines) > 1 else engines[0])
        self.hyper, self.depth, self.agents = hyper, int(depth), agents
        self.slots = self.host.slots
        self.obs = np.asarray(_jax().jit(self.world.render)(self.slots, self.params))
        self._iteration = make_iteration(self.world, model, hyper, self.n)
        self.frames = 0  # per agent

    def iterate(self) -> IterationStats:
        """One iteration of every agent: rollout, GAE, update (one call of the compiled program,
        again deeper where a slot ended more episodes than it had layouts)."""

        def block(layouts: Layouts):
            agents, slots, after, obs, stats = self._iteration(self.agents, self.slots, layouts, self.params, self.obs)
            return (agents, slots, obs), after, stats

        (self.agents, self.slots, self.obs), stats = self.host.run(block, self.depth)
        self.frames += self.hyper.rollout * self.n
        return stats
