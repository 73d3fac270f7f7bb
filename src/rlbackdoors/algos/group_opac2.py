"""K OPAC² agents of one config trained together: one batched policy forward per env step for
all K agents' actions, and each update's V, Q and policy steps as one batched forward/backward.

Why: an OPAC² agent's update (three MLP passes of 256 rows, the V and policy steps with several
sampled actions per state) is most of its training time on a CPU (measured: 0.9 ms a frame
against 0.6 ms of MuJoCo stepping and collection) and leaves an accelerator idle; stacking the
agents' weights (name -> (K, ...)) turns K small matmuls into one ``baddbmm``
(:func:`rlbackdoors.models.minigrid.run_sequential_stacked`).

Each agent stays an ordinary :class:`~rlbackdoors.algos.opac2.OPAC2`: its own networks, target,
observation normaliser, replay, replay-index generator and noise generator (the same draws, in
the same order, as alone) and its own optimiser states, kept in ``torch.optim.Adam``'s format so
its checkpoint resumes alone or in any group. The agents' losses are summed (their parameters
are disjoint: each gets exactly its own gradient) and Adam steps each with its own moments,
step count and learning rate. Results equal a lone agent's up to float rounding.
"""

from __future__ import annotations

import math
import weakref

import numpy as np
import torch

from rlbackdoors.algos.group import group_width, padded, per_chunk
from rlbackdoors.algos.stacked import FlatParameters, StackedAdam
from rlbackdoors.algos.opac2 import ADV_EPS, OPAC2, Batch, squash, squashed_log_prob
from rlbackdoors.config import LOG_STD_MAX, LOG_STD_MIN
from rlbackdoors.models.minigrid import run_sequential_stacked

NETS = ("policy", "q", "v")  # trained, each by its own optimiser; v_target follows v by Polyak steps
STATS = ("v_loss", "q_loss", "policy_loss", "q_mean", "entropy", "log_prob")


def check_group(agents: list[OPAC2]) -> None:
    """One config, one device and one network shape for the whole group."""
    lead = agents[0]
    for agent in agents[1:]:
        if agent.cfg != lead.cfg or agent.device != lead.device or agent.policy_obs_dim != lead.policy_obs_dim:
            raise ValueError("an OPAC² training group needs one opac2 config, one device and one observation size")


def named(agent: OPAC2, net: str) -> dict[str, torch.nn.Parameter]:
    """``net``'s parameters of one agent by their stacked names (``net.…``)."""
    return {f"{net}.{name}": p for name, p in getattr(agent, net).named_parameters()}


def stacked(agents: list[OPAC2], net: str, grad: bool) -> dict[str, torch.Tensor]:
    """``net``'s parameters of every agent, name (``net.…``) -> (K, ...), copies (one stack per name)."""
    each = [named(a, net) for a in agents]
    with torch.no_grad():
        out = {name: torch.stack([n[name] for n in each]) for name in each[0]}
    return {k: v.requires_grad_() for k, v in out.items()} if grad else out


