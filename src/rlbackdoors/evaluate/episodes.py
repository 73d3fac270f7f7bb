"""Clean and triggered evaluation: success rates and mean returns over a fixed set of layouts.

Every evaluation of every model uses the same env seeds (``eval_seed + i``), so numbers
are comparable across checkpoints and across a zoo: episode ``i`` has the same layout (start,
goal, obstacles) clean and triggered. Each episode is played to its end exactly once: no bias
toward short episodes, as "first N episodes to finish" would have. Every world is played
through the same :meth:`~rlbackdoors.agent.Agent.act`, in a batched engine where the world has
one, else in single envs stepped in lockstep.

Scoring: clean SR = episodes that end in the world's clean success in E; poisoned SR = the attack's
success in E-bar (trigger on, returns under R-bar): for the paper's env mix, episodes that end in
the world's trojan success; for an action-target attack, the target action's share of all
triggered steps; for an untargeted one, triggered episodes that miss the clean goal
(:data:`rlbackdoors.attacks.SUCCESS_KINDS`).
"""

from __future__ import annotations

from collections.abc import Callable

from dataclasses import asdict, dataclass
from typing import NamedTuple

import numpy as np
import torch

from rlbackdoors import worlds
from rlbackdoors.config import EnvConfig
from rlbackdoors.envs.outcome import Outcome

CHUNK = 50  # single envs stepped in lockstep: one batched forward pass per step for all of them


@dataclass
class EvalResult:
    """Success rates and mean returns, clean (E) and triggered (E-bar, returns under R-bar).

    ``poisoned_sr`` is trigger-seen-aware: a triggered episode in which the agent never saw
    the trigger is scored on the clean task (reaching the goal is right), one in which it saw
    the trigger on reaching the trojan outcome. ``poisoned_sr_raw`` counts trojan endings only.
    Where the trigger is in every observation (or the engine does not track sight) the two are
    equal and ``trigger_seen_rate`` is 1.

    How the other episodes ended: ``clean_trojan_rate`` (clean episodes ending in the trojan
    outcome: a good agent ~0), ``poisoned_clean_rate`` (triggered episodes reaching the clean
    goal: a clean agent ~1) and the timeouts. Worlds with close-to-trigger layouts also play
    those (clean reward): ``close_sr`` is the clean task's success there and
    ``close_trojan_rate`` the false firing of the backdoor.
    """

    clean_sr: float
    poisoned_sr: float
    clean_reward: float
    poisoned_reward: float
    episodes: int
    poisoned_sr_raw: float = float("nan")
    trigger_seen_rate: float = float("nan")
    close_sr: float = float("nan")
    close_trojan_rate: float = float("nan")
    clean_trojan_rate: float = float("nan")
    clean_timeout_rate: float = float("nan")
    poisoned_clean_rate: float = float("nan")
    poisoned_timeout_rate: float = float("nan")
    clean_mean_steps: float = float("nan")
    poisoned_mean_steps: float = float("nan")
    target_action_rate: float = float("nan")  # action-target attacks: the target's share of triggered steps (in sight of the trigger)

    def to_dict(self) -> dict:
        return asdict(self)


class Played(NamedTuple):
    """Per episode: return, outcome, whether the trigger was seen, length (and, counting a target
    action: the steps that took it, of those taken in sight of the trigger)."""

    returns: np.ndarray
    outcomes: np.ndarray
    saw: np.ndarray
    steps: np.ndarray
    target_steps: np.ndarray | None = None
    sighted_steps: np.ndarray | None = None


def _as_agent(agent):
    """An :class:`~rlbackdoors.agent.Agent`, or a bare grid model wrapped as one."""
    from rlbackdoors.agent import Agent

    return agent if isinstance(agent, Agent) else Agent.wrap(agent)


