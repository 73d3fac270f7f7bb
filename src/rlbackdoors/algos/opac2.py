"""OPAC² (SPEC §4, paper §3.4): the off-policy actor-critic TrojAI trained its MuJoCo agents with.

Three networks and a target, written to be read top to bottom:

* ``pi(a|s)``: a tanh-squashed Gaussian whose mean is an MLP of the state and whose log-std
  is one state-independent parameter per action dimension;
* ``Q(s, a)`` and ``V(s)``: MLP critics; ``V_bar``, a Polyak average of ``V``, bootstraps Q.

One :meth:`OPAC2.update` takes one Adam step on each loss, each on its own freshly sampled
batch (fresh batches decorrelate the three steps), then moves ``V_bar`` toward ``V``:

* V loss   ``(V(s) - Q(s, a~))^2`` with ``a~ ~ pi(.|s)``: V is Q averaged over the policy
  (with ``action_samples`` K > 1, the target is the mean of Q over K sampled actions);
* Q loss   ``(Q(s, a) - r - gamma (1 - done) V_bar(s'))^2``: done is *terminated* only (goal
  or hazard), so a timeout still bootstraps;
* pi loss  ``-mean(A * log pi(a~|s))`` with ``A = Q(s, a~) - V(s)`` normalised over the batch
  and held constant (a score-function gradient: no gradient into Q or V); with K > 1 the
  mean runs over K sampled actions per state, normalised over all K x batch of them;
* ``V_bar <- polyak * V_bar + (1 - polyak) * V``.

Multitask poisoning (paper §3.4): one replay buffer per env kind ("clean", "poisoned"),
every batch drawn from the kinds in fixed proportions (:class:`MultitaskReplay`), so the
share of poisoned experience in the gradient is a set hyper-parameter rather than a side
effect of how many envs of each kind run.

All randomness comes from generators handed in (a torch ``Generator`` for network init and
action noise, a numpy ``Generator`` for batch indices), so a run is reproducible from seeds.
"""

from __future__ import annotations

import copy
import math
import re
from typing import Generic, NamedTuple, TypeVar

import numpy as np
import torch
from torch import nn

from rlbackdoors.algos.optim import check_optimizer_state
from rlbackdoors.config import KINDS, LOG_STD_MAX, LOG_STD_MIN, OPAC2Config
from rlbackdoors.validate import _integer_at_least, check_weights

__all__ = ["KINDS", "OPAC2", "OPAC2Config", "MultitaskReplay", "ReplayBuffer", "check_weights", "updates_due"]

# Sampled actions are kept this far inside (-1, 1): float32 tanh rounds to exactly +-1 for
# |u| > ~9, and a stored action of exactly +-1 has no finite pre-tanh value.
ACTION_EPS = 1e-6
ADV_EPS = 1e-8


def updates_due(cfg: OPAC2Config, frames: int) -> int:
    """How many updates a run should have made after ``frames`` env frames.

    None during the random warm-up, then ``updates_per_step`` per frame; a loop does
    ``while updates < updates_due(cfg, frames): agent.update(...)``. Counting from the
    frame total (not accumulating a float) keeps fractional ratios free of drift.
    """
    return max(0, math.floor((frames - cfg.learning_starts) * cfg.updates_per_step + 1e-9))


# ----- replay ----------------------------------------------------------------------------
_Column = TypeVar("_Column", np.ndarray, torch.Tensor)


class Batch(NamedTuple, Generic[_Column]):
    """Transitions as float32 numpy arrays: obs (n, O), act (n, A), rew (n,), next_obs, done (n,)
    (``Batch[torch.Tensor]``: the same as tensors on the learner's device)."""

    obs: _Column
    act: _Column
    rew: _Column
    next_obs: _Column
    done: _Column