def mean_and_log_std(lead: OPAC2, params: dict, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """:meth:`GaussianPolicy.forward` for K agents: mean (K, N, A), clamped log-std (K, A)."""
    return run_sequential_stacked(lead.policy.mean, params, "policy.mean", obs), params["policy.log_std"].clamp(LOG_STD_MIN, LOG_STD_MAX)


def sample(lead: OPAC2, agents: list[OPAC2], params: dict, obs: torch.Tensor, samples: int = 1):
    """:meth:`GaussianPolicy.sample` for K agents, each agent's noise drawn from its own
    generator (a pad copy reuses its original's draw, so no stream moves twice)."""
    mean, log_std = mean_and_log_std(lead, params, obs)
    if samples > 1:
        mean = mean.repeat(1, samples, 1)  # per agent, row j * n + i is state i's j-th action
    real = [torch.randn(mean.shape[1:], generator=a.generator, device=a.generator.device) for a in agents]
    noise = torch.stack(padded(real, mean.device)).to(mean.device)
    u = (mean + noise * log_std.exp()[:, None, :]).detach()
    return squash(u), u, mean, log_std


def q_value(lead: OPAC2, params: dict, obs: torch.Tensor, act: torch.Tensor) -> torch.Tensor:
    return run_sequential_stacked(lead.q.net, params, "q.net", torch.cat((obs, act), dim=-1)).squeeze(-1)


def v_value(lead: OPAC2, params: dict, obs: torch.Tensor, net: str = "v") -> torch.Tensor:
    return run_sequential_stacked(lead.v.net, params, f"{net}.net", obs).squeeze(-1)


_POLICIES: dict[tuple[int, ...], tuple[list, tuple[int, ...], dict[str, torch.Tensor]]] = {}


def policy_stack(agents: list[OPAC2]) -> dict[str, torch.Tensor]:
    """The group's stacked policy, restacked only when a policy changed (an update or a load
    bumps its tensors' versions): agents act every env step and update every few. The cache
    holds weak references and checks them, so a new agent at a recycled id is never mistaken."""
    key = tuple(id(a) for a in agents)
    versions = tuple(p._version for a in agents for p in a.policy.parameters())
    hit = _POLICIES.get(key)
    if hit is None or hit[1] != versions or any(ref() is not a for ref, a in zip(hit[0], agents)):
        if len(_POLICIES) >= 16:
            _POLICIES.clear()
        hit = ([weakref.ref(a) for a in agents], versions, stacked(padded(agents, agents[0].device), "policy", grad=False))
        _POLICIES[key] = hit
    return hit[2]


@torch.inference_mode()
def act(agents: list[OPAC2], obs: list[np.ndarray]) -> list[np.ndarray]:
    """:meth:`OPAC2.act` (sampled actions) for K agents, each on its own observations (n, O)."""
    check_group(agents)
    lead, device = agents[0], agents[0].device
    if (joined := per_chunk(act, agents, obs)) is not None:  # each chunk at the device's width (algos.group.chunks)
        return joined
    params = policy_stack(agents)
    x = torch.stack(padded([torch.as_tensor(a.normalize(o)) for a, o in zip(agents, obs)], device)).to(device)
    action = sample(lead, agents, params, x)[0].cpu().numpy()
    return [action[k] for k in range(len(agents))]


def batches(agents: list[OPAC2], replays: list, rngs: list[np.random.Generator]) -> Batch[torch.Tensor]:
    """One replay batch per agent (its own buffer and index generator, as alone), stacked (K, B, ...)
    on the host and copied to the device once per field (not once per agent and field: on a GPU each
    is a transfer)."""
    columns = [a.batch_arrays(replay.sample(a.cfg.batch_size, rng)) for a, replay, rng in zip(agents, replays, rngs)]
    device = agents[0].device
    return Batch(*(torch.from_numpy(np.stack(padded([c[i] for c in columns], device))).to(device) for i in range(len(columns[0]))))


def update(agents: list[OPAC2], replays: list, rngs: list[np.random.Generator], n: int) -> list[list[dict[str, float]]]:
    """``n`` calls of :meth:`OPAC2.update` for K agents, batched: per agent, its ``n`` loss dicts."""
    check_group(agents)
    if (joined := per_chunk(update, agents, replays, rngs, n)) is not None:  # each chunk at the device's width (algos.group.chunks)
        return joined
    real, lead, device = len(agents), agents[0], agents[0].device
    width = group_width(real, device)
    cfg, k = lead.cfg, lead.cfg.action_samples
    members = padded(agents, device)
    flats = {net: FlatParameters(stacked(members, net, grad=False)) for net in NETS}
    params = {net: flat.views for net, flat in flats.items()}
    target = stacked(members, "v_target", grad=False)
    optimisers = {net: StackedAdam([(getattr(a, f"{net}_opt"), named(a, net)) for a in members], flats[net]) for net in NETS}
    both = {**params["policy"], **params["q"], **params["v"]}
    history = []
    for _ in range(n):
        # V: regress on Q averaged over the current policy.
        b = batches(agents, replays, rngs)
        with torch.no_grad():
            obs_k = b.obs.repeat(1, k, 1)
            action = sample(lead, agents, both, obs_k)[0]
            v_goal = q_value(lead, both, obs_k, action).view(width, k, -1).mean(1)
        v_loss = (v_value(lead, both, b.obs) - v_goal).pow(2).mean(-1)
        optimisers["v"].apply(flats["v"].grad(v_loss.sum()))

        # Q: one-step TD target through the slow V_bar.
        b = batches(agents, replays, rngs)
        with torch.no_grad():
            q_goal = b.rew + cfg.gamma * (1.0 - b.done) * v_value(lead, target, b.next_obs, "v_target")
        q = q_value(lead, both, b.obs, b.act)
        q_loss = (q - q_goal).pow(2).mean(-1)
        optimisers["q"].apply(flats["q"].grad(q_loss.sum()))

        # pi: score-function step weighted by the normalised advantage of a fresh action.
        b = batches(agents, replays, rngs)
        action, u, mean_k, log_std = sample(lead, agents, both, b.obs, samples=k)
        with torch.no_grad():
            advantage = q_value(lead, both, b.obs.repeat(1, k, 1), action) - v_value(lead, both, b.obs).repeat(1, k)
            advantage = (advantage - advantage.mean(-1, keepdim=True)) / (advantage.std(-1, keepdim=True) + ADV_EPS)
        log_prob = squashed_log_prob(u, mean_k, log_std[:, None, :])
        entropy = (log_std + 0.5 * (1.0 + math.log(2 * math.pi))).sum(-1)
        policy_loss = -(advantage * log_prob).mean(-1) - cfg.entropy_coef * entropy
        optimisers["policy"].apply(flats["policy"].grad(policy_loss.sum()))

        with torch.no_grad():  # Polyak, as OPAC2.polyak_update rounds it: scale, then add the scaled online net
            for name, value in target.items():
                value.mul_(cfg.polyak).add_(params["v"]["v" + name[len("v_target") :]] * (1.0 - cfg.polyak))
        history.append(torch.stack([v_loss, q_loss, policy_loss, q.mean(-1), entropy, log_prob.mean(-1)]).detach())
    for optimiser in optimisers.values():
        optimiser.write_back(real)
    with torch.no_grad():  # the slow V_bar back into each agent: one multi-tensor copy
        rows = [value.unbind(0) for value in target.values()]
        each = [named(a, "v_target") for a in agents]
        torch._foreach_copy_([n[name] for n in each for name in target], [row[k] for k in range(real) for row in rows])
    table = torch.stack(history).cpu().tolist() if history else []  # (n, 6, width): one sync
    return [[dict(zip(STATS, (row[i][j] for i in range(len(STATS))))) for row in table] for j in range(real)]
