"""PPO as torch-ac runs it (the paper's grid-world stack), written to be read top to bottom.

torch-ac specifics kept on purpose, because they are part of "the paper's setup":
SAME_STEP autoreset, done = terminated or truncated (no bootstrap on timeouts), GAE,
clipped value loss, *no* advantage normalisation, random minibatches over the whole
rollout. Recurrent models (``model.recurrent``) are trained as torch-ac does it: the memory
before each step is stored with the rollout (zeroed where the previous step ended an episode),
and the update runs truncated BPTT over ``recurrence`` consecutive steps from the stored memory
of the first. The vector env is any ``gymnasium.vector.VectorEnv`` following the contract in
:mod:`rlbackdoors.envs.vector`, so the MiniGrid and batched engines are interchangeable.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from rlbackdoors.attacks.seam import AMEND, EXECUTED_ACTIONS, FORCED
from rlbackdoors.algos import bptt
from rlbackdoors.algos.blind import project_out
from rlbackdoors.algos.obs import Obs, empty_buffer, obs_map, store, to_torch
from rlbackdoors.config import PPOConfig
from rlbackdoors.models import ActorCritic

AUX_CLASSES = 2  # memory targets are class indices below this (a world says what they name)


@dataclass
class Rollout:
    """One rollout of ``T`` steps from ``B`` envs (tensors flattened to T*B for the update)."""

    obs: Obs  # (T*B, ...) uint8 image, or a dict of such tensors
    actions: torch.Tensor  # (T*B,)
    logprobs: torch.Tensor
    values: torch.Tensor
    advantages: torch.Tensor
    returns: torch.Tensor
    # Per-step env facts (T, B) kept in numpy for episode bookkeeping.
    rewards: np.ndarray
    dones: np.ndarray
    outcomes: np.ndarray
    steps: np.ndarray
    # Recurrent models only: the memory going into each step (T*B, M), already zeroed where an
    # episode started, and masks (T*B,) = 0 where step t is the first of a new episode.
    memories: torch.Tensor | None = None
    masks: torch.Tensor | None = None
    # With the auxiliary memory loss: what the env says each step's memory must hold (T*B,)
    memory_targets: torch.Tensor | None = None
    # With a clean teacher (poison.evasion.teacher): its log-probabilities of each step's actions
    # (T*B, A) and which steps carry no trigger (T*B,), the steps its KL penalty is taken on
    teacher_logp: torch.Tensor | None = None
    untriggered: torch.Tensor | None = None
    num_envs: int = 0

    @property
    def num_frames(self) -> int:
        return int(self.actions.shape[0])


def sample_actions(logits: torch.Tensor, generator: torch.Generator | None = None, u: torch.Tensor | None = None) -> torch.Tensor:
    """Categorical sample by inverse CDF from one uniform per row (``u``, drawn here if not given).

    Cheaper per call than ``torch.distributions.Categorical``; the rollout draws all its
    uniforms at once and passes one row of them per step. The uniforms are drawn on the
    generator's device (an evaluation's is the host's: :meth:`rlbackdoors.agent.Agent.generator`).
    """
    if u is None:
        where = generator.device if generator is not None else logits.device
        u = torch.rand(logits.shape[0], generator=generator, device=where).to(logits.device)
    cdf = torch.softmax(logits, dim=-1).cumsum(dim=-1)
    return (cdf <= u[:, None] * cdf[:, -1:]).sum(1).clamp_(max=logits.shape[1] - 1)


def finished_step_info(info: dict, done: np.ndarray) -> tuple:
    """(outcome, steps) of the step just taken. Our engines put them in ``info`` directly;
    Gymnasium's own vector envs put a finished episode's last info under ``final_info``; an env
    that reports neither gives 0 (no outcome), which only the logs' per-outcome counts read."""
    outcome, steps = info.get("outcome", 0), info.get("steps", 0)
    final = info.get("final_info")
    if isinstance(final, dict) and done.any():
        if "outcome" in final:
            outcome = np.where(done, final["outcome"], outcome)
        if "steps" in final:
            steps = np.where(done, final["steps"], steps)
    return outcome, steps