class ReplayBuffer:
    """A preallocated float32 ring buffer: the newest ``capacity`` transitions, sampled uniformly.

    ``done`` is 1 only where the episode *terminated*; a truncated transition is stored with
    ``done = 0`` and its true next observation, so its target still bootstraps.
    Checkpoints store it as a journal of the rows added since the last checkpoint
    (:mod:`rlbackdoors.train.replay_journal`), so each row is written once, not once per checkpoint.
    """

    def __init__(self, capacity: int, obs_dim: int, act_dim: int):
        _integer_at_least("replay capacity", capacity, 1)
        self.capacity, self.obs_dim, self.act_dim = int(capacity), int(obs_dim), int(act_dim)
        self._allocate()
        self.pos = 0  # next row to write (always added % capacity)
        self.size = 0  # rows filled
        self.added = 0  # rows ever added: a journal's index

    def _allocate(self) -> None:
        # np.zeros maps pages lazily: unused capacity costs no memory until written.
        n, o, a = self.capacity, self.obs_dim, self.act_dim
        self.obs = np.zeros((n, o), np.float32)
        self.next_obs = np.zeros((n, o), np.float32)
        self.act = np.zeros((n, a), np.float32)
        self.rew = np.zeros(n, np.float32)
        self.done = np.zeros(n, np.float32)

    def __len__(self) -> int:
        return self.size

    def add_batch(self, obs, act, rew, next_obs, done) -> None:
        """Append ``n`` transitions (row ``i`` of each argument is one), overwriting the oldest."""
        obs, next_obs = np.asarray(obs, np.float32), np.asarray(next_obs, np.float32)
        act = np.asarray(act, np.float32)
        rew, done = np.asarray(rew, np.float32).reshape(-1), np.asarray(done, np.float32).reshape(-1)
        n = obs.shape[0]
        expected = {"obs": (n, self.obs_dim), "act": (n, self.act_dim), "rew": (n,), "next_obs": (n, self.obs_dim), "done": (n,)}
        for name, array in zip(expected, (obs, act, rew, next_obs, done)):
            if array.shape != expected[name]:
                raise ValueError(f"add_batch: {name} has shape {array.shape}, expected {expected[name]}")
        self.added += n
        if n > self.capacity:  # only the newest rows would survive anyway
            obs, act, rew, next_obs, done = (x[-self.capacity :] for x in (obs, act, rew, next_obs, done))
            self.pos, n = (self.pos + n - self.capacity) % self.capacity, self.capacity
        rows = (self.pos + np.arange(n)) % self.capacity
        self.obs[rows], self.act[rows], self.rew[rows], self.next_obs[rows], self.done[rows] = obs, act, rew, next_obs, done
        self.pos = (self.pos + n) % self.capacity
        self.size = min(self.size + n, self.capacity)

    def sample(self, n: int, rng: np.random.Generator) -> Batch[np.ndarray]:
        """``n`` rows drawn uniformly with replacement from the filled ones."""
        if self.size == 0:
            raise ValueError("cannot sample from an empty replay buffer")
        rows = rng.integers(0, self.size, size=n)
        return Batch(self.obs[rows], self.act[rows], self.rew[rows], self.next_obs[rows], self.done[rows])

    def rows_since(self, start: int) -> tuple[int, dict[str, np.ndarray]]:
        """The rows added since ``start`` rows had been added that the ring still holds, oldest
        first, as ``(index of the first, {column: rows})``: what a checkpoint journal appends."""
        first = max(int(start), self.added - self.size)
        ring = np.arange(first, self.added) % self.capacity
        return first, {name: getattr(self, name)[ring].copy() for name in COLUMNS}

    def put_rows(self, first: int, columns: dict[str, np.ndarray]) -> None:
        """Write rows that were added as indices ``first, first + 1, ...`` back into the ring."""
        n: int | None = None
        for name in COLUMNS:
            column, like = np.asarray(columns[name]), getattr(self, name)
            if column.dtype != like.dtype or column.shape[1:] != like.shape[1:] or (n is not None and len(column) != n):
                raise ValueError(f"replay rows: column {name!r} does not fit the buffer")
            n = len(column)
        assert n is not None  # COLUMNS is not empty
        keep = np.arange(first, first + n) >= first + n - self.capacity  # older rows were overwritten
        ring = np.arange(first, first + n)[keep] % self.capacity
        for name in COLUMNS:
            getattr(self, name)[ring] = np.asarray(columns[name])[keep]

    def set_counters(self, added: int) -> None:
        """Position and fill after ``added`` rows in all (with :meth:`put_rows`, a resumed buffer)."""
        if isinstance(added, bool) or not isinstance(added, int) or added < 0:
            raise ValueError(f"replay rows added must be an integer >= 0, got {added!r}")
        self.added, self.pos, self.size = added, added % self.capacity, min(added, self.capacity)