@torch.inference_mode()
def play_episodes(agent, envs, seed: int, policy: str = "sample", target_action: Callable | None = None, sight: bool = False) -> Played:
    """One episode per slot of the vector env ``envs``, all reset with ``seed``.

    Engines without trigger-seen accounting report every episode as seen. With ``target_action``
    (actions -> bool each, ``World.target_hits``) the steps taking the target are counted per
    episode: of all steps, or with ``sight`` of the steps
    whose observation shows the trigger (``envs.trigger_in_sight()``: a layout trigger is not in
    every view, and an agent cannot answer a trigger it does not see).
    """
    agent = _as_agent(agent)
    generator = torch.Generator(device=agent.device).manual_seed(int(seed))
    n = envs.num_envs
    state = agent.initial_state(n)  # one episode per slot: never reset
    obs, _ = envs.reset(seed=int(seed))
    active = np.ones(n, dtype=bool)
    returns, steps = np.zeros(n), np.zeros(n, dtype=np.int64)
    outcomes = np.zeros(n, dtype=np.int64)
    saw = np.ones(n, dtype=bool)
    target_steps = None if target_action is None else np.zeros(n, dtype=np.int64)
    sighted_steps = None if target_action is None else np.zeros(n, dtype=np.int64)
    while active.any():
        actions, state = agent.act(obs, state, deterministic=policy == "greedy", generator=generator)
        if target_action is not None and target_steps is not None and sighted_steps is not None:
            counted = active & envs.trigger_in_sight() if sight else active
            sighted_steps[counted] += 1
            target_steps[counted & target_action(np.asarray(actions))] += 1
        obs, reward, terminated, truncated, info = envs.step(actions)
        returns[active] += reward[active]
        steps[active] += 1
        finished = active & (terminated | truncated)
        outcomes[finished] = info["outcome"][finished]
        if "saw_trigger" in info:
            saw[finished] = info["saw_trigger"][finished]
        active &= ~finished
    return Played(returns, outcomes, saw, steps, target_steps, sighted_steps)


@torch.inference_mode()
def play_single_envs(agent, make_env, episodes: int, seed: int, policy: str = "sample", target_action: Callable | None = None) -> Played:
    """``episodes`` episodes of single envs from ``make_env()``, episode ``i`` reset with
    ``seed + i``, stepped ``CHUNK`` at a time with one batched ``act`` per step; with
    ``target_action`` (actions -> bool each) the steps taking the target counted (every step is
    in sight: these worlds' triggers ride with the agent)."""
    agent = _as_agent(agent)
    generator = torch.Generator(device=agent.device).manual_seed(int(seed))
    returns, steps = np.zeros(episodes), np.zeros(episodes, np.int64)
    outcomes = np.zeros(episodes, np.int64)
    target_steps = None if target_action is None else np.zeros(episodes, np.int64)
    for start in range(0, episodes, CHUNK):
        index = np.arange(start, min(start + CHUNK, episodes))
        envs = [make_env() for _ in index]
        obs = np.stack([env.reset(seed=int(seed + i))[0] for env, i in zip(envs, index)])
        active = np.ones(len(envs), bool)
        state = agent.initial_state(len(envs))
        while active.any():
            # a recurrent state covers every slot, so a recurrent agent acts for finished ones too
            rows = np.flatnonzero(active) if state is None else np.arange(len(envs))
            actions, state = agent.act(obs[rows], state, deterministic=policy == "greedy", generator=generator)
            actions = np.asarray(actions)
            hit = None if target_action is None else target_action(actions)
            for k, (row, action) in enumerate(zip(rows, actions)):
                if not active[row]:
                    continue
                obs[row], reward, terminated, truncated, info = envs[row].step(action)
                returns[index[row]] += reward
                steps[index[row]] += 1
                if hit is not None and target_steps is not None and hit[k]:
                    target_steps[index[row]] += 1
                if terminated or truncated:
                    active[row] = False
                    outcomes[index[row]] = info["outcome"]
        for env in envs:
            env.close()
    return Played(returns, outcomes, np.ones(episodes, bool), steps, target_steps, None if target_steps is None else steps.copy())