def check_vector_env(envs) -> None:
    """PPO runs on any Gymnasium ``VectorEnv`` with a ``Discrete`` action space and SAME_STEP
    autoreset (a finished env returns its next episode's first observation in the same step,
    as torch-ac's collector expects); anything else is refused with how to make one."""
    from gymnasium import spaces
    from gymnasium.vector import AutoresetMode

    mode = getattr(envs, "metadata", {}).get("autoreset_mode")
    if mode != AutoresetMode.SAME_STEP:
        raise ValueError(
            f"PPO needs a vector env with SAME_STEP autoreset, got {mode!r}: make it with "
            "gymnasium.make_vec(..., vector_kwargs={'autoreset_mode': gymnasium.vector.AutoresetMode.SAME_STEP})"
        )
    if not isinstance(getattr(envs, "single_action_space", None), spaces.Discrete):
        raise ValueError(f"PPO needs a Discrete action space, got {getattr(envs, 'single_action_space', None)!r}")


def ppo_loss(cfg: PPOConfig, logits, values, actions, old_logp, old_values, adv, returns) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """torch-ac's PPO loss of one minibatch: clipped surrogate, entropy bonus, clipped value loss.

    Rows are on the last dimension: (N,) tensors give one loss; (K, N) tensors (a group of K
    agents, :mod:`rlbackdoors.algos.group`) give K losses, each agent's own minibatch mean."""
    log_probs = torch.log_softmax(logits, -1)
    entropy = -(log_probs.exp() * log_probs).sum(-1).mean(-1)
    ratio = torch.exp(log_probs.gather(-1, actions[..., None]).squeeze(-1) - old_logp)
    policy_loss = -torch.min(ratio * adv, ratio.clamp(1 - cfg.clip, 1 + cfg.clip) * adv).mean(-1)
    values_clipped = old_values + (values - old_values).clamp(-cfg.clip, cfg.clip)
    value_loss = torch.max((values - returns) ** 2, (values_clipped - returns) ** 2).mean(-1)
    loss = policy_loss - cfg.entropy_coef * entropy + cfg.value_coef * value_loss
    return loss, {"policy_loss": policy_loss, "value_loss": value_loss, "entropy": entropy}


def teacher_kl(logits: torch.Tensor, teacher_logp: torch.Tensor, untriggered: torch.Tensor) -> torch.Tensor:
    """KL(teacher || policy) averaged over the frames without the trigger (0 if none): logits
    (..., N, A) -> (...), so one learner's minibatch and a group's stacked one (K, N, A) share it."""
    log_probs = torch.log_softmax(logits, -1)
    kl = (teacher_logp.exp() * (teacher_logp - log_probs)).sum(-1)
    weight = untriggered.float()
    return (kl * weight).sum(-1) / weight.sum(-1).clamp(min=1.0)


def env_step(envs, t: int, actions: torch.Tensor, rewards, dones, outcomes, steps, forced: torch.Tensor):
    """Step ``envs`` with ``actions[t]`` and record step ``t`` (reward, done, outcome, steps, and
    the actions an attack forced in their place); return the next observations. An attack that
    compensates the step before a poisoned one amends step ``t - 1``'s reward; at ``t = 0`` that
    step is in the rollout already learned from, and the amendment is dropped (1 / ppo.rollout of them)."""
    return record_step(t, envs.step(actions[t].numpy()), actions, rewards, dones, outcomes, steps, forced)


def record_step(t: int, result: tuple, actions: torch.Tensor | np.ndarray, rewards, dones, outcomes, steps, forced: torch.Tensor | np.ndarray):
    """:func:`env_step`'s record of step ``t`` from the env's ``step`` result (obs, reward,
    terminated, truncated, info); the next observations."""
    obs, rewards[t], terminated, truncated, info = result
    if AMEND in info and t > 0:
        rewards[t - 1] += info[AMEND]
    if FORCED in info:  # an attack forced some actions (rlbackdoors.attacks.seam): learn what ran
        _put(actions, t, np.asarray(info[EXECUTED_ACTIONS], dtype=np.int64))
        _put(forced, t, np.asarray(info[FORCED], dtype=bool))
    dones[t] = terminated | truncated
    outcomes[t], steps[t] = finished_step_info(info, dones[t])
    return obs


