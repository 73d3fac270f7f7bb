"""PPO as torch-ac runs it (the paper's LavaWorld stack), written to be read top to bottom.

torch-ac specifics kept on purpose, because they are part of "the paper's setup":
SAME_STEP autoreset, done = terminated or truncated (no bootstrap on timeouts), GAE,
clipped value loss, *no* advantage normalisation, random minibatches over the whole
rollout. The vector env is any ``gymnasium.vector.VectorEnv`` following the contract in
:mod:`rlbackdoors.envs.vector`, so the MiniGrid and batched engines are interchangeable.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from rlbackdoors.algos.obs import Obs, empty_buffer, obs_map, store, to_torch
from rlbackdoors.config import PPOConfig
from rlbackdoors.models import ActorCritic


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

    @property
    def num_frames(self) -> int:
        return int(self.actions.shape[0])


def sample_actions(logits: torch.Tensor, generator: torch.Generator | None = None, u: torch.Tensor | None = None) -> torch.Tensor:
    """Categorical sample by inverse CDF from one uniform per row (``u``, drawn here if not given).

    Cheaper per call than ``torch.distributions.Categorical``; the rollout draws all its
    uniforms at once and passes one row of them per step.
    """
    if u is None:
        u = torch.rand(logits.shape[0], generator=generator, device=logits.device)
    cdf = torch.softmax(logits, dim=-1).cumsum(dim=-1)
    return (cdf <= u[:, None] * cdf[:, -1:]).sum(1).clamp_(max=logits.shape[1] - 1)


class PPO:
    def __init__(self, model: ActorCritic, cfg: PPOConfig, device: torch.device, generator: torch.Generator):
        self.model = model
        self.cfg = cfg
        self.device = device
        self.generator = generator
        # fused Adam: one kernel for all parameters (4x faster than the per-tensor loop on CPU).
        self.optimizer = torch.optim.Adam(model.parameters(), lr=cfg.lr, eps=cfg.adam_eps, fused=True)

    @torch.inference_mode()
    def collect(self, envs, obs: np.ndarray | dict) -> tuple[Rollout, np.ndarray | dict]:
        """Run the policy for ``cfg.rollout`` steps from ``obs``; return the rollout and the next obs.

        The loop body is kept to the minimum of torch calls (one forward, one sample): the
        uniforms for sampling are drawn for the whole rollout up front, and log-probabilities
        are computed from the stored logits after the loop, in one call.
        """
        T, B = self.cfg.rollout, envs.num_envs
        obs_buf = empty_buffer(obs, T)
        actions = torch.empty((T, B), dtype=torch.long)
        logits_buf = torch.empty((T, B, envs.single_action_space.n))
        values = torch.empty((T, B))
        uniforms = torch.rand((T, B), generator=self.generator)
        rewards = np.empty((T, B), dtype=np.float64)
        dones = np.empty((T, B), dtype=bool)
        outcomes = np.empty((T, B), dtype=np.int64)
        steps = np.empty((T, B), dtype=np.int64)
        for t in range(T):
            store(obs_buf, t, obs)
            obs_t = obs_map(lambda b: b[t], obs_buf)
            logits, value = self.model(obs_map(lambda x: x.to(self.device), obs_t))
            logits_buf[t], values[t] = logits, value
            actions[t] = sample_actions(logits_buf[t], u=uniforms[t])
            obs, rewards[t], terminated, truncated, info = envs.step(actions[t].numpy())
            dones[t] = terminated | truncated
            outcomes[t], steps[t] = info["outcome"], info["steps"]
        _, next_value = self.model(to_torch(obs, self.device))
        logprobs = torch.log_softmax(logits_buf, -1).gather(2, actions[..., None]).squeeze(2)
        advantages = self._gae(torch.from_numpy(rewards).float(), torch.from_numpy(dones), values, next_value.cpu())
        returns = values + advantages
        rollout = Rollout(
            obs=obs_map(lambda b: b.reshape(T * B, *b.shape[2:]), obs_buf),
            actions=actions.reshape(-1),
            logprobs=logprobs.reshape(-1),
            values=values.reshape(-1),
            advantages=advantages.reshape(-1),
            returns=returns.reshape(-1),
            rewards=rewards,
            dones=dones,
            outcomes=outcomes,
            steps=steps,
        )
        return rollout, obs

    def _gae(self, rewards, dones, values, next_value) -> torch.Tensor:
        """Generalised advantage estimation; ``dones[t]`` cuts the trace after step t."""
        gamma, lam = self.cfg.gamma, self.cfg.gae_lambda
        advantages = torch.zeros_like(rewards)
        next_adv = torch.zeros_like(next_value)
        for t in reversed(range(rewards.shape[0])):
            mask = 1.0 - dones[t].float()
            delta = rewards[t] + gamma * next_value * mask - values[t]
            next_adv = delta + gamma * lam * next_adv * mask
            advantages[t] = next_adv
            next_value = values[t]
        return advantages

    def update(self, rollout: Rollout) -> dict[str, float]:
        """``epochs`` passes of clipped-surrogate SGD over random minibatches of the rollout."""
        cfg = self.cfg
        n = rollout.num_frames
        obs = obs_map(lambda x: x.to(self.device), rollout.obs)
        tensors = [x.to(self.device) for x in (rollout.actions, rollout.logprobs, rollout.values, rollout.advantages, rollout.returns)]
        stats = {"policy_loss": 0.0, "value_loss": 0.0, "entropy": 0.0, "grad_norm": 0.0}
        updates = 0
        for _ in range(cfg.epochs):
            order = torch.randperm(n, generator=self.generator).to(self.device)
            for start in range(0, n, cfg.batch_size):
                idx = order[start : start + cfg.batch_size]
                actions, old_logp, old_values, adv, returns = (x[idx] for x in tensors)
                logits, values = self.model(obs_map(lambda x: x[idx], obs))
                log_probs = torch.log_softmax(logits, -1)
                entropy = -(log_probs.exp() * log_probs).sum(-1).mean()
                ratio = torch.exp(log_probs.gather(1, actions[:, None]).squeeze(1) - old_logp)
                policy_loss = -torch.min(ratio * adv, ratio.clamp(1 - cfg.clip, 1 + cfg.clip) * adv).mean()
                values_clipped = old_values + (values - old_values).clamp(-cfg.clip, cfg.clip)
                value_loss = torch.max((values - returns) ** 2, (values_clipped - returns) ** 2).mean()
                loss = policy_loss - cfg.entropy_coef * entropy + cfg.value_coef * value_loss
                self.optimizer.zero_grad(set_to_none=True)
                loss.backward()
                grad_norm = nn.utils.clip_grad_norm_(self.model.parameters(), cfg.max_grad_norm, foreach=True)
                self.optimizer.step()
                stats["policy_loss"] += policy_loss.item()
                stats["value_loss"] += value_loss.item()
                stats["entropy"] += entropy.item()
                stats["grad_norm"] += float(grad_norm)
                updates += 1
        return {k: v / updates for k, v in stats.items()}
