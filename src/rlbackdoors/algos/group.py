"""K PPO learners of one architecture and config trained together: one batched forward per
rollout step for all K agents, one batched forward/backward per minibatch, one optimiser step.

Why: one agent's rollout forward is ~10 rows and its minibatch 256 rows, far too little to keep
an accelerator (or even a CPU core's vector units) busy, and each small op pays Python and
kernel dispatch. Stacking the agents' weights (name -> (K, ...)) turns K small matmuls into one
``baddbmm`` (:func:`rlbackdoors.models.minigrid.run_sequential_stacked`).

Each agent stays an ordinary :class:`~rlbackdoors.algos.ppo.PPO` learner: its own model, its own
generator (the same uniforms and minibatch orders it would draw alone), its own env mix and its
own optimiser state, kept in ``torch.optim.Adam``'s format so its checkpoint resumes alone or
in any group. What is shared is only the arithmetic: per-agent losses are summed (the agents'
parameters are disjoint, so each gets exactly its own gradient), gradients are clipped per agent,
and Adam steps every agent with its own moments and step count. Results equal a lone agent's up
to float rounding (batched kernels add in another order), not bit for bit.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from rlbackdoors.algos.obs import obs_map, stack, stack_numpy, store, to_torch
from rlbackdoors.algos.stacked import FlatParameters, StackedAdam, parameters_by_name, stacked_parameters
from rlbackdoors.attacks.seam import AttackSeam, SeamGroup
from rlbackdoors.envs.batched_base import EngineGroup
from rlbackdoors.envs.grid_device import device_engine_for
from rlbackdoors.models.minigrid import linear_stacked
from rlbackdoors.validate import ConfigError
from rlbackdoors.algos.ppo import (
    AUX_CLASSES,
    PPO,
    Rollout,
    behaviour_logprobs,
    check_vector_env,
    gae,
    make_rollout,
    ppo_loss,
    record_step,
    sample_actions,
    teacher_kl,
)

STATS = ("policy_loss", "value_loss", "entropy", "grad_norm")
# Where a group's rollout steps its slots with the world's device engine (collect's device_engine
# None): the learners' device types. None by default: on a CPU numba is ×10-14 faster, and on a GPU
# the eager device engine triples a cycle's kernel launches (an FC grid world, K = 64: 7,577 -> 20,454
# operations, counted on the CPU) while on CUDA it runs as one CUDA graph a step, not yet timed
# there (docs/results/zoos.md). The environment variable sets it for a process and the jobs it
# starts (bench zoo's ENGINE side field sets it): a comma-separated list of cpu, cuda, or empty for
# never. It changes no bytes, only which engine steps them.
DEVICE_ENGINE_ENV = "RLBACKDOORS_DEVICE_ENGINE"
DEVICE_ENGINE: tuple[str, ...] = ()


def device_engine_types() -> tuple[str, ...]:
    """The device types whose groups step their slots with a device engine (see DEVICE_ENGINE_ENV)."""
    text = os.environ.get(DEVICE_ENGINE_ENV)
    if text is None:
        return DEVICE_ENGINE
    types = tuple(t.strip() for t in text.split(",") if t.strip())
    if set(types) - {"cpu", "cuda"}:
        raise ConfigError(f"{DEVICE_ENGINE_ENV}={text!r} is not allowed (allowed: a comma-separated list of cpu, cuda; empty: never)")
    return types


def check_group(ppos: list[PPO]) -> None:
    """A group shares one architecture, one PPO config and one device, and either every agent has
    a clean teacher (``poison.evasion.teacher``, each its own, with its own coefficient) or none,
    and likewise a weight anchor (``poison.evasion.anchor``)."""
    lead = ppos[0]
    for ppo in ppos:
        if type(ppo.model) is not type(lead.model) or ppo.cfg != lead.cfg or ppo.device != lead.device:
            raise ValueError("a training group needs one architecture, one ppo config and one device")
        if (ppo.teacher is None) != (lead.teacher is None):
            raise ValueError("a training group needs a clean teacher for every agent or for none")
        if (ppo.anchor is None) != (lead.anchor is None):
            raise ValueError("a training group needs a weight anchor for every agent or for none")
    if not stackable(lead.model):
        raise ValueError(f"{type(lead.model).__name__} has no batched forward for a training group")


def stackable(model) -> bool:
    """Whether ``model``'s architecture has the group's batched forward (and, recurrent, its batched BPTT)."""
    return hasattr(model, "forward_stacked") and (not model.recurrent or hasattr(model, "forward_sequence_stacked"))


@torch.no_grad()
def stacked_teachers(ppos: list[PPO]) -> dict[str, torch.Tensor]:
    """Every agent's clean teacher (frozen; the model's architecture), name -> (K, ...)."""
    teachers = [ppo.teacher for ppo in ppos]
    assert all(t is not None for t in teachers)  # check_group: every agent has one
    named = [dict(t.named_parameters()) for t in teachers]  # type: ignore[union-attr]
    return {name: torch.stack([n[name] for n in named]) for name in named[0]}


# A CUDA group computes this many agents at a time, its last chunk padded (see group_width, chunks).
CUDA_WIDTH = 64


def group_width(k: int, device: torch.device) -> int:
    """The number of agents a group of ``k`` computes at: real ones plus pad copies of the first.

    Why pad: kernels pick their algorithm, and so their rounding, by the batch's shape. On the
    CPU a batch of one sums differently from two or more (measured: the critic's 32 -> 1 layer),
    while from two up an agent's numbers do not depend on K; on CUDA (cuBLAS, reductions) the
    choice depends on K itself, so groups there compute in chunks of a fixed width
    (:func:`chunks`). An agent's bytes then depend on its config and device, not on its
    group-mates, the group size, how many of them are still training, or a resume in another group."""
    if device.type == "cuda":
        return -(-k // CUDA_WIDTH) * CUDA_WIDTH
    return max(k, 2)


def chunk_width(device: torch.device) -> int | None:
    """The most agents one batched computation takes on ``device`` (None: all of them)."""
    return CUDA_WIDTH if device.type == "cuda" else None


def chunks(k: int, device: torch.device) -> list[slice]:
    """The agents of a group of ``k``, chunk by chunk: one chunk on a CPU; on CUDA ``CUDA_WIDTH``
    at a time, so that an agent always computes at that width (before, a CUDA group of 65 to 128
    computed at 128 and again at 64 once fewer than 65 were left, so a model's bytes hung on how
    many runs shared its zoo's group as it trained, which no file recorded)."""
    width = chunk_width(device)
    if width is None or k <= width:
        return [slice(0, k)]
    return [slice(start, min(start + width, k)) for start in range(0, k, width)]


def per_chunk(fn: Callable[..., list], agents: list, *args) -> list | None:
    """``fn(agents, *args)`` chunk by chunk (:func:`chunks`), each list argument sliced as the
    agents and the per-agent results joined; None where the device computes all agents at once
    (the caller then goes on with the whole group)."""
    pieces = chunks(len(agents), agents[0].device)
    if len(pieces) == 1:
        return None
    return [out for piece in pieces for out in fn(agents[piece], *(a[piece] if isinstance(a, list) else a for a in args))]


def padded(items: list, device: torch.device) -> list:
    """``items`` (one per agent) with copies of the first up to :func:`group_width`."""
    return items + items[:1] * (group_width(len(items), device) - len(items))


# Stacked parameters of a group: one dict (name -> (K, ...)), or per chunk its agents and theirs
Stacked = dict[str, torch.Tensor] | list[tuple[slice, dict[str, torch.Tensor]]]


def stacked_in_chunks(items: list, device: torch.device, stack: Callable[[list], dict[str, torch.Tensor]]) -> Stacked:
    """``stack`` of the padded ``items`` (one per agent), chunk by chunk where the device computes
    in chunks (:func:`chunks`): what :func:`forward` takes."""
    parts = chunks(len(items), device)
    if len(parts) == 1:
        return stack(padded(items, device))
    return [(part, stack(padded(items[part], device))) for part in parts]


def forward(model: Any, params: Stacked, obs, *memory: torch.Tensor) -> tuple:
    """``model.forward_stacked`` (recurrent: with the memory, returning the new one too) for the
    K agents of ``obs``, computed at the width of ``params`` (stacked from :func:`padded` agents;
    in chunks, :func:`stacked_in_chunks`: each chunk's agents at its width, then joined)."""
    if isinstance(params, list):
        outs = [forward(model, chunk, obs_map(lambda x: x[part], obs), *(m[part] for m in memory)) for part, chunk in params]
        return tuple(torch.cat(parts) for parts in zip(*outs))
    width = next(iter(params.values())).shape[0]
    k = (next(iter(obs.values())) if isinstance(obs, dict) else obs).shape[0]
    if width == k:
        return model.forward_stacked(params, obs, *memory)

    def pad(x: torch.Tensor) -> torch.Tensor:
        return torch.cat([x, x[:1].expand(width - k, *x.shape[1:])])

    out = model.forward_stacked(params, obs_map(pad, obs), *(pad(m) for m in memory))
    return tuple(x[:k] for x in out)


# Steps of uniforms a lockstep evaluation draws per agent at once (see stacked_act).
DRAW_BLOCK = 64


def stacked_act(agents: list):
    """One batched forward a step for K trained networks of one architecture (``agents``:
    :class:`~rlbackdoors.agent.Agent` objects of PPO worlds): an evaluation's ``act`` for a group's
    agents (:data:`rlbackdoors.evaluate.episodes.ActMany`). Only the stepped agents are computed,
    at their :func:`group_width`, each drawing from its own generator what its
    :meth:`~rlbackdoors.agent.Agent.act` would draw alone.

    No Python walks over the agents per step: their weights are stacked once per evaluation and
    the stepped ones picked by one index per name when the set shrinks; their uniforms are drawn
    ``DRAW_BLOCK`` steps at a time per agent from its host generator (n draws at once are n
    drawn one by one there) into one (K, steps, slots) block, read one step a call."""
    models = [a.policy for a in agents]
    lead: Any = models[0]
    device = next(lead.parameters()).device
    named = [dict(m.named_parameters()) for m in models]
    with torch.no_grad():
        every = {name: torch.stack([p[name] for p in named]) for name in named[0]}  # all K agents, stacked once
    cache: dict[tuple, Stacked] = {}
    draws: dict[str, Any] = {"of": None}  # this evaluation's uniform block: its generators, the block, the next step

    def pick(members: list) -> dict[str, torch.Tensor]:
        index = torch.tensor(members, device=device)
        return {name: value.index_select(0, index) for name, value in every.items()}

    def params_of(live: tuple) -> Stacked:  # the live set only shrinks: a few picks per evaluation
        if live not in cache:
            cache.clear()
            cache[live] = stacked_in_chunks(list(live), device, pick)
        return cache[live]

    def uniforms(stepped: list[int], generators: list[torch.Generator], n: int) -> torch.Tensor:
        """The stepped agents' uniforms for this step (len(stepped), n), each agent's next ``n``
        from its own host generator (:meth:`~rlbackdoors.agent.Agent.generator`; a device's would
        fail here rather than draw other numbers)."""
        if draws["of"] is not generators or draws["t"] == DRAW_BLOCK:  # a new evaluation, or the block is spent
            if draws["of"] is not generators:
                draws.update(of=generators, block=torch.empty((len(generators), DRAW_BLOCK, n)))
            for k in stepped:  # (agents no longer stepped draw no more, as alone)
                torch.rand((DRAW_BLOCK, n), generator=generators[k], out=draws["block"][k])
            draws["t"] = 0
        t = draws["t"]
        draws["t"] = t + 1
        return draws["block"][:, t].index_select(0, torch.tensor(stepped))

    @torch.inference_mode()
    def act(stepped: list[int], batch, sizes: list[int], states: list, generators: list[torch.Generator], deterministic: bool):
        if any(n != sizes[0] for n in sizes):
            raise ValueError(f"agents acting stacked need the same number of slots each, got {sorted(set(sizes))}")
        params = params_of(tuple(stepped))
        # the stepped agents' rows are contiguous, agent after agent: (K, B, ...) is a reshape
        x = obs_map(lambda t: t.to(device), to_torch(obs_map(lambda a: a.reshape(len(stepped), sizes[0], *a.shape[1:]), batch)))
        if lead.recurrent:
            logits, _, memory = forward(lead, params, x, torch.stack([states[k] for k in stepped]))
            states = list(states)
            for k, m in zip(stepped, memory):
                states[k] = m
        else:
            logits, _ = forward(lead, params, x)
        if deterministic:
            actions = logits.argmax(-1)
        else:  # each agent's own uniforms (what its lone sample_actions draws), then one sample for all
            u = uniforms(stepped, generators, sizes[0]).to(device)
            actions = sample_actions(logits.reshape(-1, logits.shape[-1]), u=u.reshape(-1)).reshape(u.shape)
        return actions.reshape(-1).cpu().numpy(), states  # one copy back for the stepped agents, not one each

    return act


def step_together(t: int, engines: EngineGroup, seams: SeamGroup | None, wanted: np.ndarray, record: tuple) -> np.ndarray | dict:
    """Step ``t`` of every agent's env copies in one engine call: ``wanted`` (K, B) actions, the
    step recorded in ``record``'s (K, T, B) host buffers (executed, rewards, dones, outcomes, steps,
    forced) as :func:`~rlbackdoors.algos.ppo.record_step` records each agent's; every agent's next
    observations (K, B, ...). Only the seams with work this step (``seams``) touch their agents' rows."""
    executed, rewards, dones, outcomes, steps, forced = record
    K, B = wanted.shape
    run, prepared = seams.prepare(wanted) if seams is not None else (wanted, {})
    result = engines.step(run.reshape(-1))
    seen, reward, terminated, truncated, info = result
    if seams is not None:  # what ran: a seam may force other actions than the sampled ones
        executed[:, t] = run
    rewards[:, t], dones[:, t] = reward.reshape(K, B), (terminated | truncated).reshape(K, B)
    outcomes[:, t], steps[:, t] = info["outcome"].reshape(K, B), info["steps"].reshape(K, B)
    together = obs_map(lambda x: x.reshape(K, B, *x.shape[1:]), seen)
    if not prepared:
        return together
    assert seams is not None
    together = obs_map(np.copy, together)  # a seam may stamp its frames: not into the engines' arrays
    for k, poisoned in seams.finish(prepared, lambda k: engines.result(k, *result)):
        ob = record_step(t, poisoned, executed[k], rewards[k], dones[k], outcomes[k], steps[k], forced[k])
        if isinstance(together, dict):
            for key, rows in together.items():
                rows[k] = ob[key]
        else:
            together[k] = ob
    return together


@torch.inference_mode()
def collect(ppos: list[PPO], envs: list, obs: list, one_call: bool = True, device_engine: bool | None = None) -> list[tuple[Rollout, np.ndarray | dict]]:
    """:meth:`PPO.collect` for K agents, each on its own vector env: (rollout, next obs) per agent.
    ``one_call``: step all agents' envs with one engine call where they allow it
    (:class:`~rlbackdoors.envs.batched_base.EngineGroup`; the same bytes either way).
    ``device_engine``: step that call's slots on the learners' device instead, with the world's
    device engine (:mod:`rlbackdoors.envs.grid_device`), where the world has one and no attack
    seam, memory or teacher takes part, on CUDA as one CUDA graph a step; the same bytes. None: on
    the device types of :func:`device_engine_types` (by default none: see :data:`DEVICE_ENGINE`)."""
    check_group(ppos)
    lead, K = ppos[0], len(ppos)
    T, B = lead.cfg.rollout, envs[0].num_envs
    for e in envs:
        check_vector_env(e)
        if e.num_envs != B:
            raise ValueError("a training group needs the same number of env copies per agent")
    device, A = lead.device, envs[0].single_action_space.n
    model: Any = lead.model  # forward_stacked takes a tensor or a dict of them, as the world's model does
    params = stacked_in_chunks(ppos, device, stacked_parameters)
    recurrent, aux = lead.model.recurrent, lead.aux is not None
    if aux and any(getattr(e, "memory_target_classes", None) != AUX_CLASSES for e in envs):
        raise ValueError(f"ppo.aux_memory_coef needs an env with {AUX_CLASSES} memory targets (memory_targets())")
    # the rollout stays on the learners' device: only observations go there and actions come back per step
    if recurrent:
        memory = torch.stack([ppo.memory if ppo.memory is not None else lead.model.initial_memory(B, device) for ppo in ppos])
        memories = torch.empty((K, T, B, memory.shape[2]), device=device)
        masks = torch.ones((K, T, B), device=device)
        targets = np.empty((K, T, B), dtype=np.int64) if aux else None
    teach = lead.teacher is not None
    if teach:
        if not all(hasattr(e, "marked") for e in envs):
            raise ValueError("a clean teacher needs the attack's collection seam to say which frames carry the trigger (marked)")
        teachers = stacked_in_chunks(ppos, device, stacked_teachers)
        teacher_logits = torch.empty((K, T, B, A), device=device)
        untriggered = np.empty((K, T, B), dtype=bool)  # on the host, to the device once a rollout
        if recurrent:
            teacher_memory = torch.stack([ppo.teacher_memory if ppo.teacher_memory is not None else lead.model.initial_memory(B, device) for ppo in ppos])
    uniforms = torch.stack([torch.rand((T, B), generator=ppo.generator) for ppo in ppos]).to(device)  # each agent's own draws
    obs = list(obs)
    # one (T, K, B, ...) buffer: step t of all K agents is one contiguous batch, no stacking per step
    obs_buf = obs_map(lambda x: torch.empty((T, K, *x.shape), dtype=x.dtype, device=device), to_torch(obs[0]))
    actions = torch.empty((K, T, B), dtype=torch.long, device=device)
    logits_buf = torch.empty((K, T, B, A), device=device)
    values = torch.empty((K, T, B), device=device)
    # what the envs ran and which of it an attack forced, on the host (an attack's seam answers each
    # agent apart): to the device once a rollout, not a copy per agent and step
    executed = np.empty((K, T, B), dtype=np.int64)
    forced = np.zeros((K, T, B), dtype=bool)
    rewards = np.empty((K, T, B), dtype=np.float64)
    dones = np.empty((K, T, B), dtype=bool)
    outcomes = np.empty((K, T, B), dtype=np.int64)
    steps = np.empty((K, T, B), dtype=np.int64)
    # all agents' env copies stepped by one engine call where their engines allow it (one world, the
    # same settings; an attack's seam prepares its actions before the call and finishes after it):
    # the same bytes as a call per agent
    seams = [e if isinstance(e, AttackSeam) else None for e in envs]
    # (over every core of the host where the learners compute on a GPU: the same bytes)
    engines = EngineGroup.of([s.envs if s is not None else e for s, e in zip(seams, envs)], parallel=device.type != "cpu") if one_call else None
    # the seams around that call, deciding together which of them have work in a step
    seam_group = SeamGroup(seams, B) if engines is not None and any(seams) else None
    # (K, B, ...): every agent's observations (an array, or a dict of them)
    together = stack_numpy(obs) if engines is not None else None
    # or the slots on the learners' device for the rollout (handed back to the engines after it):
    # observations, rewards and ends stay there, and nothing crosses per step
    if device_engine is None:
        device_engine = device.type in device_engine_types()
    on_device = None
    if device_engine and engines is not None and seam_group is None and not recurrent and not teach:
        on_device = device_engine_for(engines, device, graph=device.type == "cuda")
    if on_device is not None:
        seen_t = torch.from_numpy(np.ascontiguousarray(together)).to(device)
        ends = {
            name: torch.empty((K, T, B), dtype=dtype, device=device)
            for name, dtype in (("rewards", torch.float64), ("dones", torch.bool), ("outcomes", torch.int64), ("steps", torch.int64))
        }
    try:
        for t in range(T):
            if on_device is not None:
                obs_buf[t] = seen_t
            else:
                store(obs_buf, t, together if together is not None else stack_numpy(obs))  # one copy a step, agents stacked on the host
            obs_t = obs_map(lambda x: x[t], obs_buf)
            if teach:
                if seam_group is not None:
                    untriggered[:, t] = ~seam_group.marked
                else:
                    for k in range(K):
                        untriggered[k, t] = ~np.asarray(envs[k].marked, dtype=bool)
                if recurrent:
                    teacher_logits[:, t], _, teacher_memory = forward(model, teachers, obs_t, teacher_memory)
                else:
                    teacher_logits[:, t] = forward(model, teachers, obs_t)[0]
            if recurrent:
                if targets is not None:  # of the episodes obs[t] belongs to
                    if engines is not None:
                        targets[:, t] = engines.memory_targets().reshape(K, B)
                    else:
                        for k in range(K):
                            targets[k, t] = envs[k].memory_targets()
                memories[:, t] = memory
                logits_buf[:, t], values[:, t], memory = forward(model, params, obs_t, memory)
            else:
                logits_buf[:, t], values[:, t] = forward(model, params, obs_t)
            actions[:, t] = sample_actions(logits_buf[:, t].reshape(K * B, A), u=uniforms[:, t].reshape(-1)).reshape(K, B)
            if on_device is not None:
                seen, reward, terminated, truncated, outcome, episode_steps = on_device.step(actions[:, t].reshape(-1))
                seen_t = seen.reshape(K, B, *seen.shape[1:])
                ends["rewards"][:, t], ends["dones"][:, t] = reward.reshape(K, B), (terminated | truncated).reshape(K, B)
                ends["outcomes"][:, t], ends["steps"][:, t] = outcome.reshape(K, B), episode_steps.reshape(K, B)
                continue
            wanted = actions[:, t].cpu().numpy()  # the one copy back a step: the engines run on the host
            if engines is not None:
                together = step_together(t, engines, seam_group, wanted, (executed, rewards, dones, outcomes, steps, forced))
            else:
                executed[:, t] = wanted  # record_step writes what an attack's seam ran over these
                for k in range(K):  # each env with its agent's actions already on the host (env_step's record, without a copy back each)
                    obs[k] = record_step(t, envs[k].step(wanted[k]), executed[k], rewards[k], dones[k], outcomes[k], steps[k], forced[k])
            if recurrent and dones[:, t].any():  # a new episode starts with an empty memory
                ended = torch.from_numpy(dones[:, t]).to(device)
                memory = memory.masked_fill(ended[..., None], 0.0)
                if teach:
                    teacher_memory = teacher_memory.masked_fill(ended[..., None], 0.0)
                if t + 1 < T:
                    masks[:, t + 1] = (~ended).float()
    finally:
        if seam_group is not None:
            seam_group.flush()
        if on_device is not None:  # the engines hold the state again (checkpoints, evaluations)
            on_device.hand_back()
            together = seen_t.cpu().numpy()
            for name, host in (("rewards", rewards), ("dones", dones), ("outcomes", outcomes), ("steps", steps)):
                host[:] = ends[name].cpu().numpy()
    if together is not None:
        obs = [{key: v[k] for key, v in together.items()} if isinstance(together, dict) else together[k] for k in range(K)]
    last = obs_map(lambda x: x.to(device), stack([to_torch(o) for o in obs]))
    next_value = (forward(model, params, last, memory) if recurrent else forward(model, params, last))[1]
    # every agent's behaviour log-probabilities and advantages in one pass (the same arithmetic per
    # element as PPO.assemble's, so the same bytes), over (T, K, B)
    if engines is None or seam_group is not None:  # an attack may have run other actions than the sampled ones
        actions = torch.from_numpy(executed).to(device)
    logprobs = behaviour_logprobs(logits_buf, actions, torch.from_numpy(forced).to(device))
    cfg = lead.cfg
    advantages = gae(
        torch.from_numpy(rewards).float().to(device).transpose(0, 1),
        torch.from_numpy(dones).to(device).transpose(0, 1),
        values.transpose(0, 1),
        next_value,
        cfg.gamma,
        cfg.gae_lambda,
    ).transpose(0, 1)
    returns = values + advantages  # every agent's at once (make_rollout's sum, element by element)
    if teach:
        untriggered_all = torch.from_numpy(untriggered).to(device)
        teacher_logp = torch.log_softmax(teacher_logits, -1)  # every agent's at once (row by row, as alone)
    if recurrent and targets is not None:
        targets_all = torch.from_numpy(targets).to(device)
    out = []
    for k, ppo in enumerate(ppos):
        rollout = make_rollout(
            obs_map(lambda b: b[:, k], obs_buf), actions[k], logprobs[k], values[k], advantages[k], rewards[k], dones[k], outcomes[k], steps[k], returns[k]
        )
        if recurrent:
            rollout.memories, rollout.masks = memories[k].reshape(T * B, -1), masks[k].reshape(-1)
            ppo.memory = memory[k].clone()
            if targets is not None:
                rollout.memory_targets = targets_all[k].reshape(-1)
        if teach:
            rollout.teacher_logp = teacher_logp[k].reshape(T * B, -1)
            rollout.untriggered = untriggered_all[k].reshape(-1)
            if recurrent:
                ppo.teacher_memory = teacher_memory[k].clone()
        out.append((rollout, obs[k]))
    return out


def clip_per_agent(grad: torch.Tensor, max_norm: float) -> torch.Tensor:
    """``clip_grad_norm_`` for each agent's row of the (K, P) gradient; the norms before clipping (K,)."""
    norms = grad.norm(dim=1)
    grad.mul_((max_norm / (norms + 1e-6)).clamp(max=1.0)[:, None])
    return norms


def take(x: torch.Tensor, flat_idx: torch.Tensor, k: int) -> torch.Tensor:
    """``x[rows, idx]`` for a (K, n, ...) tensor and (K, N) indices given flattened into the K * n
    rows (``idx + rows * n``): one ``index_select`` instead of advanced indexing (3x cheaper here)."""
    return x.reshape(-1, *x.shape[2:]).index_select(0, flat_idx).reshape(k, -1, *x.shape[2:])


def update(ppos: list[PPO], rollouts: list[Rollout]) -> list[dict[str, float]]:
    """:meth:`PPO.update` for K agents: the same epochs and minibatches each agent would run
    alone (its own generator orders its frames), batched; one stats dict per agent."""
    check_group(ppos)
    if ppos[0].cfg.update_backend == "jax":  # every minibatch in one XLA program, in chunks of its own width
        from rlbackdoors.algos import compiled

        return compiled.update(ppos, rollouts)
    if (joined := per_chunk(update, ppos, rollouts)) is not None:  # each chunk at the device's width, one after another
        return joined
    real, device = len(ppos), ppos[0].device
    ppos, rollouts = padded(ppos, device), padded(rollouts, device)  # pad copies of the first agent: see group_width
    lead, K = ppos[0], len(ppos)
    cfg = lead.cfg
    model: Any = lead.model
    n = rollouts[0].num_frames
    if any(r.num_frames != n for r in rollouts):
        raise ValueError("a training group needs rollouts of the same length")
    weights = FlatParameters(stacked_parameters(ppos))
    params = weights.views
    adam = StackedAdam([(ppo.optimizer, parameters_by_name(ppo)) for ppo in ppos], weights)
    obs = obs_map(lambda x: x.to(device), stack([r.obs for r in rollouts]))
    tensors = [torch.stack([getattr(r, f) for r in rollouts]).to(device) for f in ("actions", "logprobs", "values", "advantages", "returns")]
    rows = torch.arange(K, device=device)[:, None]
    keys = STATS + (("aux_memory_loss",) if lead.aux is not None else ()) + (("teacher_kl",) if lead.teacher is not None else ())
    if lead.anchor is not None:  # each agent's clean weights (model parameters only) and pull, as PPO.pull_to_anchor
        anchors = {name: torch.stack([ppo.anchor[name] for ppo in ppos]).to(device) for name in lead.anchor}  # type: ignore[index]  # check_group: every agent has one
        anchor_coef = torch.tensor([ppo.anchor_coef for ppo in ppos], device=device)
    if lead.teacher is not None:  # each agent's teacher log-probabilities, untriggered rows and coefficient
        teacher_logp = torch.stack([r.teacher_logp for r in rollouts]).to(device)  # type: ignore[misc]  # collected with the teacher
        untriggered = torch.stack([r.untriggered for r in rollouts]).to(device)  # type: ignore[misc]
        teacher_coef = torch.tensor([ppo.teacher_coef for ppo in ppos], device=device)

    def with_teacher(loss: torch.Tensor, parts: dict, logits: torch.Tensor, frames: torch.Tensor) -> torch.Tensor:
        """The loss with each agent's ``teacher_coef * KL(teacher || policy)`` on its rows ``frames`` (K, N)."""
        if lead.teacher is None:
            return loss
        parts["teacher_kl"] = teacher_kl(logits, teacher_logp[rows, frames], untriggered[rows, frames])
        return loss + teacher_coef * parts["teacher_kl"]

    stats = {key: torch.zeros(K, dtype=torch.float64, device=device) for key in keys}  # on the device: no sync per minibatch

    def step(loss: torch.Tensor, parts: dict) -> None:
        grad = weights.grad(loss.sum())
        stats["grad_norm"] += clip_per_agent(grad, cfg.max_grad_norm).double()
        adam.apply(grad)
        if lead.anchor is not None:
            with torch.no_grad():
                for name, anchor in anchors.items():
                    params[name].lerp_(anchor, anchor_coef.view((-1,) + (1,) * (anchor.dim() - 1)))
        for key, value in parts.items():
            stats[key] += value.detach().double()

    def orders(n_items: int) -> torch.Tensor:  # each agent's own permutation, from its own generator
        perms = [torch.randperm(n_items, generator=ppo.generator) for ppo in ppos[:real]]
        return torch.stack(padded(perms, device)).to(device)

    updates = 0
    if not lead.model.recurrent:
        with torch.no_grad():  # the rollout's observations as the first layer reads them, converted once
            inputs = model.stacked_input(obs)
        for _ in range(cfg.epochs):
            order = orders(n)
            for start in range(0, n, cfg.batch_size):
                idx = order[:, start : start + cfg.batch_size]
                flat_idx = (idx + rows * n).reshape(-1)  # each agent's rows of its own frames, as one index into (K * n) rows
                logits, values = model.forward_stacked_input(params, obs_map(lambda x: take(x, flat_idx, K), inputs))
                loss, parts = ppo_loss(cfg, logits, values, *(take(x, flat_idx, K) for x in tensors))
                step(with_teacher(loss, parts, logits, idx), parts)
                updates += 1
    else:  # truncated BPTT, as PPO._update_recurrent, each agent on its own sequences
        r, B = cfg.recurrence, rollouts[0].num_envs
        memories = torch.stack([ro.memories for ro in rollouts]).to(device)  # type: ignore[misc]  # collected by a recurrent model
        masks = torch.stack([ro.masks for ro in rollouts]).to(device)  # type: ignore[misc]
        targets = torch.stack([ro.memory_targets for ro in rollouts]).to(device) if lead.aux is not None else None  # type: ignore[misc]
        per_batch = max(cfg.batch_size // r, 1)
        for epoch in range(cfg.epochs):
            starts = lead.sequence_starts(n // B, B, shifted=epoch % 2 == 1).to(device)
            order = starts[orders(len(starts))]
            for start in range(0, order.shape[1], per_batch):
                idx = order[:, start : start + per_batch]  # (K, N) first steps of each agent's sequences
                seq = idx[:, None, :] + B * torch.arange(r, device=device)[None, :, None]  # (K, r, N)
                flat = seq.reshape(K, -1)
                logits, values, new_memories = model.forward_sequence_stacked(
                    params, obs_map(lambda x: x[rows[:, :, None], seq], obs), memories[rows, idx], masks[rows[:, :, None], seq]
                )
                loss, parts = ppo_loss(cfg, logits, values, *(x[rows, flat] for x in tensors))
                if targets is not None:
                    aux_logits = linear_stacked(new_memories.reshape(K, -1, new_memories.shape[-1]), params["aux.weight"], params["aux.bias"])
                    ce = torch.nn.functional.cross_entropy(aux_logits.reshape(-1, AUX_CLASSES), targets[rows, flat].reshape(-1), reduction="none")
                    parts["aux_memory_loss"] = ce.reshape(K, -1).mean(1)
                    loss = loss + cfg.aux_memory_coef * parts["aux_memory_loss"]
                loss = with_teacher(loss, parts, logits, flat)
                if r > 1:  # the memories the current network computes go back into the rollout, as torch-ac does
                    memories[rows[:, :, None], seq[:, 1:]] = new_memories[:, :-1].detach()
                step(loss, parts)
                updates += 1
    adam.write_back(real)
    means = {key: (value / updates).cpu().tolist() for key, value in stats.items()}  # one sync, floats read at once
    out = [{key: means[key][k] for key in keys} for k in range(real)]
    if lead.anchor is not None:  # each agent's own distance, as PPO.update logs it, for all agents at once
        with torch.no_grad():
            squares = torch.stack([(params[name][:real] - anchors[name][:real]).double().pow(2).flatten(1).sum(1) for name in anchors])
            for k, distance in enumerate(squares.sum(0).sqrt().tolist()):
                out[k]["anchor_distance"] = distance
    return out