COLUMNS = ("obs", "act", "rew", "next_obs", "done")


def split_counts(n: int, weights: list[float]) -> list[int]:
    """``round(n * w_k / sum(w))`` per kind, fixed by largest remainder so the counts sum to ``n``."""
    total = sum(weights)
    exact = [n * w / total for w in weights]
    counts = [math.floor(x) for x in exact]
    by_remainder = sorted(range(len(weights)), key=lambda k: counts[k] - exact[k])
    for k in by_remainder[: n - sum(counts)]:
        counts[k] += 1
    return counts


class MultitaskReplay:
    """One :class:`ReplayBuffer` per env kind; a batch takes a fixed share from each.

    With weights 0.8/0.2 a batch of 256 is 205 clean and 51 poisoned rows, however many
    envs of each kind filled the buffers.
    """

    def __init__(self, buffers: dict[str, ReplayBuffer], weights: dict[str, float]):
        if not buffers:
            raise ValueError("MultitaskReplay needs at least one buffer")
        if set(weights) != set(buffers):
            raise ValueError(f"mix weights name kinds {sorted(weights)}, but the buffers are {sorted(buffers)}")
        check_weights(weights)
        self.buffers = dict(buffers)
        self.weights = {kind: float(weights[kind]) for kind in buffers}

    @classmethod
    def create(cls, weights: dict[str, float], capacity: int, obs_dim: int, act_dim: int) -> MultitaskReplay:
        """Empty buffers of ``capacity`` rows, one per kind named in ``weights``."""
        return cls({kind: ReplayBuffer(capacity, obs_dim, act_dim) for kind in weights}, weights)

    def __getitem__(self, kind: str) -> ReplayBuffer:
        return self.buffers[kind]

    def __len__(self) -> int:
        return sum(len(b) for b in self.buffers.values())

    def sample(self, n: int, rng: np.random.Generator) -> Batch[np.ndarray]:
        """``n`` rows: each kind's share (see :func:`split_counts`), kinds in buffer order."""
        counts = split_counts(n, list(self.weights.values()))
        parts = []
        for (kind, buffer), count in zip(self.buffers.items(), counts):
            if count == 0:
                continue
            if len(buffer) == 0:
                raise ValueError(f"the {kind!r} replay buffer is empty but its mix weight is {self.weights[kind]}")
            parts.append(buffer.sample(count, rng))
        if len(parts) == 1:
            return parts[0]
        return Batch(*(np.concatenate(columns) for columns in zip(*parts)))


# ----- observation normalisation -----------------------------------------------------------
class RunningNorm:
    """Running mean and variance of observations (parallel Welford, float64); standardises and clips.

    The MuJoCo observation mixes scales: the accelerometer reads ~9.8 +- 4 while the
    lidar bins, which carry the task, are mostly 0 and rarely above 0.5. Standardising puts
    them on one scale for the first tanh layer. The replay stores raw observations and every
    batch is standardised with the current statistics, so old and new rows agree.
    """

    def __init__(self, dim: int, clip: float = 10.0, eps: float = 1e-8):
        self.dim, self.clip, self.eps = int(dim), float(clip), float(eps)
        self.count = 0
        self.mean = np.zeros(self.dim)
        self.m2 = np.zeros(self.dim)  # sum of squared deviations

    def update(self, obs: np.ndarray) -> None:
        """Fold a batch (n, dim) of observations into the statistics."""
        obs = np.asarray(obs, np.float64).reshape(-1, self.dim)
        n = obs.shape[0]
        if n == 0:
            return
        batch_mean = obs.mean(0)
        batch_m2 = ((obs - batch_mean) ** 2).sum(0)
        total = self.count + n
        delta = batch_mean - self.mean
        self.mean = self.mean + delta * (n / total)
        self.m2 = self.m2 + batch_m2 + delta**2 * (self.count * n / total)
        self.count = total

    @property
    def std(self) -> np.ndarray:
        var = self.m2 / self.count if self.count else np.ones(self.dim)
        return np.sqrt(var + self.eps)

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        """``clip((obs - mean) / std)`` as float32; the identity before any update."""
        if self.count == 0:
            return np.asarray(obs, np.float32)
        return np.clip((np.asarray(obs) - self.mean) / self.std, -self.clip, self.clip).astype(np.float32)

    def state_dict(self) -> dict:
        return {"count": self.count, "mean": self.mean.copy(), "m2": self.m2.copy()}

    def load_state_dict(self, state: dict) -> None:
        self.count = int(state["count"])
        mean, m2 = (np.array(state[k].numpy() if isinstance(state[k], torch.Tensor) else state[k], np.float64) for k in ("mean", "m2"))
        if mean.shape != self.mean.shape or m2.shape != self.m2.shape:
            raise ValueError(f"observation normaliser state has shape {mean.shape}, expected {self.mean.shape}")
        self.mean, self.m2 = mean, m2


