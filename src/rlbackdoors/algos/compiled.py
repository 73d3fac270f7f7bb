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

import dataclasses
import functools
import math
from dataclasses import dataclass, field
from typing import Any, Callable, NamedTuple

import numpy as np
import torch

from rlbackdoors.algos.bptt import sequence_starts
from rlbackdoors.algos.stacked import FlatParameters, StackedAdam, parameters_by_name, stacked_parameters
from rlbackdoors.algos.xla import STATS, gpu_devices, run_layers, start, structure
from rlbackdoors.envs.grid_jax import GridWorld, KindLayouts, Layouts, Slots, join, params_poisoned, run_hosts


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
    recurrence: int = 1  # truncated BPTT's steps (recurrent models)
    aux_coef: float = 0.0  # the auxiliary memory head's weight (recurrent models; 0: none)

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
            recurrence=int(ppo_cfg.recurrence),
            aux_coef=float(ppo_cfg.aux_memory_coef),
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


@dataclass(frozen=True)
class Poisoning:
    """What an attack's collection seam and the evasive variants add to the program (static: part
    of its key). ``schedule``: the seam's ("steps": it picks and stamps frames within a budget;
    "episodes": the E-bar copies are the marked frames; None: no seam); ``rule``: the poisoner's
    :meth:`~rlbackdoors.attacks.seam.Poisoner.program_key`; ``near``: how many near-trigger stamps
    (0: none); ``teacher``, ``anchor``: the fine-tuning variants' terms; ``sight``, ``near_layouts``:
    a layout trigger's (its fixed triggered copies, marked where a view shows it whole; its
    near-trigger copies, which the engine draws). The numbers (budget, c,
    near share, coefficients) are data, one per agent, so group-mates drawn with other settings
    share one program."""

    schedule: str | None
    rule: tuple
    near: int
    teacher: bool
    anchor: bool
    sight: bool = False  # a layout trigger: the marked frames are its triggered copies' views that show it whole
    near_layouts: bool = False  # near-trigger layouts the engine draws (counted, not stamped)
    switched: bool = False  # a layout trigger the step schedule's budget switches per episode: decided in the program
    poisoner: Any = field(default=None, compare=False, hash=False)  # whose rule the program calls (any with this key)


class Seam(NamedTuple):
    """A run's seam as the program carries it (a pytree). Per agent (leading axis K in a call):
    ``numbers`` (name -> float32: ``budget``, ``near``, ``compensation``, ``teacher``, ``anchor`` and
    the rule's), ``luts`` ((1 + near, 256) uint8: the trigger's table, then its near variants'),
    ``counts`` (int32, :data:`COUNTS`), ``carry`` (the rule's own state), ``teacher`` and ``anchor``
    (weights by name, or None). Per env copy (K N rows): ``near_copies`` (the clean copies that show
    near triggers under the episode schedule), ``episodes`` (a layout trigger's triggered copies) and ``before`` ((., 2) bool: did the step into the
    last frame end an episode, was the frame before it marked: what compensation reads).
    A layout trigger switched per episode by the budget (``Poisoning.switched``; None elsewhere):
    ``episodes`` then says whose current episode holds the trigger, ``in_near`` whose holds a
    near-trigger pattern, ``switchable`` which copies may be switched (per copy), ``started`` the
    triggered and near-trigger episodes started so far (per agent, (2,) int32): AttackSeam's
    ``triggered``, ``in_near``, ``switchable`` and ``started``."""

    numbers: dict
    luts: Any
    counts: Any
    carry: dict
    teacher: dict | None
    anchor: dict | None
    near_copies: Any
    before: Any
    episodes: Any  # (K N,) bool: a layout trigger's triggered copies (every episode of theirs)
    switchable: Any = None
    in_near: Any = None
    started: Any = None


KIND_SALTS = {"trigger": 0x7A1C3E559D2B4F01, "near": 0x4E3AB6C1F0925D17}  # the kinds of layouts' streams: the engine's XOR these (KindLayouts)
COUNTS = ("frames", "frames_poisoned", "rewards_rewritten", "actions_forced", "frames_near", "rewards_compensated")  # AttackSeam's counters
_ROWS = ("near_copies", "before", "episodes", "switchable", "in_near")  # Seam fields per env copy (joined row-wise); the others per agent (stacked)


def agent_state(model: torch.nn.Module, seed: int, aux: torch.nn.Module | None = None) -> Agents:
    """One agent's learning state (no agent axis): ``model``'s weights as they are (the torch
    trainer's initialisation where it was just built after ``torch.manual_seed(seed)``) and PPO's
    auxiliary memory head's (``aux``, as ``aux.*``: the algorithm's, never in model.pt), Adam's
    moments zero, a PRNG key from ``seed``."""
    jax = start()
    params = {name: p.detach().cpu().numpy().astype(np.float32).copy() for name, p in _named(model, aux).items()}
    zeros = {name: np.zeros_like(value) for name, value in params.items()}
    key = np.asarray(jax.random.key_data(jax.random.PRNGKey(seed)), dtype=np.uint32)
    return Agents(params, zeros, {n: z.copy() for n, z in zeros.items()}, np.float32(0.0), key)


def _named(model: torch.nn.Module, aux: torch.nn.Module | None) -> dict[str, torch.nn.Parameter]:
    """The parameters an agent learns, by name: the model's, then the auxiliary head's as ``aux.*``
    (:func:`rlbackdoors.algos.stacked.parameters_by_name`'s names)."""
    return {**dict(model.named_parameters()), **({f"aux.{n}": p for n, p in aux.named_parameters()} if aux is not None else {})}


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
    params = {name: np.asarray(value) for name, value in agents.params.items() if not name.startswith("aux.")}
    k = next(iter(params.values())).shape[0]
    return [{name: torch.from_numpy(value[i].copy()) for name, value in params.items()} for i in range(k)]