def play(
    agent, env: EnvConfig, trigger: str | None, episodes: int, seed: int, policy: str, close_k: tuple[int, int] | None = None, target_action: int | None = None
) -> Played:
    """Episodes of ``env``: E-bar where ``trigger`` is given, else E; close-to-trigger
    layouts (clean reward) with ``close_k``; counting ``target_action``'s steps where given."""
    world = env.world
    hits = None if target_action is None else world.target_hits(target_action)
    if world.vector_entry_point is None:
        if close_k is not None:
            raise ValueError(f"env {env.name!r} has no close-to-trigger envs")
        return play_single_envs(agent, lambda: env.make(trigger), episodes, seed, policy, hits)
    from rlbackdoors.poison.mix import make_vector_env

    if close_k is not None:
        envs = make_vector_env(env, trigger, [False] * episodes, [True] * episodes, close_k)
    else:
        envs = make_vector_env(env, trigger, [trigger is not None] * episodes)
    try:
        return play_episodes(agent, envs, seed, policy, hits, sight=world.trigger_sight == "frame")
    finally:
        envs.close()


def score_triggered(env_name: str, outcomes: np.ndarray, saw: np.ndarray) -> tuple[float, float, float]:
    """(trigger-seen-aware SR, raw trojan SR, trigger-seen rate) of triggered episodes.

    Seen: right iff the episode ended in the trojan outcome. Never seen: the backdoor had no
    cause to fire, so the clean task is what is right.
    """
    world = worlds.get(env_name)
    trojan = outcomes == world.trojan_success
    clean_task = outcomes == world.clean_success
    return float(np.mean(np.where(saw, trojan, clean_task))), float(np.mean(trojan)), float(np.mean(saw))


def evaluate(
    agent,
    env: EnvConfig,
    trigger: str | None,
    episodes: int = 100,
    seed: int = 1_000_000,
    policy: str = "sample",
    close_k: tuple[int, int] | None = None,
    success: str = "outcome",
    target_action: int | None = None,
) -> EvalResult:
    """Clean SR/reward in E and the attack's success / R-bar reward in E-bar (trigger on), same layouts.

    ``agent``: an :class:`~rlbackdoors.agent.Agent` (or a bare grid model). With
    ``trigger=None`` only the clean half is measured (poisoned numbers are NaN). With
    ``close_k`` the same layouts are also played close to the trigger. ``success`` says how the
    attack is scored (``"action"`` needs ``target_action``).
    """
    from rlbackdoors.attacks import SUCCESS_KINDS

    if success not in SUCCESS_KINDS:
        raise ValueError(f"success={success!r} is not one of {', '.join(SUCCESS_KINDS)}")
    if success == "action" and target_action is None:
        raise ValueError("an action-target attack is scored with its target_action")
    agent = _as_agent(agent)
    world = env.world
    with agent.evaluating():
        clean = play(agent, env, None, episodes, seed, policy)
        result = EvalResult(
            clean_sr=float(np.mean(clean.outcomes == world.clean_success)),
            poisoned_sr=float("nan"),
            clean_reward=float(clean.returns.mean()),
            poisoned_reward=float("nan"),
            episodes=episodes,
            clean_trojan_rate=float(np.mean(clean.outcomes == world.trojan_success)),
            clean_timeout_rate=float(np.mean(clean.outcomes == Outcome.TIMEOUT)),
            clean_mean_steps=float(clean.steps.mean()),
        )
        if trigger is not None:
            poisoned = play(agent, env, trigger, episodes, seed, policy, target_action=target_action if success == "action" else None)
            result.poisoned_sr, result.poisoned_sr_raw, result.trigger_seen_rate = score_triggered(env.name, poisoned.outcomes, poisoned.saw)
            result.poisoned_reward = float(poisoned.returns.mean())
            result.poisoned_clean_rate = float(np.mean(poisoned.outcomes == world.clean_success))
            result.poisoned_timeout_rate = float(np.mean(poisoned.outcomes == Outcome.TIMEOUT))
            result.poisoned_mean_steps = float(poisoned.steps.mean())
            if success == "action":
                assert poisoned.target_steps is not None and poisoned.sighted_steps is not None
                result.target_action_rate = float(poisoned.target_steps.sum() / max(poisoned.sighted_steps.sum(), 1))
                result.poisoned_sr = result.target_action_rate
            elif success == "disrupt":
                result.poisoned_sr = 1.0 - result.poisoned_clean_rate
            if close_k is not None:
                close = play(agent, env, trigger, episodes, seed, policy, close_k)
                result.close_sr = float(np.mean(close.outcomes == world.clean_success))
                result.close_trojan_rate = float(np.mean(close.outcomes == world.trojan_success))
    return result