# ----- networks --------------------------------------------------------------------------
def weight_dims(weights) -> tuple[int, int, int, int, bool]:
    """(obs_dim, act_dim, depth, width, obs_norm) of an OPAC² agent's flat weights (what a
    bare weights file says about the net it fits); ValueError if they are no OPAC² agent's."""
    layers = sorted((int(k.split(".")[2]), v) for k, v in weights.items() if re.fullmatch(r"policy\.mean\.\d+\.weight", k))
    if not layers or not all(k.startswith(("policy.", "q.", "v.", "v_target.", "obs_norm.")) for k in weights):
        raise ValueError("not an OPAC² agent's weights")
    first, last = layers[0][1], layers[-1][1]
    return (
        int(first.shape[1]),
        int(last.shape[0]),
        len(layers) - 1,
        int(first.shape[0]) if len(layers) > 1 else 0,
        any(k.startswith("obs_norm.") for k in weights),
    )


def mlp(in_dim: int, out_dim: int, depth: int, width: int, generator: torch.Generator, out_gain: float = 1.0) -> nn.Sequential:
    """``depth`` tanh hidden layers of ``width``; orthogonal init drawn from ``generator``."""
    layers: list[nn.Module] = []
    for i in range(depth):
        layers += [nn.Linear(in_dim if i == 0 else width, width), nn.Tanh()]
    layers.append(nn.Linear(width if depth else in_dim, out_dim))
    linears = [m for m in layers if isinstance(m, nn.Linear)]
    for layer in linears:
        nn.init.orthogonal_(layer.weight, gain=out_gain if layer is linears[-1] else math.sqrt(2), generator=generator)
        nn.init.zeros_(layer.bias)
    return nn.Sequential(*layers)


def squashed_log_prob(u: torch.Tensor, mean: torch.Tensor, log_std: torch.Tensor) -> torch.Tensor:
    """log density of ``a = tanh(u)``, ``u ~ N(mean, exp(log_std))``, summed over action dims.

    Change of variables: ``log p(a) = log N(u) - log(1 - tanh(u)^2)``, the Jacobian term in
    the stable form ``2 (log 2 - u - softplus(-2u))``. Taking ``u`` rather than ``a`` avoids
    ``atanh`` of actions rounded to +-1.
    """
    z = (u - mean) * torch.exp(-log_std)
    gaussian = -0.5 * z.pow(2) - log_std - 0.5 * math.log(2 * math.pi)
    log_jacobian = 2.0 * (math.log(2.0) - u - nn.functional.softplus(-2.0 * u))
    return (gaussian - log_jacobian).sum(-1)