def network(model: torch.nn.Module) -> tuple:
    """The network as the program runs it (static data, part of the program's key): its layers
    (:func:`rlbackdoors.algos.xla.structure`) and whether its heads read the agent's
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
    terms: Any  # (logits, values, actions, old_logp, old_values, adv, returns[, weight]) -> loss, (policy, value, entropy), log-probabilities


@functools.cache
def parts(net: tuple | None, hyper: Hyper) -> Parts:
    """:class:`Parts` for a :func:`network` and ``hyper`` (the directions are read where the network
    appends them); ``net`` None: only the rules that read no network (``terms``, ``adam``, ``gae``:
    what the recurrent update shares)."""
    jax = start()
    jnp, lax = jax.numpy, jax.lax
    h = hyper
    run = run_layers  # full fp32 products, as torch's
    layers, direction = net if net is not None else (((), (), ()), False)

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

    def terms(logits, values, actions, old_logp, old_values, adv, returns, weight=None):
        """torch-ac's PPO loss (rlbackdoors.algos.ppo.ppo_loss) of a minibatch's logits and values:
        the total and (policy, value, entropy); means over the rows, or (``weight``: 0 for a
        padding row) over the rows that count. Also the log-probabilities (the teacher's KL reads them)."""
        mean = (lambda a: a.mean()) if weight is None else (lambda a: (a * weight).sum() / weight.sum())  # noqa: E731
        log_probs = jax.nn.log_softmax(logits)
        entropy = mean(-(jnp.exp(log_probs) * log_probs).sum(-1))
        ratio = jnp.exp(jnp.take_along_axis(log_probs, actions[:, None], 1)[:, 0] - old_logp)
        policy_loss = -mean(jnp.minimum(ratio * adv, jnp.clip(ratio, 1 - h.clip, 1 + h.clip) * adv))
        clipped = old_values + jnp.clip(values - old_values, -h.clip, h.clip)
        value_loss = mean(jnp.maximum((values - returns) ** 2, (clipped - returns) ** 2))
        total = policy_loss - h.entropy_coef * entropy + h.value_coef * value_loss
        return total, (policy_loss, value_loss, entropy), log_probs

    def loss(p, x, d, actions, old_logp, old_values, adv, returns, teacher=None):
        """:func:`terms` on :func:`inputs` rows ``x`` (seen in directions ``d``); with ``teacher`` =
        (its log-probabilities, the frames without the trigger, the coefficient), plus the clean
        teacher's KL there (ppo.teacher_kl), its value last of the parts."""
        logits, values = heads(p, x, d)
        total, losses, log_probs = terms(logits, values, actions, old_logp, old_values, adv, returns)
        policy_loss, value_loss, entropy = losses
        if teacher is None:
            return total, (policy_loss, value_loss, entropy)
        teacher_logp, untriggered, coef = teacher
        weight = untriggered.astype(jnp.float32)
        kl = ((jnp.exp(teacher_logp) * (teacher_logp - log_probs)).sum(-1) * weight).sum() / jnp.maximum(weight.sum(), 1.0)
        return total + coef * kl, (policy_loss, value_loss, entropy, kl)

    beta1, beta2 = h.betas

    def adam(p, avg, sq, step, grad, lr=None):
        """One optimiser step: clipping by the whole gradient's norm (clip_grad_norm_), then torch's
        Adam (at ``lr``, an agent's own rate where the caller hands one, else ``hyper.lr``)."""
        norm = jnp.sqrt(sum(jnp.sum(g * g) for g in jax.tree_util.tree_leaves(grad)))
        scale = jnp.minimum(h.max_grad_norm / (norm + 1e-6), 1.0)
        grad = jax.tree_util.tree_map(lambda g: g * scale, grad)
        step = step + 1
        avg = jax.tree_util.tree_map(lambda m, g: m + (1 - beta1) * (g - m), avg, grad)
        sq = jax.tree_util.tree_map(lambda v, g: beta2 * v + (1 - beta2) * g * g, sq, grad)
        lr_t = (h.lr if lr is None else lr) / (1 - beta1**step)
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

    return Parts(inputs, forward, sample, loss, adam, gae, terms)


def agents_step(P: Parts, unravel: Callable, teacher: bool = False) -> Callable:
    """K agents' optimiser steps on their minibatches, ``(w, avg, sq, step, lr, anchor, coefs,
    *batch)`` each with a leading agent axis: each agent's weights one flat vector (``unravel``
    gives them their names; one fused pass of the clipping and Adam over all of them, not one a
    tensor), at its own rate ``lr`` (None: ``hyper.lr``); with an anchor, each weight pulled that
    share of the way back to it after the step (ppo.pull_to_anchor); with ``teacher``, the batch
    ends with the teacher's log-probabilities and the untriggered mask. Returns the stepped state
    and the losses (policy, value, entropy, gradient norm, then the teacher's KL)."""
    jax = start()
    jnp = jax.numpy

    def agent(w, avg, sq, step, lr, anchor, coefs, *batch):
        if teacher:
            *batch, teacher_logp, untriggered = batch
            loss = lambda w, *b: P.loss(unravel(w), *b, teacher=(teacher_logp, untriggered, coefs["teacher"]))  # noqa: E731
        else:
            loss = lambda w, *b: P.loss(unravel(w), *b)  # noqa: E731
        grad, losses = jax.grad(loss, has_aux=True)(w, *batch)
        w, avg, sq, step, norm = P.adam(w, avg, sq, step, grad, lr)
        if anchor is not None:
            w = w + coefs["anchor"] * (anchor - w)
        return w, avg, sq, step, jnp.stack([*losses[:3], norm, *losses[3:]])

    return jax.vmap(agent)


@functools.cache
def _iteration(world: GridWorld, net: tuple, hyper: Hyper, num_envs: int, poisoning: Poisoning | None = None):
    jax = start()
    from jax.flatten_util import ravel_pytree

    jnp, lax = jax.numpy, jax.lax
    T, N, h = hyper.rollout, num_envs, hyper
    frames = T * N
    if frames % h.batch_size:
        raise ValueError(f"the compiled trainer needs ppo.batch_size={h.batch_size} to divide a rollout's {frames} frames (ppo.rollout x env copies)")
    minibatches = frames // h.batch_size
    z = poisoning
    teacher = z is not None and z.teacher
    recurrent = is_recurrent(net)
    P = parts(None if recurrent else net, hyper)
    appends_direction = not recurrent and net[1]
    aux = recurrent and h.aux_coef > 0
    if recurrent:  # a CNN-GRU: the memory goes into each forward with the view and comes out after it
        from rlbackdoors.algos.xla import recurrent_forward

        if z is not None and z.poisoner.needs_values:
            raise ValueError("the compiled trainer's recurrent agents have no value-guided attack (the critic's value of a frame needs the episode's memory)")
        if aux and world.memory_targets is None:
            raise ValueError("ppo.aux_memory_coef needs a world whose JAX step says what each episode must remember (GridWorld.memory_targets)")
        policy = jax.vmap(lambda p, o, d, m: recurrent_forward(net, p, o, m))  # K agents' networks, each on its own N copies
        per_batch = max(h.batch_size // h.recurrence, 1)
        epochs = [sequence_starts(T, N, h.recurrence, shifted=e % 2 == 1) for e in range(h.epochs)]
    else:
        policy = jax.vmap(lambda p, o, d, m: (*P.forward(p, o, d), None))

    def iteration(agents: Agents, slots: Slots, layouts: Layouts, params: Any, obs, seam: Any = None, memory: Any = None):
        """One iteration of K agents; the slots, layouts, world parameters and views are the K x N
        copies' (agent k's copies in rows k N .. k N + N - 1), stepped as one batch: the engine's
        gathers are then plain ones, where under ``vmap`` they were batched gathers, x0.3 the speed.
        ``seam``: the runs' attack seam and evasive variants (:class:`Seam`, as ``poisoning`` shapes
        it); ``memory``: a recurrent network's, of the running episodes: ``(own, teacher's)``, each
        (K N, M), the clean teacher's None without one."""
        K = agents.step.shape[0]
        keys = jax.vmap(lambda k: jax.random.split(jax.random.wrap_key_data(k), 3))(agents.key)  # next, rollout, orders
        uniforms = jax.vmap(lambda k: jax.random.uniform(k, (T, N)))(keys[:, 1])
        uniforms = jnp.swapaxes(uniforms, 0, 1).reshape(T, K * N)

        def act(obs, dirs, memory=None):  # dirs: the direction each view is seen in (the slots' own)
            logits, value, after = policy(
                agents.params, obs.reshape(K, N, *obs.shape[1:]), dirs.reshape(K, N), None if memory is None else memory.reshape(K, N, -1)
            )
            return logits.reshape(K * N, -1), value.reshape(K * N), None if after is None else after.reshape(K * N, -1)

        def forget(after, done):  # a new episode starts with an empty memory
            return None if after is None else jnp.where(done[:, None], 0.0, after)

        if z is None:
            xs, state = uniforms, None
        else:  # the seam's own draws, from a key folded off the rollout's (the policy's uniforms stay as without)
            picks = jax.vmap(lambda k: jax.random.uniform(jax.random.fold_in(k, 0x5EA3), (T, N, 3)))(keys[:, 1])
            xs = (uniforms, jnp.swapaxes(picks, 0, 1).reshape(T, K * N, 3))
            values0 = act(obs, slots.dirs)[1] if z.poisoner.needs_values else jnp.zeros(K * N)
            switch = (seam.episodes, seam.in_near, seam.started) if z.switched else None
            state = (seam.counts, seam.before, seam.carry, values0, switch)
            rows = functools.partial(jnp.repeat, repeats=N, axis=0)  # (K, ...) per agent -> (K N, ...) per env copy

        # 1. rollout (with a seam: its marks, stamps, forced actions and R-bar around the engine's step)
        def env_step(carry, x):
            slots, layouts, obs, state, memories = carry
            memory, guide_memory = memories if recurrent else (None, None)
            u, seen, marked = x, obs, None
            kept = (memory, world.memory_targets(world, slots) if aux else None)  # the memory into the step, what the episode asks to remember
            if z is not None:
                u, picks = x
                marked, near, state = mark(state, picks, params, slots, obs)
                seen = stamp(obs, marked, near, picks)
            logits, value, after = act(seen, slots.dirs, memory)
            action = P.sample(logits, u)
            dirs = slots.dirs if appends_direction else None  # (a network without it: nothing more in the program)
            if z is None:
                slots, layouts, out = world.step(slots, layouts, params, action)
                done = out.terminated | out.truncated
                return (slots, layouts, out.obs, state, remembered(after, None, done)), (obs, dirs, action, logits, value, out.reward, done, *kept)
            forced = jnp.zeros_like(marked)
            if z.poisoner.forces_actions:
                executed = jnp.where(marked, rows(seam.numbers["target"]).astype(jnp.int32), action)
                forced, action = marked & (executed != action), executed
            if z.switched:  # what each slot's next episode holds, decided as the seam decides it before a step
                upcoming, nearing = switches(state)
                kind = jnp.where(upcoming, 1, jnp.where(nearing, 2, 0)).astype(jnp.int32)  # the layouts' queues: clean, trigger, near
                slots, layouts, out = world.step(slots, layouts, params, action, kind)
            else:
                slots, layouts, out = world.step(slots, layouts, params, action)
            done = out.terminated | out.truncated
            if z.switched:
                state = switched(state, done, upcoming, nearing)
            next_values = act(out.obs, slots.dirs)[1] if z.poisoner.needs_values else state[3]
            reward, amend, state = rewrite(state, out.reward, action, marked, forced, next_values, done)
            guide, guided = None, None
            if teacher:  # the clean teacher on the frames as the learner saw them (a recurrent one from its own memory)
                guide, _, guided = policy(
                    seam.teacher,
                    seen.reshape(K, N, *seen.shape[1:]),
                    slots.dirs.reshape(K, N),
                    None if guide_memory is None else guide_memory.reshape(K, N, -1),
                )
                guide, guided = guide.reshape(K * N, -1), None if guided is None else guided.reshape(K * N, -1)
            return (slots, layouts, out.obs, state, remembered(after, guided, done)), (
                seen,
                dirs,
                action,
                logits,
                value,
                reward,
                done,
                *kept,
                forced,
                amend,
                marked,
                guide,
            )

        def remembered(after, guided, done):  # what the carry holds next (None: a feed-forward network)
            return (forget(after, done), forget(guided, done)) if recurrent else None

        def mark(state, picks, params, slots, obs):
            """The frames about to be acted on that carry the trigger, and those that get a near one
            (AttackSeam._mark and _stamp_near: a budgeted random pick among the eligible under the
            step schedule, the E-bar copies under the episode one), counted."""
            counts, before, carry, values, switch = state
            counted = counts[:, 0] + N
            if z.switched:  # a layout trigger: the frames of triggered episodes that show it whole
                marked = (switch[0] & world.sight(world, slots, obs)).reshape(K, N)
            elif z.schedule == "steps":
                if z.poisoner.needs_values:
                    carry, eligible = jax.vmap(lambda p, c, v: z.poisoner.select(p, c, v, N))(seam.numbers, carry, values.reshape(K, N))
                else:
                    eligible = jnp.ones((K, N), dtype=bool)
                allowance = jnp.floor(seam.numbers["budget"] * counted.astype(jnp.float32)).astype(jnp.int32) - counts[:, 1]
                marked = pick(eligible, picks[:, 0].reshape(K, N), allowance)
            elif z.schedule == "episodes" and z.sight:  # a layout trigger: its copies' frames that show it whole
                marked = (seam.episodes & world.sight(world, slots, obs)).reshape(K, N)
            elif z.schedule == "episodes":
                marked = params_poisoned(params).reshape(K, N)
            else:
                marked = jnp.zeros((K, N), dtype=bool)
            poisoned = counts[:, 1] + marked.sum(1)
            near = jnp.zeros((K, N), dtype=bool)
            if z.near and z.schedule == "steps":
                allowance = jnp.floor(seam.numbers["near"] * poisoned.astype(jnp.float32)).astype(jnp.int32) - counts[:, 4]
                near = pick(~marked, picks[:, 1].reshape(K, N), allowance)
            elif z.near_layouts:  # every frame of the near-trigger episodes (those the trigger's are not)
                near = (switch[1] if z.switched else seam.near_copies & ~seam.episodes).reshape(K, N)
            elif z.near:
                near = seam.near_copies.reshape(K, N) & ~marked
            counts = counts.at[:, 0].set(counted).at[:, 1].set(poisoned).at[:, 4].add(near.sum(1))
            return marked.reshape(-1), near.reshape(-1), (counts, before, carry, values, switch)

        def switches(state):
            """The slots whose next episode, if they reset at this step, holds the trigger, and
            those whose holds a near-trigger pattern (AttackSeam._next_episodes, _near_episodes):
            the trigger while the budget has frames to spend and fewer episodes hold it than its
            share of the copies; a near pattern while fewer near episodes started than ``near``
            times the triggered ones."""
            counts, _, _, _, (episodes, _, started) = state
            numbers = seam.numbers
            room = numbers["room"].astype(jnp.int32) - episodes.reshape(K, N).sum(1)
            spend = (numbers["budget"] * counts[:, 0].astype(jnp.float32) - counts[:, 1].astype(jnp.float32) > 0) & (room > 0)
            upcoming = seam.switchable & ~episodes & rows(spend)
            nearing = jnp.zeros_like(upcoming)
            if z.near_layouts:
                nearing = seam.switchable & ~upcoming & rows(started[:, 1].astype(jnp.float32) < numbers["near"] * started[:, 0].astype(jnp.float32))
            return upcoming, nearing

        def switched(state, done, upcoming, nearing):
            """The switches taken by the slots that reset (AttackSeam.finish): their new episodes' flags, counted."""
            counts, before, carry, values, (episodes, in_near, started) = state
            per = lambda a: a.reshape(K, N).sum(1)  # noqa: E731
            starts_near = done & nearing & ~upcoming
            started = started.at[:, 1].add(per(starts_near)).at[:, 0].add(per(done & upcoming))
            switch = (jnp.where(done, upcoming, episodes), jnp.where(done, starts_near, in_near), started)
            return counts, before, carry, values, switch

        def pick(candidates, u, allowance):
            """Per agent, ``min(allowance, candidates)`` of its candidates at random: those whose
            random key ranks below the allowance among the candidates' (the rank by N x N
            comparisons, ties to the lower index)."""
            key = jnp.where(candidates, u, 2.0)
            first = jnp.arange(N)[None, :, None] > jnp.arange(N)[None, None, :]  # [i, j]: j comes before i on a tie
            below = (key[:, None, :] < key[:, :, None]) | ((key[:, None, :] == key[:, :, None]) & first)
            rank = (below & candidates[:, None, :]).sum(2)
            return candidates & (rank < allowance[:, None])

        def stamp(obs, marked, near, picks):
            """The trigger's table on marked frames (where the seam stamps them), a near variant's,
            drawn per frame, on near ones (the world's observation edit, one lookup a byte)."""
            if z.sight or (z.schedule != "steps" and not z.near):  # (a layout trigger is in the layout, not stamped)
                return obs
            on = (marked if z.schedule == "steps" else jnp.zeros_like(marked)) | near
            which = jnp.where(marked, 0, 1 + jnp.minimum((picks[:, 2] * max(z.near, 1)).astype(jnp.int32), max(z.near, 1) - 1))
            tables = jnp.arange(K * N) // N * (1 + z.near) + which  # each frame's table among all of them, flat
            b = obs.shape[0]
            flat = (tables[:, None] * 256 + obs.reshape(b, -1).astype(jnp.int32)).reshape(obs.shape)
            return jnp.where(on[:, None, None, None], seam.luts.reshape(-1)[flat], obs)  # (one gather from all the tables)

        def rewrite(state, reward, action, marked, forced, next_values, done):
            """R-bar of the marked frames by the attack's rule, the compensation of the step before
            where it compensates (added to that step's reward after the rollout), counted."""
            counts, before, carry, _, switch = state
            numbers = {k: rows(v) for k, v in seam.numbers.items()}
            hits = action == numbers["target"].astype(jnp.int32) if "target" in numbers else None
            poisoned = z.poisoner.rule(jnp, numbers, hits, reward, next_values, done).astype(jnp.float32)
            rewritten = jnp.where(marked, poisoned, reward)
            amend = jnp.zeros_like(reward)
            if z.poisoner.compensation > 0:
                due = marked & ~before[:, 0] & ~before[:, 1]
                amend = jnp.where(due, numbers["compensation"] * (reward - poisoned), 0.0)
                counts = counts.at[:, 5].add(due.reshape(K, N).sum(1))
                before = jnp.stack([done, marked], axis=1)
            per = lambda a: a.reshape(K, N).sum(1)  # noqa: E731
            counts = counts.at[:, 3].add(per(forced))
            if z.poisoner.rewrites_rewards:
                counts = counts.at[:, 2].add(per(marked))
            return rewritten, amend, (counts, before, carry, next_values, switch)

        (slots, layouts, next_obs, state, memory), collected = lax.scan(env_step, (slots, layouts, obs, state, memory), xs)
        obs_t, dirs_t, actions, logits, values, rewards, dones, memories, targets = collected[:9]
        next_value = act(next_obs, slots.dirs, memory[0] if recurrent else None)[1]
        logp = jnp.take_along_axis(jax.nn.log_softmax(logits), actions[..., None], -1)[..., 0]
        guides: tuple = ()
        if z is not None:
            forced, amend, marked, guide = collected[9:]
            logp = jnp.where(forced, 0.0, logp)  # a forced action was taken with probability 1 (ppo.behaviour_logprobs)
            rewards = rewards.at[:-1].add(amend[1:])  # the step before a poisoned one (at t = 0 it was learned from already)
            if teacher:
                guides = (jax.nn.log_softmax(guide), ~marked)

        # 2. GAE (each column an env copy: the agents' columns side by side)
        adv = P.gae(rewards, dones, values, next_value)

        # 3. update: each agent's epochs of minibatches, orders from its own key
        def per_agent(a):  # (T, K N, ...) -> (K T N, ...): agent k's frames in rows k F .. k F + F - 1, time-major
            a = a.reshape(T, K, N, *a.shape[2:])
            return jnp.moveaxis(a, 1, 0).reshape(K * frames, *a.shape[3:])

        unravel = ravel_pytree(jax.tree_util.tree_map(lambda a: a[0], agents.params))[1]
        ravel = jax.vmap(lambda tree: ravel_pytree(tree)[0])
        anchor = ravel(seam.anchor) if z is not None and z.anchor else None
        coefs = {k: seam.numbers[k] for k in ("teacher", "anchor")} if z is not None else {}
        if recurrent and anchor is not None:  # the auxiliary head is the algorithm's, never anchored (ppo.set_anchor): its rows held where they are
            anchor = ravel({n: seam.anchor[n] if n in seam.anchor else jnp.zeros_like(v) for n, v in agents.params.items()})
            coefs["held"] = ravel({n: jnp.full_like(v, n in seam.anchor) for n, v in agents.params.items()})
        start = (ravel(agents.params), ravel(agents.avg), ravel(agents.sq), agents.step)
        if recurrent:  # truncated BPTT from the stored memories (an episode's first step masked)
            masks = jnp.concatenate([jnp.ones((1, K * N)), 1.0 - dones[:-1].astype(jnp.float32)])
            seq_orders = sequence_orders(jax.vmap(lambda k: jax.random.split(k, h.epochs))(keys[:, 2]))
            data = (obs_t, masks, actions, logp, values, adv, values + adv, targets if aux else jnp.zeros_like(actions))
            w, avg, sq, step, means = recurrent_update(net, unravel, h, N, hoisted=True)(
                *start,
                None,
                per_agent(memories).reshape(K, frames, -1),
                seq_orders,
                *(per_agent(a).reshape(K, frames, *a.shape[2:]) for a in data),
                anchor=anchor,
                coefs=coefs,
                teacher=tuple(per_agent(a).reshape(K, frames, *a.shape[2:]) for a in guides) if teacher else None,
            )
            more = {"aux_memory_loss": means[:, 4]} if aux else {}
            if teacher:
                more["teacher_kl"] = means[:, 5 if aux else 4]
        else:
            x = P.inputs(obs_t.reshape(T * K * N, *obs_t.shape[2:]))  # the network's input, once
            x = x.reshape(T, K * N, *x.shape[1:])
            batch = [per_agent(a) if a is not None else None for a in (x, dirs_t, actions, logp, values, adv, values + adv, *guides)]
            orders = jax.vmap(lambda k: jax.vmap(lambda e: jax.random.permutation(e, frames))(jax.random.split(k, h.epochs)))(keys[:, 2])
            rows_of = orders.reshape(K, h.epochs * minibatches, h.batch_size) + (jnp.arange(K) * frames)[:, None, None]
            step_agents = agents_step(P, unravel, teacher)

            def minibatch(carry, idx):  # idx (K, batch_size): rows of the flat batch
                w, avg, sq, step, losses = step_agents(*carry, None, anchor, coefs, *(None if a is None else a[idx] for a in batch))
                return (w, avg, sq, step), losses

            (w, avg, sq, step), losses = lax.scan(minibatch, start, jnp.swapaxes(rows_of, 0, 1))
            means = losses.mean(0)  # (K, 4 + the teacher's KL)
            more = {"teacher_kl": means[:, 4]} if teacher else {}
        p, avg, sq = (jax.vmap(unravel)(a) for a in (w, avg, sq))
        if anchor is not None:  # ||weights - anchor|| after the update (ppo.anchor_distance: the model's)
            more["anchor_distance"] = jnp.sqrt((((w - anchor) * coefs["held"] if recurrent else w - anchor) ** 2).sum(1))

        # each step's rewards and episode ends, per agent (the runs' episode bookkeeping)
        rewards, dones = (jnp.moveaxis(a.reshape(T, K, N), 1, 0) for a in (rewards, dones))
        stats = IterationStats(means[:, 0], means[:, 1], means[:, 2], means[:, 3], rewards, dones)
        agents = Agents(p, avg, sq, step, jax.vmap(jax.random.key_data)(keys[:, 0]))
        if z is not None:
            seam = seam._replace(counts=state[0], before=state[1], carry=state[2])
            if z.switched:
                seam = seam._replace(episodes=state[4][0], in_near=state[4][1], started=state[4][2])
        if recurrent:
            return agents, slots, layouts, next_obs, stats, seam, more, memory
        if z is None:
            return agents, slots, layouts, next_obs, stats
        return agents, slots, layouts, next_obs, stats, seam, more

    def sequence_orders(keys):
        """Each epoch's truncated-BPTT sequence starts (:func:`sequence_starts`, shifted on odd
        epochs) permuted by each agent's key for that epoch (``keys`` (K, epochs)), cut into
        minibatches of ``batch_size // recurrence`` sequences, the last one padded with -1: per
        epoch (minibatches, K, sequences), as :func:`recurrent_update` reads them."""
        out = []
        for e, starts in enumerate(epochs):
            batches = -(-len(starts) // per_batch)

            def order(k, starts=starts, batches=batches):
                drawn = jnp.asarray(starts, jnp.int32)[jax.random.permutation(k, len(starts))]
                return jnp.concatenate([drawn, jnp.full(batches * per_batch - len(starts), -1, jnp.int32)]).reshape(batches, per_batch)

            out.append(jnp.swapaxes(jax.vmap(order)(keys[:, e]), 0, 1))
        return tuple(out)

    return jax.jit(iteration)


def is_recurrent(net: tuple) -> bool:
    """A network as :func:`~rlbackdoors.algos.xla.recurrent_structure` reads it (parts, GRU stack,
    one-hot planes), not as :func:`network` does (layers, direction)."""
    return len(net) == 3


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

    def __init__(self, model: torch.nn.Module, engine, hyper: Hyper, seed: int, obs, jax_world, depth: int = 64, aux: torch.nn.Module | None = None):
        from rlbackdoors.algos.xla import recurrent_structure

        self.recurrent = bool(getattr(model, "recurrent", False))  # a CNN-GRU: its memories go in and out with the views
        if (aux is not None) != (self.recurrent and hyper.aux_coef > 0):
            raise ValueError("an auxiliary memory head goes with a recurrent model and ppo.aux_memory_coef > 0")
        self.model, self.aux, self.hyper, self.jax_world = model, aux, hyper, jax_world
        self.net = recurrent_structure(model) if self.recurrent else network(model)
        self.state, self.depth = agent_state(model, seed, aux), int(depth)
        self.guides: dict[str, tuple[dict, float]] = {}  # "teacher" / "anchor" -> (weights by name, coefficient)
        self.teacher_memory: np.ndarray | None = None  # a recurrent clean teacher's memories of the running episodes
        self.rebind(engine, obs)

    def rebind(self, engine, obs) -> None:
        """Train on from here in other env copies (a reset engine and its observations: the
        curriculum's switch to the full world, or a fine-tuning run's to the poisoning mix), the
        agent's learning state as it is. ``engine`` may be an attack's collection seam
        (:class:`~rlbackdoors.attacks.seam.AttackSeam`) around the engine: the program then does
        what it asks, from the counters it holds, and writes them back after each iteration.
        ``obs`` are the engine's own (clean) observations, not the seam's."""
        from rlbackdoors.attacks.seam import AttackSeam

        self.seam = engine if isinstance(engine, AttackSeam) else None
        self.world, self.params, self.host = self.jax_world(engine.envs if self.seam is not None else engine)
        self.kinds: tuple = ()  # the queues of triggered and near-trigger layouts, where the program switches them
        if self.seam is not None and self.seam.sight is not None and self.seam.fixed is None:
            self.kinds = tuple(KindLayouts(self.host, kind, salt) for kind, salt in KIND_SALTS.items() if kind == "trigger" or self.seam.near_layout)
        self.slots, self.dict_obs = self.host.slots, isinstance(obs, dict)
        self.views = np.asarray(obs["image"] if self.dict_obs else obs, dtype=np.uint8)
        if self.views.shape != (self.host.num_envs, self.world.view_size, self.world.view_size, 3):
            raise ValueError(f"views of shape {self.views.shape} do not fit {self.host.num_envs} env copies")
        if self.dict_obs and not np.array_equal(np.asarray(obs["direction"]), self.slots.dirs):
            raise ValueError("the observations' directions are not the env copies' own")
        if self.recurrent:  # new copies start new episodes: empty memories (ppo.memory = None)
            self.memory = self._empty()
        self._poison()

    def _empty(self) -> np.ndarray:
        return np.zeros((self.host.num_envs, int(getattr(self.model, "memory_size"))), dtype=np.float32)

    def set_teacher(self, weights: dict, coef: float) -> None:
        """``poison.evasion.teacher``: ``coef * KL(teacher || policy)`` on the frames without the
        trigger, the teacher ``weights`` (a state dict of this network) frozen (ppo.PPO.set_teacher)."""
        self._guide("teacher", weights, coef)

    def set_anchor(self, weights: dict, coef: float) -> None:
        """``poison.evasion.anchor``: each weight pulled ``coef`` of the way back to ``weights`` after every optimiser step."""
        self._guide("anchor", weights, coef)

    def _guide(self, name: str, weights: dict, coef: float) -> None:
        names = [n for n, _ in self.model.named_parameters()]
        self.guides[name] = ({n: np.asarray(weights[n].detach().cpu().numpy(), dtype=np.float32).copy() for n in names}, float(coef))
        if name == "teacher" and self.recurrent:  # a new teacher starts with empty memories (ppo.set_teacher)
            self.teacher_memory = self._empty()
        self._poison()

    def _poison(self) -> None:
        """:class:`Poisoning` and this agent's :class:`Seam` from the seam and the guides (None: neither)."""
        from rlbackdoors.attacks.seam import Poisoner

        seam, n = self.seam, self.host.num_envs
        if seam is None and not self.guides:
            self.poisoning, self.seam_state = None, None
            return
        if self.recurrent and seam is not None and seam.poisoner.needs_values:
            raise ValueError("the compiled trainer's recurrent agents have no value-guided attack (the critic's value of a frame needs the episode's memory)")
        if seam is not None and seam.sight not in (None, "frame"):
            raise ValueError(f"the compiled trainer marks a layout trigger's frames in sight of it, not sight={seam.sight!r}")
        if seam is not None and seam.sight is not None and self.world.sight is None:
            raise ValueError("this world's JAX step does not say which views show the trigger (GridWorld.sight)")
        if "teacher" in self.guides and seam is None:
            raise ValueError("a clean teacher needs the attack's collection seam to say which frames carry the trigger (marked)")
        poisoner = seam.poisoner if seam is not None else Poisoner()
        near_layouts = seam is not None and seam.near_layout
        near = len(seam.near_stamps) if seam is not None and seam.near > 0 and not near_layouts else 0
        schedule = None if seam is None else seam.schedule
        switched = bool(self.kinds)
        trigger = (
            _table(seam.stamp) if seam is not None and seam.stamp is not None and schedule == "steps" else np.arange(256, dtype=np.uint8)
        )  # (the engine's copies show theirs)
        luts = np.stack([trigger, *(_table(f) for f in seam.near_stamps)] if near and seam is not None else [trigger])
        numbers = {
            "budget": seam.budget if seam is not None else 0.0,
            "near": seam.near if seam is not None else 0.0,
            "compensation": poisoner.compensation,
            **{k: float(v) for k, v in poisoner.numbers().items()},
            **{k: self.guides[k][1] if k in self.guides else 0.0 for k in ("teacher", "anchor")},
            **(
                {"room": max(1, math.ceil(seam.budget * n))} if switched and seam is not None else {}
            ),  # the triggered episodes at once (AttackSeam._next_episodes)
        }
        counts = [getattr(seam, c) if seam is not None else 0 for c in COUNTS]
        sight = seam is not None and seam.sight is not None
        self.poisoning = Poisoning(
            schedule, poisoner.program_key(), near, "teacher" in self.guides, "anchor" in self.guides, sight, near_layouts, switched, poisoner
        )
        flags = (seam.triggered if switched else seam.fixed) if seam is not None and seam.sight is not None else None
        self.seam_state = Seam(
            numbers={k: np.float32(v) for k, v in numbers.items()},
            luts=luts,
            counts=np.asarray(counts, dtype=np.int32),
            carry=poisoner.carry(),
            teacher=self.guides["teacher"][0] if "teacher" in self.guides else None,
            anchor=self.guides["anchor"][0] if "anchor" in self.guides else None,
            near_copies=np.asarray(seam.near_copies if seam is not None else np.zeros(n, dtype=bool), dtype=bool),
            episodes=np.asarray(flags if flags is not None else np.zeros(n, dtype=bool), dtype=bool).copy(),
            before=np.asarray(seam.before.T if seam is not None else np.stack([np.ones(n, bool), np.zeros(n, bool)], 1), dtype=bool).copy(),
            **(
                {"switchable": seam.switchable.copy(), "in_near": seam.in_near.copy(), "started": np.asarray(seam.started, dtype=np.int32)}
                if switched and seam is not None
                else {}
            ),
        )

    def _seam_back(self, state: Seam) -> None:
        """The program's seam state kept, and its counters, marks and the rule's state written into
        the :class:`AttackSeam` (whose checkpoint and ``budget_used`` read them)."""
        self.seam_state = state
        seam = self.seam
        if seam is None:
            return
        for name, value in zip(COUNTS, np.asarray(state.counts)):
            setattr(seam, name, int(value))
        seam.before = np.asarray(state.before, dtype=bool).T.copy()
        seam.marked = seam.before[1].copy()  # the last frames acted on (the next ones are marked by the next iteration)
        seam.poisoner.set_carry({k: np.asarray(v) for k, v in state.carry.items()})
        if self.kinds:
            seam.triggered, seam.in_near = np.array(state.episodes, dtype=bool), np.array(state.in_near, dtype=bool)
            seam.started = [int(v) for v in np.asarray(state.started)]

    @property
    def obs(self):
        """The env copies' current observations, as their engine gives them (the views, with the directions where it does)."""
        if self.dict_obs:
            return {"image": self.views, "direction": np.asarray(self.slots.dirs).astype(np.int64)}
        return self.views

    @property
    def hosts(self):
        """The host side(s) of the env copies' layouts: one queue, or (where the program switches
        what an episode holds) a tuple of the clean, triggered and near-trigger queues."""
        return (self.host, *self.kinds) if self.kinds else self.host

    @property
    def program(self) -> tuple:
        """What picks the compiled program: learners with the same key share one call."""
        return (self.world, self.net, self.hyper, self.host.num_envs, self.poisoning)

    def sync(self) -> torch.nn.Module:
        """The torch model (and the auxiliary head) with the agent's current weights (the model returned)."""
        with torch.no_grad():
            for name, p in _named(self.model, self.aux).items():
                p.copy_(torch.from_numpy(np.array(self.state.params[name])))
        return self.model

    def checkpoint(self) -> dict:
        """The agent's learning state as plain tensors and numbers; the env copies' state goes back
        into the engine (whose ``state_dict`` a checkpoint then holds beside it)."""
        self.host.hand_back(self.slots)
        a = self.state
        tensors = {part: {n: torch.from_numpy(np.array(v)) for n, v in getattr(a, part).items()} for part in ("params", "avg", "sq")}
        streams = {"streams": [[int(v) for v in kind.rewind()] for kind in self.kinds]} if self.kinds else {}  # where each kind's next layout is drawn
        memory = {"memory": torch.from_numpy(np.array(self.memory))} if self.recurrent else {}  # the running episodes'
        if self.teacher_memory is not None:
            memory["teacher_memory"] = torch.from_numpy(np.array(self.teacher_memory))
        return {**tensors, "step": float(a.step), "key": [int(k) for k in np.asarray(a.key)], **streams, **memory}

    def load(self, state: dict) -> None:
        """Put back a :meth:`checkpoint` (untrusted: every array must fit the model, or StateError)."""
        from rlbackdoors.state import StateError

        names = {n: tuple(p.shape) for n, p in _named(self.model, self.aux).items()}
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
        if self.kinds:
            streams = state.get("streams")
            if not isinstance(streams, list) or len(streams) != len(self.kinds):
                raise StateError(f"compiled learner: streams is not {len(self.kinds)} kinds of layouts' streams")
            for kind, words in zip(self.kinds, streams):
                if not isinstance(words, list) or len(words) != self.host.num_envs or not all(isinstance(w, int) and 0 <= w < 2**64 for w in words):
                    raise StateError("compiled learner: a kind of layouts' streams are not one 64-bit word an env copy")
                kind.streams = np.asarray(words, dtype=np.uint64)
        elif "streams" in state:
            raise StateError("compiled learner: it holds layouts' streams this run does not draw")
        for name in ("memory", "teacher_memory"):  # a recurrent agent's, and its clean teacher's (set by set_teacher before a load)
            have = (self.memory if self.recurrent else None) if name == "memory" else self.teacher_memory
            if have is None:
                if name in state:
                    raise StateError(f"compiled learner: it holds {name} this run does not have")
                continue
            memory = state.get(name)
            if not isinstance(memory, torch.Tensor) or memory.shape != have.shape or memory.dtype != torch.float32 or not bool(torch.isfinite(memory).all()):
                raise StateError(f"compiled learner: {name} is not the env copies' memories (float32, shape {have.shape})")
            setattr(self, name, memory.numpy().copy())
        self.state = Agents(parts["params"], parts["avg"], parts["sq"], np.float32(step), np.asarray(key, dtype=np.uint32))


def iterate(learners: list[Learner], capacity: int | None = None) -> list[Iterated]:
    """One iteration of every learner, all in one call of the compiled program: their agents side
    by side, their env copies one batch. The program is compiled for ``capacity`` agents (default:
    as many as there are); fewer are padded with copies of the first, whose results are dropped,
    so a run's numbers depend on its config and the capacity, not on its group-mates (tested)."""
    jax = start()
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

    seam = None if lead.poisoning is None else join_seams([r.seam_state for r in rows])
    memory = None
    if lead.recurrent:  # the running episodes' memories, and a clean teacher's beside them
        guided = lead.poisoning is not None and lead.poisoning.teacher
        memory = (np.concatenate([r.memory for r in rows]), np.concatenate([r.teacher_memory for r in rows]) if guided else None)

    def block(layouts: Layouts):
        if memory is not None:
            a, s, after, o, stats, z, more, m = program(agents, slots, layouts, params, obs, seam, memory)
            return (a, s, o, z, more, m), after, stats
        if seam is None:
            a, s, after, o, stats = program(agents, slots, layouts, params, obs)
            return (a, s, o, None, {}, None), after, stats
        a, s, after, o, stats, z, more = program(agents, slots, layouts, params, obs, seam)
        return (a, s, o, z, more, None), after, stats

    ((a, s, o, z, more, m), stats), depth = run_hosts([r.hosts for r in rows], block, max(r.depth for r in learners), takers=k)
    a, s, o, z, more, m, stats = jax.device_get((a, s, o, z, more, m, stats))
    n, out = lead.host.num_envs, []
    for i, learner in enumerate(learners):
        learner.state = agent_row(a, i)
        learner.slots = jax.tree_util.tree_map(lambda f, i=i: f[i * n : (i + 1) * n], s)
        learner.views, learner.depth = o[i * n : (i + 1) * n], depth
        if learner.recurrent:
            learner.memory = np.array(m[0][i * n : (i + 1) * n])
            learner.teacher_memory = None if m[1] is None else np.array(m[1][i * n : (i + 1) * n])
        if z is not None:
            learner._seam_back(seam_row(z, i, n))
        losses = {key: float(getattr(stats, key)[i]) for key in STATS} | {key: float(v[i]) for key, v in more.items()}
        out.append(Iterated(stats.rewards[i], stats.dones[i], losses, capacity))
    return out


def _table(stamp) -> np.ndarray:
    """A frame trigger's stamp as its table of 256 bytes, checked to be one (the program stamps by lookup)."""
    table = np.asarray(stamp(np.arange(256, dtype=np.uint8)), dtype=np.uint8)
    probe = np.random.default_rng(0).integers(0, 256, size=(4, 7, 7, 3), dtype=np.uint8)
    if table.shape != (256,) or not np.array_equal(np.asarray(stamp(probe)), table[probe]):
        raise ValueError("the compiled trainer stamps a trigger that maps each byte by a table; this trigger is not one")
    return table


def join_seams(seams: list) -> Seam:
    """Several runs' seams as one call's: the per-agent fields stacked, the per-copy ones joined row-wise."""
    import jax

    def together(name, *parts):
        if parts[0] is None:
            return None
        glue = np.concatenate if name in _ROWS else np.stack
        return jax.tree_util.tree_map(lambda *a: glue(a), *parts)

    return Seam(*(together(name, *parts) for name, parts in zip(Seam._fields, zip(*seams))))


def seam_row(seam: Seam, i: int, n: int) -> Seam:
    """Run ``i``'s seam out of :func:`join_seams`' (``n`` env copies a run)."""
    import jax

    def row(name, part):
        if part is None:
            return None
        return jax.tree_util.tree_map(lambda a: np.array(a[i * n : (i + 1) * n] if name in _ROWS else a[i]), part)

    return Seam(*(row(name, part) for name, part in zip(Seam._fields, seam)))


# --- the update alone, on the torch trainer's rollouts (ppo.update_backend = "jax") -------------
#
# The torch trainer collects (its engines, its seam, its forward), and this program runs the update
# of :func:`parts` (the same loss and Adam as the iteration's) over every epoch and minibatch. The
# weights and Adam's state are read from and written back to each agent's torch model and
# ``torch.optim.Adam`` (a checkpoint resumes under either backend); the minibatch orders are drawn
# from each run's own torch generator, as torch's update draws them. XLA's kernels round
# differently at different batch widths, so a group's agents are computed in chunks of exactly
# :data:`WIDTH` (padded with copies of the chunk's first): an agent's bytes depend on its config,
# not on its group-mates or the group's size; a lone run computes at width 1 (tests/test_jax_update.py).
# On CUDA the tensors pass to JAX and back through DLPack without a copy, in chunks of :data:`CUDA_WIDTH`.

WIDTH = 8  # agents per XLA call in a CPU group
CUDA_WIDTH = 64  # ... in a CUDA group: the torch group's width there (algos.group.CUDA_WIDTH)


def check(model: Any, device: torch.device) -> None:
    """Refuse (``ValueError``, one line) what :func:`update` cannot run: a model other than
    :func:`~rlbackdoors.algos.xla.structure` reads, a device other than the CPU or CUDA, a JAX without GPU support."""
    if device.type not in ("cpu", "cuda"):
        raise ValueError(f"ppo.update_backend='jax' runs on the CPU or CUDA, not {device.type!r}")
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError("ppo.update_backend='jax' on CUDA: no CUDA device is available (train.device 'cpu')")
    if getattr(model, "recurrent", False):
        from rlbackdoors.algos.xla import recurrent_structure

        recurrent_structure(model)
        if device.type != "cpu":
            raise ValueError("ppo.update_backend='jax' runs a recurrent model's update on the CPU (train.device 'cpu'), not on CUDA yet")
        return
    structure(model)
    jax = start(gpu=device.type == "cuda")
    if device.type == "cuda" and not gpu_devices(jax):
        raise ValueError("ppo.update_backend='jax' with train.device='cuda' needs JAX with CUDA (jax[cuda]); this one has no GPU: use 'torch'")


def _placed(jax, device: torch.device):
    """Torch tensor -> JAX array on the learners' device: the CPU's XLA device for CPU tensors
    (never a GPU JAX would pick by default on a GPU machine: a CPU run's bytes are the CPU's), and
    the same GPU memory, no copy, for CUDA tensors (DLPack, after torch's queued work is done)."""
    if device.type == "cpu":
        cpu = jax.devices("cpu")[0]
        return lambda t: jax.device_put(t.numpy(), cpu)
    torch.cuda.synchronize(device)
    return lambda t: jax.dlpack.from_dlpack(t.contiguous())


def _back(array, device: torch.device) -> torch.Tensor:
    """JAX array -> torch tensor on the learners' device (a CPU copy: XLA's buffer is read-only)."""
    if device.type == "cpu":
        return torch.from_numpy(np.array(array))
    array.block_until_ready()
    return torch.from_dlpack(array)


@functools.cache
def _update_program(layers: tuple, layout: tuple, hyper: Hyper):
    """The jitted update of K agents' flat weight rows (``layout``: each name's columns and shape)."""
    jax = start()
    jnp = jax.numpy
    P = parts((layers, False), hyper)

    def unravel(row):
        return {name: row[begin:end].reshape(shape) for name, begin, end, shape in layout}

    step_agents = agents_step(P, unravel)

    def update(rows, avg, sq, step, lr, inputs, actions, old_logp, old_values, adv, returns, orders):
        """Every minibatch of the update in turn (``orders``: (minibatches, K, batch) frame indices)."""

        def minibatch(carry, idx):
            def take(a):
                return jnp.take_along_axis(a, idx.reshape(idx.shape + (1,) * (a.ndim - 2)), 1)

            rows, avg, sq, step = carry
            batch = (take(inputs), None, *(take(a) for a in (actions, old_logp, old_values, adv, returns)))  # (no directions: feed-forward views)
            rows, avg, sq, step, losses = step_agents(rows, avg, sq, step, lr, None, {}, *batch)
            return (rows, avg, sq, step), losses

        (rows, avg, sq, step), losses = jax.lax.scan(minibatch, (rows, avg, sq, step), orders)
        return rows, avg, sq, step, losses.mean(0)

    return jax.jit(update)


@functools.cache
def _recurrent_update_program(net: tuple, layout: tuple, hyper: Hyper, num_envs: int):
    """The jitted truncated-BPTT update of K recurrent agents' flat weight rows (``layout``: each
    name's columns and shape), :func:`recurrent_update` on the torch trainer's rollouts."""
    jax = start()

    def unravel(row):
        return {name: row[begin:end].reshape(shape) for name, begin, end, shape in layout}

    return jax.jit(recurrent_update(net, unravel, hyper, num_envs))


def recurrent_update(net: tuple, unravel: Callable, hyper: Hyper, num_envs: int, hoisted: bool = False) -> Callable:
    """K recurrent agents' truncated-BPTT update (the torch trainer's ``PPO._update_recurrent``),
    un-jitted: the ``jax`` backend's program and the compiled recurrent iteration's third part.
    Per minibatch, each sequence replayed from its stored memory over ``hyper.recurrence`` steps
    (the memory masked where an episode began), the loss the mean over its rows (a padding
    sequence, index -1, counts for nothing: a ragged last minibatch), the memories the network
    computes written back for later minibatches, then one clipped Adam step over the model and the
    auxiliary memory head (``hyper.aux_coef`` > 0: its cross-entropy on each step's memory)."""
    jax = start()
    jnp, lax = jax.numpy, jax.lax
    from rlbackdoors.algos.xla import recurrent_embed, recurrent_forward, recurrent_heads, recurrent_step

    P = parts(None, hyper)
    r, B, aux_coef = hyper.recurrence, num_envs, hyper.aux_coef

    def agent(w, avg, sq, step, lr, anchor, coefs, teacher, memories, idx, obs, masks, actions, old_logp, old_values, adv, returns, targets):
        valid = idx >= 0
        starts = jnp.where(valid, idx, 0)
        steps = starts[None, :] + B * jnp.arange(r)[:, None]  # (r, N): step i of each sequence
        rows = steps.reshape(-1)  # step-major, as forward_sequence's rows
        weight = jnp.tile(valid, r).astype(jnp.float32)
        frames = memories.shape[0]

        def loss(w):
            p = unravel(w)

            if hoisted:  # the embedding and the heads once on all the sequences' rows, only the GRU steps in the scan
                n = len(idx)
                emb = recurrent_embed(net, obs[rows], p).reshape(r, n, -1)

                def step(m, x):
                    e, keep = x
                    out, m = recurrent_step(net, p, e, m * keep[:, None])
                    return m, (out, m)

                _, (outs, new) = lax.scan(step, memories[starts], (emb, masks[steps]))
                logits, values, _ = recurrent_heads(net, p, outs.reshape(r * n, -1), None)
            else:

                def one(m, x):
                    o, keep = x
                    logits, values, m = recurrent_forward(net, p, o, m * keep[:, None])
                    return m, (logits, values, m)

                _, (logits, values, new) = lax.scan(one, memories[starts], (obs[steps], masks[steps]))
            total, losses, log_probs = P.terms(
                logits.reshape(r * len(idx), -1), values.reshape(-1), *(a[rows] for a in (actions, old_logp, old_values, adv, returns)), weight
            )
            if aux_coef > 0:  # each step's memory after that step names its episode's target (cross-entropy)
                aux = jax.nn.log_softmax(jnp.matmul(new.reshape(len(rows), -1), p["aux.weight"].T, precision="highest") + p["aux.bias"])
                aux_loss = -(jnp.take_along_axis(aux, targets[rows][:, None], 1)[:, 0] * weight).sum() / weight.sum()
                total, losses = total + aux_coef * aux_loss, (*losses, aux_loss)
            if teacher is not None:  # the clean teacher's KL on the rows without the trigger (ppo.teacher_kl)
                teacher_logp, untriggered = teacher
                counted = weight * untriggered[rows].astype(jnp.float32)
                kl = ((jnp.exp(teacher_logp[rows]) * (teacher_logp[rows] - log_probs)).sum(-1) * counted).sum() / jnp.maximum(counted.sum(), 1.0)
                total, losses = total + coefs["teacher"] * kl, (*losses, kl)
            return total, (losses, new)

        grad, (losses, new) = jax.grad(loss, has_aux=True)(w)
        w, avg, sq, step, norm = P.adam(w, avg, sq, step, grad, lr)
        if anchor is not None:  # the weight anchor's pull after the step (ppo.pull_to_anchor), on the model's weights alone (``coefs["held"]``)
            w = w + coefs["anchor"] * coefs["held"] * (anchor - w)
        if r > 1:  # the memories the pre-step network computed, for the minibatches after this one
            at = jnp.where(valid[None, :], steps[1:], frames).reshape(-1)
            memories = memories.at[at].set(lax.stop_gradient(new[:-1]).reshape(len(at), -1), mode="drop")
        return w, avg, sq, step, memories, jnp.stack([*losses[:3], norm, *losses[3:]])

    agents = jax.vmap(agent)

    def update(
        rows, avg, sq, step, lr, memories, orders, obs, masks, actions, old_logp, old_values, adv, returns, targets, *, anchor=None, coefs=None, teacher=None
    ):
        """Every epoch's minibatches in turn (``orders``: per epoch (minibatches, K, sequences) start indices, -1 padding)."""
        data = (obs, masks, actions, old_logp, old_values, adv, returns, targets)
        losses = []
        for epoch in orders:  # (the epochs have their own counts of sequences: torch-ac's shifted starts)

            def minibatch(carry, idx):
                rows, avg, sq, step, memories = carry
                rows, avg, sq, step, memories, parts_ = agents(rows, avg, sq, step, lr, anchor, coefs or {}, teacher, memories, idx, *data)
                return (rows, avg, sq, step, memories), parts_

            (rows, avg, sq, step, memories), part = lax.scan(minibatch, (rows, avg, sq, step, memories), epoch)
            losses.append(part)
        return rows, avg, sq, step, jnp.concatenate(losses).mean(0)

    return update


def _recurrent_orders(ppos: list, steps: int, num_envs: int, width: int, real: int) -> tuple[np.ndarray, ...]:
    """Each epoch's minibatches of BPTT sequence starts, drawn from each real agent's own generator
    as torch's recurrent update draws them (``PPO.sequence_starts``, shifted on odd epochs, then a
    permutation), a pad agent its chunk's first's: per epoch (minibatches, K, sequences), -1 padding."""
    cfg = ppos[0].cfg
    per_batch = max(cfg.batch_size // cfg.recurrence, 1)
    epochs = []
    for epoch in range(cfg.epochs):
        drawn = []
        for ppo in ppos[:real]:
            starts = ppo.sequence_starts(steps, num_envs, shifted=epoch % 2 == 1)
            drawn.append(starts[torch.randperm(len(starts), generator=ppo.generator)].numpy())
        drawn += drawn[:1] * (width - real)
        n = len(drawn[0])
        batches = -(-n // per_batch)
        padded = np.full((width, batches * per_batch), -1, dtype=np.int32)
        padded[:, :n] = np.stack(drawn)
        epochs.append(padded.reshape(width, batches, per_batch).transpose(1, 0, 2).copy())
    return tuple(epochs)


class _Chunk(NamedTuple):
    """One XLA call's agents of an update: the real ones padded to ``width`` with copies of the
    first, their stacked weights and Adam state (written back into each torch model and optimiser)."""

    ppos: list
    rollouts: list
    real: int
    weights: Any  # FlatParameters
    adam: Any  # StackedAdam
    layout: tuple  # each name's columns and shape in a flat row


def _chunks(ppos: list, rollouts: list, width: int):
    """:class:`_Chunk` s of ``width`` agents, in order."""
    for begin in range(0, len(ppos), width):
        chunk, chunk_rollouts = ppos[begin : begin + width], rollouts[begin : begin + width]
        real = len(chunk)
        chunk, chunk_rollouts = chunk + chunk[:1] * (width - real), chunk_rollouts + chunk_rollouts[:1] * (width - real)
        weights = FlatParameters(stacked_parameters(chunk))
        adam = StackedAdam([(ppo.optimizer, parameters_by_name(ppo)) for ppo in chunk], weights)
        layout = tuple((name, columns.start, columns.stop, tuple(shape[1:])) for name, (columns, shape) in weights.layout.items())
        yield _Chunk(chunk, chunk_rollouts, real, weights, adam, layout)


def _torch_hyper(lead) -> Hyper:
    """The run's PPO settings with its torch optimiser's Adam eps and betas."""
    group = lead.optimizer.param_groups[0]
    return dataclasses.replace(Hyper.of(lead.cfg), adam_eps=float(group["eps"]), betas=(float(group["betas"][0]), float(group["betas"][1])))


def _adam_inputs(put, c: _Chunk) -> tuple:
    """The chunk's weights, Adam moments, step counts and rates, on the learners' device."""
    return put(c.weights.flat), put(c.adam.exp_avg), put(c.adam.exp_avg_sq), put(c.adam.step.float()), put(c.adam.lr)


def _written_back(c: _Chunk, device, rows, avg, sq, step, losses, names) -> list[dict[str, float]]:
    """The program's weights and Adam state into the chunk's torch models and optimisers; the real agents' mean losses by ``names``."""
    with torch.no_grad():
        c.weights.flat.copy_(_back(rows, device))
        c.adam.exp_avg.copy_(_back(avg, device))
        c.adam.exp_avg_sq.copy_(_back(sq, device))
        c.adam.step.copy_(_back(step, device).double())
    c.adam.write_back(c.real)
    means = np.asarray(losses, dtype=np.float64)  # (K, losses)
    return [{key: float(means[k, i]) for i, key in enumerate(names)} for k in range(c.real)]


def _update_recurrent(ppos: list, rollouts: list, width: int) -> list[dict[str, float]]:
    """:func:`update` for recurrent models (``model.recurrent``): the torch trainer's rollouts, its
    stored memories and masks, truncated BPTT in :func:`_recurrent_update_program`."""
    from rlbackdoors.algos.xla import recurrent_structure

    lead = ppos[0]
    model, device = lead.model, lead.device
    jax = start()
    net, hyper = recurrent_structure(model), _torch_hyper(lead)
    num_envs = rollouts[0].num_envs
    steps = rollouts[0].num_frames // num_envs
    aux = lead.aux is not None
    names = ("policy_loss", "value_loss", "entropy", "grad_norm", *(("aux_memory_loss",) if aux else ()))
    out: list[dict[str, float]] = []
    for c in _chunks(ppos, rollouts, width):
        chunk_rollouts = c.rollouts
        orders = _recurrent_orders(c.ppos, steps, num_envs, width, c.real)
        obs = torch.stack([r.obs for r in chunk_rollouts])
        if not isinstance(obs, torch.Tensor) or obs.dtype != torch.uint8:
            raise ValueError("ppo.update_backend='jax' runs recurrent models on raw uint8 views")
        targets = [r.memory_targets if aux else torch.zeros(r.num_frames, dtype=torch.int64) for r in chunk_rollouts]
        columns = [torch.stack([getattr(r, f) for r in chunk_rollouts]) for f in ("masks", "actions", "logprobs", "values", "advantages", "returns")]
        put = _placed(jax, device)
        program = _recurrent_update_program(net, c.layout, hyper, num_envs)
        rows, avg, sq, step, losses = program(
            *_adam_inputs(put, c),
            put(torch.stack([r.memories for r in chunk_rollouts]).float()),
            tuple(jax.device_put(o, jax.devices("cpu")[0]) if device.type == "cpu" else jax.numpy.asarray(o) for o in orders),
            put(obs),
            *(put(c) for c in columns[:1]),
            put(columns[1].int()),
            *(put(c) for c in columns[2:]),
            put(torch.stack(targets).int()),
        )
        out += _written_back(c, device, rows, avg, sq, step, losses, names)
    return out


def update(ppos: list, rollouts: list, width: int | None = None) -> list[dict[str, float]]:
    """PPO's update for ``ppos`` (one architecture and PPO config, checked by the caller) on the
    torch trainer's ``rollouts``, ``width`` agents per XLA call (a group: :data:`WIDTH` on the CPU,
    :data:`CUDA_WIDTH` on CUDA; a lone run: 1); one stats dict per agent, as
    :func:`rlbackdoors.algos.group.update` returns them."""
    from rlbackdoors.algos.obs import stack

    lead = ppos[0]
    device = lead.device
    if width is None:
        width = CUDA_WIDTH if device.type == "cuda" else WIDTH
    if lead.model.recurrent:
        return _update_recurrent(ppos, rollouts, width)
    jax = start(gpu=device.type == "cuda")
    cfg, model = lead.cfg, lead.model
    n = rollouts[0].num_frames
    if any(r.num_frames != n for r in rollouts):
        raise ValueError("a training group needs rollouts of the same length")
    if n % cfg.batch_size:
        raise ValueError(f"ppo.update_backend='jax' needs ppo.batch_size={cfg.batch_size} to divide a rollout's {n} frames (ppo.rollout x env copies)")
    layers, hyper = structure(model), _torch_hyper(lead)
    out: list[dict[str, float]] = []
    for c in _chunks(ppos, rollouts, width):
        chunk, chunk_rollouts, real = c.ppos, c.rollouts, c.real
        with torch.no_grad():
            inputs = model.stacked_input(stack([r.obs for r in chunk_rollouts]))
        if not isinstance(inputs, torch.Tensor):
            raise ValueError(f"ppo.update_backend='jax' runs models on one observation array, not {type(model).__name__}'s")
        # each real agent's minibatch orders, every epoch's drawn in turn from its own generator
        # (as torch's update draws them); a pad copy takes its chunk's first agent's
        perms = [torch.stack([torch.randperm(n, generator=ppo.generator) for _ in range(cfg.epochs)]) for ppo in chunk[:real]]
        orders = torch.stack(perms + perms[:1] * (width - real), 1)  # (epochs, K, n)
        orders = orders.reshape(cfg.epochs, width, n // cfg.batch_size, cfg.batch_size).transpose(1, 2).reshape(-1, width, cfg.batch_size)
        columns = [torch.stack([getattr(r, f) for r in chunk_rollouts]) for f in ("actions", "logprobs", "values", "advantages", "returns")]
        put = _placed(jax, device)
        rows, avg, sq, step, losses = _update_program(layers, c.layout, hyper)(
            *_adam_inputs(put, c),
            put(inputs),
            *(put(column) for column in columns),
            put(orders.int().to(device)),
        )
        out += _written_back(c, device, rows, avg, sq, step, losses, STATS)
    return out


__all__ = [
    "Agents",
    "Hyper",
    "IterationStats",
    "Iterated",
    "Learner",
    "agent_state",
    "check",
    "init_agents",
    "iterate",
    "make_iteration",
    "state_dicts",
    "update",
]