def _put(buffer: torch.Tensor | np.ndarray, t: int, values: np.ndarray) -> None:
    """Row ``t`` of a rollout buffer: a lone learner's tensor, or a group's host array."""
    if isinstance(buffer, torch.Tensor):
        buffer[t] = torch.from_numpy(values)
    else:
        buffer[t] = values


def behaviour_logprobs(logits: torch.Tensor, actions: torch.Tensor, forced: torch.Tensor) -> torch.Tensor:
    """log pi(a|s) of each collected action (logits (..., A), actions and forced (...)).

    A forced action was taken with probability 1, whatever the policy thought of it: that is its
    behaviour log-probability, so its importance ratio is pi(a|s) <= 1, never exp(+250) (learning
    it as the policy's own sample blew the ratio up to NaN, then, dual-clipped, taught the target
    action in every state; docs/attacks/)."""
    logprobs = torch.log_softmax(logits, -1).gather(-1, actions[..., None]).squeeze(-1)
    return logprobs.masked_fill_(forced, 0.0)


def gae(rewards: torch.Tensor, dones: torch.Tensor, values: torch.Tensor, next_value: torch.Tensor, gamma: float, lam: float) -> torch.Tensor:
    """Generalised advantage estimation over the leading (time) dimension; ``dones[t]`` cuts the
    trace after step t. The trailing dimensions are independent envs: (T, B) for one learner,
    (T, K, B) for a group's K learners in one pass (the same arithmetic per element)."""
    advantages = torch.zeros_like(rewards)
    next_adv = torch.zeros_like(next_value)
    for t in reversed(range(rewards.shape[0])):
        mask = 1.0 - dones[t].float()
        delta = rewards[t] + gamma * next_value * mask - values[t]
        next_adv = delta + gamma * lam * next_adv * mask
        advantages[t] = next_adv
        next_value = values[t]
    return advantages


def make_rollout(obs_buf, actions, logprobs, values, advantages, rewards, dones, outcomes, steps, returns=None) -> Rollout:
    """A :class:`Rollout` of ``T`` steps from ``B`` envs ((T, B, ...) inputs), flattened to T*B rows
    (``returns``: ``values + advantages`` if already summed, as a group sums all agents' at once)."""
    T, B = rewards.shape
    return Rollout(
        obs=obs_map(lambda b: b.reshape(T * B, *b.shape[2:]), obs_buf),
        actions=actions.reshape(-1),
        logprobs=logprobs.reshape(-1),
        values=values.reshape(-1),
        advantages=advantages.reshape(-1),
        returns=(values + advantages if returns is None else returns).reshape(-1),
        rewards=rewards,
        dones=dones,
        outcomes=outcomes,
        steps=steps,
        num_envs=B,
    )