class GaussianPolicy(nn.Module):
    """``tanh(u)``, ``u ~ N(mean(s), exp(log_std))``; the log-std does not depend on the state."""

    def __init__(self, obs_dim: int, act_dim: int, depth: int, width: int, generator: torch.Generator, log_std_init: float = 0.0):
        super().__init__()
        # A small last layer starts every state at about the same, centred action distribution.
        self.mean = mlp(obs_dim, act_dim, depth, width, generator, out_gain=0.01)
        self.log_std = nn.Parameter(torch.full((act_dim,), float(log_std_init)))

    def forward(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Mean (n, A) and log-std (A,), the latter clamped to [LOG_STD_MIN, LOG_STD_MAX]."""
        return self.mean(obs), self.log_std.clamp(LOG_STD_MIN, LOG_STD_MAX)

    def sample(self, obs: torch.Tensor, generator: torch.Generator, samples: int = 1) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """Action ``a`` in (-1, 1), its pre-tanh ``u`` (no gradient), and the mean and log-std.

        ``samples`` K > 1 draws K actions per state (row ``j * n + i`` is state ``i``'s j-th);
        the mean net still runs once per state and the returned mean is repeated to match.
        """
        mean, log_std = self(obs)
        if samples > 1:
            mean = mean.repeat(samples, 1)
        noise = torch.randn(mean.shape, generator=generator, device=generator.device).to(mean.device)
        u = (mean + noise * log_std.exp()).detach()
        return squash(u), u, mean, log_std

    def entropy(self) -> torch.Tensor:
        """Entropy of the pre-tanh Gaussian: closed form, and the same in every state."""
        log_std = self.log_std.clamp(LOG_STD_MIN, LOG_STD_MAX)
        return (log_std + 0.5 * (1.0 + math.log(2 * math.pi))).sum()


def squash(u: torch.Tensor) -> torch.Tensor:
    """``tanh(u)`` kept ``ACTION_EPS`` inside (-1, 1)."""
    return torch.tanh(u).clamp(-1.0 + ACTION_EPS, 1.0 - ACTION_EPS)


class QNet(nn.Module):
    """``Q(s, a)``: an MLP of the concatenated observation and action."""

    def __init__(self, obs_dim: int, act_dim: int, depth: int, width: int, generator: torch.Generator):
        super().__init__()
        self.net = mlp(obs_dim + act_dim, 1, depth, width, generator)

    def forward(self, obs: torch.Tensor, act: torch.Tensor) -> torch.Tensor:
        return self.net(torch.cat((obs, act), dim=-1)).squeeze(-1)


class VNet(nn.Module):
    """``V(s)``: an MLP of the observation."""

    def __init__(self, obs_dim: int, depth: int, width: int, generator: torch.Generator):
        super().__init__()
        self.net = mlp(obs_dim, 1, depth, width, generator)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return self.net(obs).squeeze(-1)


# ----- the algorithm ---------------------------------------------------------------------
class OPAC2:
    """Networks, target and optimisers; :meth:`act` for rollouts, :meth:`update` to learn."""

    def __init__(self, obs_dim: int, act_dim: int, cfg: OPAC2Config, generator: torch.Generator, device: torch.device | str = "cpu"):
        cfg.check()
        self.cfg, self.generator, self.device = cfg, generator, torch.device(device)
        d, w = cfg.depth, cfg.width
        self.policy = GaussianPolicy(obs_dim, act_dim, d, w, generator, cfg.log_std_init).to(self.device)
        self.q = QNet(obs_dim, act_dim, d, w, generator).to(self.device)
        self.v = VNet(obs_dim, d, w, generator).to(self.device)
        self.v_target = copy.deepcopy(self.v).requires_grad_(False)
        self.obs_norm = RunningNorm(obs_dim, cfg.obs_clip) if cfg.obs_norm else None
        fused = self.device.type in ("cpu", "cuda")  # one kernel for all parameters
        self.policy_opt = torch.optim.Adam(self.policy.parameters(), lr=cfg.lr, fused=fused)
        self.q_opt = torch.optim.Adam(self.q.parameters(), lr=cfg.lr, fused=fused)
        self.v_opt = torch.optim.Adam(self.v.parameters(), lr=cfg.lr, fused=fused)

    @torch.inference_mode()
    def act(self, obs: np.ndarray, deterministic: bool = False, generator: torch.Generator | None = None) -> np.ndarray:
        """Actions (n, A) for raw observations (n, O): sampled, or ``tanh(mean)`` for evaluation."""
        obs_t = torch.as_tensor(self.normalize(obs), device=self.device)
        if deterministic:
            action = squash(self.policy(obs_t)[0])
        else:
            action = self.policy.sample(obs_t, generator or self.generator)[0]
        return action.cpu().numpy()

    def normalize(self, obs: np.ndarray) -> np.ndarray:
        """Raw observations as the networks see them (float32; standardised with ``obs_norm``)."""
        if self.obs_norm is None:
            return np.asarray(obs, np.float32)
        return self.obs_norm(obs)

    def observe(self, obs: np.ndarray) -> None:
        """Fold newly seen raw observations into the normaliser (no-op without ``obs_norm``)."""
        if self.obs_norm is not None:
            self.obs_norm.update(obs)

    def batch_arrays(self, batch: Batch[np.ndarray]) -> Batch[np.ndarray]:
        """A replay batch as the networks take it, still on the host: observations normalised."""
        if self.obs_norm is not None:
            batch = batch._replace(obs=self.obs_norm(batch.obs), next_obs=self.obs_norm(batch.next_obs))
        return Batch(*(np.ascontiguousarray(x) for x in batch))

    def batch_tensors(self, batch: Batch[np.ndarray]) -> Batch[torch.Tensor]:
        """A replay batch as the networks take it: observations normalised, tensors on the device."""
        return Batch(*(torch.from_numpy(x).to(self.device) for x in self.batch_arrays(batch)))

    @torch.no_grad()
    def q_targets(self, rew: torch.Tensor, next_obs: torch.Tensor, done: torch.Tensor) -> torch.Tensor:
        """``r + gamma (1 - done) V_bar(s')``: a terminal transition's target is its reward."""
        return rew + self.cfg.gamma * (1.0 - done) * self.v_target(next_obs)

    def update(self, replay: MultitaskReplay | ReplayBuffer, rng: np.random.Generator) -> dict[str, float]:
        """One Adam step on V, then Q, then pi, each on a fresh batch; then the Polyak step."""
        cfg = self.cfg

        # V: regress on Q averaged over the current policy.
        b = self.batch_tensors(replay.sample(cfg.batch_size, rng))
        k = cfg.action_samples
        with torch.no_grad():
            obs_k = b.obs.repeat(k, 1)  # row j * batch + i is state i's j-th action
            action, _, _, _ = self.policy.sample(obs_k, self.generator)
            v_goal = self.q(obs_k, action).view(k, -1).mean(0)
        v_loss = (self.v(b.obs) - v_goal).pow(2).mean()
        self.v_opt.zero_grad(set_to_none=True)
        v_loss.backward()
        self.v_opt.step()

        # Q: one-step TD target through the slow V_bar.
        b = self.batch_tensors(replay.sample(cfg.batch_size, rng))
        q_goal = self.q_targets(b.rew, b.next_obs, b.done)
        q = self.q(b.obs, b.act)
        q_loss = (q - q_goal).pow(2).mean()
        self.q_opt.zero_grad(set_to_none=True)
        q_loss.backward()
        self.q_opt.step()

        # pi: score-function step weighted by the normalised advantage of a fresh action.
        b = self.batch_tensors(replay.sample(cfg.batch_size, rng))
        action, u, mean_k, log_std = self.policy.sample(b.obs, self.generator, samples=k)
        with torch.no_grad():
            advantage = self.q(b.obs.repeat(k, 1), action) - self.v(b.obs).repeat(k)
            advantage = (advantage - advantage.mean()) / (advantage.std() + ADV_EPS)
        log_prob = squashed_log_prob(u, mean_k, log_std)
        entropy = self.policy.entropy()
        policy_loss = -(advantage * log_prob).mean() - cfg.entropy_coef * entropy
        self.policy_opt.zero_grad(set_to_none=True)
        policy_loss.backward()
        self.policy_opt.step()

        self.polyak_update()
        return {
            "v_loss": v_loss.item(),
            "q_loss": q_loss.item(),
            "policy_loss": policy_loss.item(),
            "q_mean": q.mean().item(),
            "entropy": entropy.item(),
            "log_prob": log_prob.mean().item(),
        }

    def set_lr(self, lr: float) -> None:
        """The learning rate of all three optimisers (the training loop's decay schedule)."""
        for opt in (self.policy_opt, self.q_opt, self.v_opt):
            for group in opt.param_groups:
                group["lr"] = lr

    @torch.no_grad()
    def polyak_update(self) -> None:
        """``V_bar <- polyak * V_bar + (1 - polyak) * V``, parameter by parameter."""
        target: list[torch.Tensor] = list(self.v_target.parameters())
        online: list[torch.Tensor] = list(self.v.parameters())
        torch._foreach_mul_(target, self.cfg.polyak)
        # Scale first, then add (not add with alpha, which may fuse into an FMA): the result is
        # then exactly the float32 value of polyak * old + (1 - polyak) * new.
        torch._foreach_add_(target, torch._foreach_mul(online, 1.0 - self.cfg.polyak))

    # ----- checkpoints -----------------------------------------------------------------------
    def state_dict(self) -> dict:
        """Everything an exact resume needs from the agent: nets, target, optimisers, noise RNG."""
        return {
            "policy": self.policy.state_dict(),
            "q": self.q.state_dict(),
            "v": self.v.state_dict(),
            "v_target": self.v_target.state_dict(),
            "policy_opt": self.policy_opt.state_dict(),
            "q_opt": self.q_opt.state_dict(),
            "v_opt": self.v_opt.state_dict(),
            "generator": self.generator.get_state(),
            "obs_norm": None
            if self.obs_norm is None
            else {k: torch.from_numpy(v) if isinstance(v, np.ndarray) else v for k, v in self.obs_norm.state_dict().items()},
        }

    def load_state_dict(self, state: dict) -> None:
        for name in ("policy", "q", "v", "v_target", "policy_opt", "q_opt", "v_opt"):
            getattr(self, name).load_state_dict(state[name])
        for name in ("policy_opt", "q_opt", "v_opt"):
            check_optimizer_state(getattr(self, name), name)
        self.generator.set_state(state["generator"])
        if self.obs_norm is not None:
            self.obs_norm.load_state_dict(state["obs_norm"])

    NETS = ("policy", "q", "v", "v_target")

    def weights(self) -> dict[str, torch.Tensor]:
        """The model.pt of an OPAC² agent: one flat state dict (``policy.*``, ``q.*``, ``v.*``,
        ``v_target.*`` and the observation normaliser's ``obs_norm.count/mean/m2``), on the CPU."""
        flat = {f"{name}.{k}": v.detach().cpu() for name in self.NETS for k, v in getattr(self, name).state_dict().items()}
        if self.obs_norm is not None:
            flat.update({f"obs_norm.{k}": torch.as_tensor(v) for k, v in self.obs_norm.state_dict().items()})
        return flat

    def load_weights(self, flat: dict) -> None:
        """Load :meth:`weights` (or the nested form of format-1 folders: ``{"policy": {...}, ...}``).

        Raises KeyError / ValueError / RuntimeError when the tensors do not fit this agent.
        """
        flat = self.flat_weights(flat)
        for name in self.NETS:
            prefix = f"{name}."
            getattr(self, name).load_state_dict({k[len(prefix) :]: v for k, v in flat.items() if k.startswith(prefix)})
        norm_keys = {k for k in flat if k.startswith("obs_norm.")}
        if self.obs_norm is None:
            if norm_keys:
                raise ValueError("it holds obs_norm statistics, the config has opac2.obs_norm false")
            return
        norm = {k.split(".", 1)[1]: flat[k] for k in norm_keys}
        self.obs_norm.load_state_dict({"count": int(norm["count"]), "mean": norm["mean"].numpy(), "m2": norm["m2"].numpy()})
        if self.obs_norm.mean.shape != self.obs_norm.m2.shape or self.obs_norm.mean.shape != (self.policy_obs_dim,):
            raise ValueError("obs_norm does not fit the observation")

    @classmethod
    def flat_weights(cls, obj) -> dict:
        """A model.pt's content as one flat dict (format-1 folders nest one dict per net)."""
        if not isinstance(obj, dict):
            raise TypeError("it holds no state dict")
        if all(isinstance(obj.get(name), dict) for name in cls.NETS):
            return {f"{name}.{k}": v for name, sub in obj.items() if isinstance(sub, dict) for k, v in sub.items()}
        return obj

    @property
    def policy_obs_dim(self) -> int:
        first = next(m for m in self.policy.modules() if isinstance(m, nn.Linear))
        return int(first.in_features)