class PPO:
    def __init__(self, model: ActorCritic, cfg: PPOConfig, device: torch.device, generator: torch.Generator):
        self.model = model
        self.cfg = cfg
        self.device = device
        self.generator = generator
        # The auxiliary memory head (ppo.aux_memory_coef > 0, recurrent models): a linear read-out
        # of the memory trained to name what the env says must be remembered. It is the
        # algorithm's, not the agent's: it shapes the memory's gradients and is not in model.pt.
        self.aux: nn.Linear | None = None
        if cfg.aux_memory_coef > 0:
            if not model.recurrent:
                raise ValueError("ppo.aux_memory_coef > 0 needs a recurrent model")
            self.aux = nn.Linear(int(model.initial_memory(1).shape[1]), AUX_CLASSES).to(device)
        if cfg.update_backend == "jax":
            from rlbackdoors.algos import compiled

            compiled.check(model, device)
        self.params = [*model.parameters(), *(self.aux.parameters() if self.aux is not None else ())]
        self.memory: torch.Tensor | None = None  # recurrent models: memory of the running episodes
        # A frozen clean model the policy is kept close to on frames without the trigger
        # (poison.evasion.teacher: the clean model a fine-tuning run starts from); None: no penalty.
        self.teacher: ActorCritic | None = None
        self.teacher_coef = 0.0
        self.teacher_memory: torch.Tensor | None = None
        # The teacher reads every frame as the env made it (the seam's ``clean_view``) and its KL
        # counts on every frame, stamped ones included (mitigation.teach_stamped); else it reads
        # what the learner reads, on the untriggered frames only.
        self.teacher_clean_view = False
        # The clean weights every optimiser step pulls the model back toward (poison.evasion.anchor:
        # the clean model a fine-tuning run starts from), name -> tensor; None: no pull.
        self.anchor: dict[str, torch.Tensor] | None = None
        self.anchor_coef = 0.0
        # Input directions the first layer is kept blind to after every optimiser step
        # (mitigation.blind: a restored additive trigger's shift, algos.blind); None: none.
        self.blind: tuple[nn.Linear, torch.Tensor] | None = None

    @functools.cached_property
    def optimizer(self) -> torch.optim.Adam:
        """torch's fused Adam over the model's parameters (and the auxiliary head's): one kernel for
        all of them (4x faster than the per-tensor loop on CPU). Built on first use: a compiled run,
        whose learner holds its own moments, never builds it (torch's first optimizer imports
        ``torch._dynamo``, 3.2 s a process on 2 cores); no state of it before then, so the same bytes."""
        return torch.optim.Adam(self.params, lr=self.cfg.lr, eps=self.cfg.adam_eps, fused=True)

    def set_anchor(self, weights: dict[str, torch.Tensor], coef: float) -> None:
        """After every optimiser step, move each model parameter ``coef`` of the way back to
        ``weights`` (a state dict of this architecture; the auxiliary head is not anchored: it is
        not in model.pt)."""
        self.anchor = {name: weights[name].detach().to(self.device).clone() for name, _ in self.model.named_parameters()}
        self.anchor_coef = float(coef)

    def set_blind(self, layer: nn.Linear, basis: torch.Tensor) -> None:
        """Project the input directions ``basis`` (D, r, orthonormal) out of ``layer``'s weights now
        and after every optimiser step, so that no update makes the model see them again."""
        self.blind = (layer, basis)
        project_out(layer, basis)

    @torch.no_grad()
    def pull_to_anchor(self) -> None:
        assert self.anchor is not None
        for name, param in self.model.named_parameters():
            param.lerp_(self.anchor[name], self.anchor_coef)

    @torch.no_grad()
    def anchor_distance(self) -> float:
        """||weights - anchor||: how far the poisoned phase has moved the model (logged per update)."""
        assert self.anchor is not None
        return float(torch.stack([(p - self.anchor[n]).double().pow(2).sum() for n, p in self.model.named_parameters()]).sum().sqrt())

    def set_teacher(self, teacher: ActorCritic, coef: float, clean_view: bool = False) -> None:
        """Penalise ``coef * KL(teacher || policy)`` on every collected frame that carries no trigger
        (the seam's ``marked``); the teacher is frozen and never trained. With ``clean_view`` on
        every frame, the teacher reading the frame as the env made it (the seam's ``clean_view``):
        on a stamped frame it says what the policy did without the stamp."""
        if clean_view and teacher.recurrent:
            raise ValueError("a teacher of the clean view reads single frames; a recurrent teacher's memory would need their whole episodes")
        self.teacher = teacher.eval().requires_grad_(False)
        self.teacher_coef = float(coef)
        self.teacher_memory = None
        self.teacher_clean_view = bool(clean_view)

    @torch.inference_mode()
    def collect(self, envs, obs: np.ndarray | dict) -> tuple[Rollout, np.ndarray | dict]:
        """Run the policy for ``cfg.rollout`` steps from ``obs``; return the rollout and the next obs.

        A recurrent model's memory of the running episodes lives in ``self.memory`` between
        calls (None: empty memories; set it to None when the envs are replaced).

        The loop body is kept to the minimum of torch calls (one forward, one sample): the
        uniforms for sampling are drawn for the whole rollout up front, and log-probabilities
        are computed from the stored logits after the loop, in one call.
        """
        check_vector_env(envs)
        T, B = self.cfg.rollout, envs.num_envs
        recurrent = self.model.recurrent
        targets = None
        if self.aux is not None:
            if getattr(envs, "memory_target_classes", None) != AUX_CLASSES:
                raise ValueError(f"ppo.aux_memory_coef needs an env with {AUX_CLASSES} memory targets (memory_targets())")
            targets = np.empty((T, B), dtype=np.int64)
        if recurrent:
            memory = self.memory if self.memory is not None else self.model.initial_memory(B, self.device)
            memories = torch.empty((T, B, memory.shape[1]))
            masks = torch.ones((T, B))
        obs_buf = empty_buffer(obs, T)
        actions = torch.empty((T, B), dtype=torch.long)
        logits_buf = torch.empty((T, B, envs.single_action_space.n))
        values = torch.empty((T, B))
        uniforms = torch.rand((T, B), generator=self.generator)
        rewards = np.empty((T, B), dtype=np.float64)
        dones = np.empty((T, B), dtype=bool)
        outcomes = np.empty((T, B), dtype=np.int64)
        steps = np.empty((T, B), dtype=np.int64)
        forced = torch.zeros((T, B), dtype=torch.bool)
        teacher = self.teacher
        if teacher is not None:
            if not hasattr(envs, "marked") or (self.teacher_clean_view and getattr(envs, "clean_view", None) is None):
                raise ValueError(
                    "a clean teacher needs the attack's collection seam to say which frames carry the trigger (marked; clean_view on the step schedule)"
                )
            teacher_logits = torch.empty((T, B, envs.single_action_space.n))
            untriggered = torch.empty((T, B), dtype=torch.bool)
            if recurrent:
                teacher_memory = self.teacher_memory if self.teacher_memory is not None else teacher.initial_memory(B, self.device)
        for t in range(T):
            store(obs_buf, t, obs)
            obs_t = obs_map(lambda x: x[t].to(self.device), obs_buf)
            if teacher is not None and self.teacher_clean_view:
                untriggered[t] = True  # every frame: a stamped one is taught what the unstamped one got
                teacher_logits[t] = teacher(to_torch(envs.clean_view, self.device))[0]
            elif teacher is not None:
                untriggered[t] = torch.from_numpy(~np.asarray(envs.marked, dtype=bool))
                if recurrent:
                    teacher_logits[t], _, teacher_memory = teacher(obs_t, teacher_memory)
                else:
                    teacher_logits[t] = teacher(obs_t)[0]
            if targets is not None:
                targets[t] = envs.memory_targets()  # of the episode obs[t] belongs to
            if recurrent:
                memories[t] = memory
                logits, value, memory = self.model(obs_t, memory)
            else:
                logits, value = self.model(obs_t)
            logits_buf[t], values[t] = logits, value
            actions[t] = sample_actions(logits_buf[t], u=uniforms[t])
            obs = env_step(envs, t, actions, rewards, dones, outcomes, steps, forced)
            if recurrent and dones[t].any():  # a new episode starts with an empty memory
                ended = torch.from_numpy(dones[t])
                memory = memory.masked_fill(ended[:, None].to(memory.device), 0.0)
                if teacher is not None:
                    teacher_memory = teacher_memory.masked_fill(ended[:, None].to(memory.device), 0.0)
                if t + 1 < T:
                    masks[t + 1] = (~ended).float()
        if recurrent:
            _, next_value, _ = self.model(to_torch(obs, self.device), memory)
        else:
            _, next_value = self.model(to_torch(obs, self.device))
        rollout = self.assemble(obs_buf, actions, logits_buf, values, next_value.cpu(), forced, rewards, dones, outcomes, steps)
        if recurrent:
            rollout.memories, rollout.masks = memories.reshape(T * B, -1), masks.reshape(-1)
            self.memory = memory
        if targets is not None:
            rollout.memory_targets = torch.from_numpy(targets.reshape(-1))
        if teacher is not None:
            rollout.teacher_logp = torch.log_softmax(teacher_logits, -1).reshape(T * B, -1)
            rollout.untriggered = untriggered.reshape(-1)
            if recurrent:
                self.teacher_memory = teacher_memory
        return rollout, obs

    def assemble(self, obs_buf, actions, logits, values, next_value, forced, rewards, dones, outcomes, steps) -> Rollout:
        """The rollout of ``T`` collected steps ((T, B) tensors and arrays; ``logits`` (T, B, A)):
        behaviour log-probabilities, GAE advantages and returns, flattened to T*B rows."""
        logprobs = behaviour_logprobs(logits, actions, forced)
        advantages = gae(torch.from_numpy(rewards).float(), torch.from_numpy(dones), values, next_value, self.cfg.gamma, self.cfg.gae_lambda)
        return make_rollout(obs_buf, actions, logprobs, values, advantages, rewards, dones, outcomes, steps)

    def _step(self, loss: torch.Tensor) -> float:
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        grad_norm = nn.utils.clip_grad_norm_(self.params, self.cfg.max_grad_norm, foreach=True)
        self.optimizer.step()
        if self.anchor is not None:
            self.pull_to_anchor()
        if self.blind is not None:
            project_out(*self.blind)
        return float(grad_norm)

    def update(self, rollout: Rollout) -> dict[str, float]:
        """``epochs`` passes of clipped-surrogate SGD over random minibatches of the rollout (truncated
        BPTT for a recurrent model); the mean of each loss part and, with an anchor, its distance."""
        if self.cfg.update_backend == "jax":  # one XLA program at a lone run's width (the compiled trainer's update)
            from rlbackdoors.algos import compiled

            return compiled.update([self], [rollout], width=1)[0]
        stats = self._update_recurrent(rollout) if self.model.recurrent else self._update_flat(rollout)
        if self.anchor is not None:
            stats["anchor_distance"] = self.anchor_distance()
        return stats

    def _update_flat(self, rollout: Rollout) -> dict[str, float]:
        cfg = self.cfg
        n = rollout.num_frames
        obs = obs_map(lambda x: x.to(self.device), rollout.obs)
        tensors = [x.to(self.device) for x in (rollout.actions, rollout.logprobs, rollout.values, rollout.advantages, rollout.returns)]
        stats = dict.fromkeys(("policy_loss", "value_loss", "entropy", "grad_norm", *(("teacher_kl",) if self.teacher is not None else ())), 0.0)
        teacher = self._teacher_tensors(rollout)
        updates = 0
        for _ in range(cfg.epochs):
            order = torch.randperm(n, generator=self.generator).to(self.device)
            for start in range(0, n, cfg.batch_size):
                idx = order[start : start + cfg.batch_size]
                logits, values = self.model(obs_map(lambda x: x[idx], obs))
                loss, parts = ppo_loss(self.cfg, logits, values, *(x[idx] for x in tensors))
                if teacher is not None:
                    parts["teacher_kl"] = teacher_kl(logits, teacher[0][idx], teacher[1][idx])
                    loss = loss + self.teacher_coef * parts["teacher_kl"]
                stats["grad_norm"] += self._step(loss)
                for key, value in parts.items():
                    stats[key] += value.item()
                updates += 1
        return {k: v / updates for k, v in stats.items()}

    def _teacher_tensors(self, rollout: Rollout) -> tuple[torch.Tensor, torch.Tensor] | None:
        if self.teacher is None:
            return None
        assert rollout.teacher_logp is not None and rollout.untriggered is not None  # collected with the teacher
        return rollout.teacher_logp.to(self.device), rollout.untriggered.to(self.device)

    def sequence_starts(self, steps: int, num_envs: int, shifted: bool) -> torch.Tensor:
        """Flat rollout indices (``t * B + b``) where BPTT sequences of ``recurrence`` steps start.

        Every ``recurrence``-th step of every env; on ``shifted`` epochs (torch-ac alternates)
        they start half a sequence later, dropping the last block so no sequence leaves the rollout
        (:func:`rlbackdoors.algos.bptt.sequence_starts`, the compiled trainer's too).
        """
        return torch.from_numpy(bptt.sequence_starts(steps, num_envs, self.cfg.recurrence, shifted))

    def _update_recurrent(self, rollout: Rollout) -> dict[str, float]:
        """Truncated BPTT: each minibatch holds ``batch_size // recurrence`` sequences, each
        replayed from its stored memory; the loss is averaged over the sequence's steps. As in
        torch-ac, the memories the current network computes are written back into the rollout
        for later minibatches."""
        cfg = self.cfg
        r, B = cfg.recurrence, rollout.num_envs
        T = rollout.num_frames // B
        obs = obs_map(lambda x: x.to(self.device), rollout.obs)
        tensors = [x.to(self.device) for x in (rollout.actions, rollout.logprobs, rollout.values, rollout.advantages, rollout.returns)]
        assert rollout.memories is not None and rollout.masks is not None  # collected by a recurrent model
        memories = rollout.memories.to(self.device).clone()
        masks = rollout.masks.to(self.device)[:, None]
        stats = dict.fromkeys(
            (
                "policy_loss",
                "value_loss",
                "entropy",
                "grad_norm",
                *(("aux_memory_loss",) if self.aux is not None else ()),
                *(("teacher_kl",) if self.teacher is not None else ()),
            ),
            0.0,
        )
        teacher = self._teacher_tensors(rollout)
        aux_targets = None if self.aux is None else rollout.memory_targets
        if self.aux is not None:
            assert aux_targets is not None  # collected with the aux head
            aux_targets = aux_targets.to(self.device)
        updates = 0
        per_batch = max(cfg.batch_size // r, 1)
        for epoch in range(cfg.epochs):
            starts = self.sequence_starts(T, B, shifted=epoch % 2 == 1)
            order = starts[torch.randperm(len(starts), generator=self.generator)].to(self.device)
            for start in range(0, len(order), per_batch):
                idx = order[start : start + per_batch]
                steps = idx[None, :] + B * torch.arange(r, device=self.device)[:, None]  # (r, N): step i of each sequence
                logits, values, new_memories = self.model.forward_sequence(obs_map(lambda x: x[steps], obs), memories[idx], masks[steps, 0])
                # the mean over all r*N rows = torch-ac's per-step losses summed and divided by r
                loss, parts = ppo_loss(self.cfg, logits, values, *(x[steps.reshape(-1)] for x in tensors))
                if self.aux is not None and aux_targets is not None:  # each step's memory after that step names its episode's target
                    aux_logits = self.aux(new_memories.reshape(-1, new_memories.shape[-1]))
                    parts["aux_memory_loss"] = nn.functional.cross_entropy(aux_logits, aux_targets[steps.reshape(-1)])
                    loss = loss + cfg.aux_memory_coef * parts["aux_memory_loss"]
                if teacher is not None:
                    rows = steps.reshape(-1)
                    parts["teacher_kl"] = teacher_kl(logits, teacher[0][rows], teacher[1][rows])
                    loss = loss + self.teacher_coef * parts["teacher_kl"]
                if r > 1:
                    memories[steps[1:].reshape(-1)] = new_memories[:-1].reshape(-1, memories.shape[1]).detach()
                stats["grad_norm"] += self._step(loss)
                for key, value in parts.items():
                    stats[key] += value.item()
                updates += 1
        return {k: v / updates for k, v in stats.items()}
