"""Behavioural trigger search: put candidate triggers of the world's family into its env and
watch whether the agent turns to the trojan outcome.

A detector knows the world's trigger *family* (as TrojAI performers did: the env code was
public) but not the model's trigger. For each candidate of the family, the agent plays a few
seeded episodes of E-bar built with that candidate (the world's own env and trigger code), and
the share of episodes ending in the world's trojan outcome (lava, the pattern's lava, the other
object, the hazard) is compared with the same share in the clean env E. The search is budgeted
and deterministic: a screening stage over ``candidates`` candidates (0: the family's
``CANDIDATES``), a refinement stage over the
``refine`` neighbours of the best few, and a confirmation of the best ``confirm`` with more
episodes on other layouts. Candidates are played :data:`TOGETHER` at a time in a batched-engine
world, recurrent policies too (:func:`run_trials`). A ``seconds`` budget (0: none) cuts screening short on a slow machine
(then results depend on the machine's speed).

The candidates come from a module per trigger family, ``search_<family>.py`` beside this one,
picked by the module the world's trigger class lives in (``rlbackdoors.triggers.<family>``), so
no world is named here. Each gives ``candidates(env_cfg, rng, limit)``, ``neighbours(spec,
env_cfg, rng, limit)``, ``EPISODES``, ``MAX_STEPS`` and ``CANDIDATES``; a family whose triggers
are too many to list may also give ``invert(agent, env_cfg, rng, restarts)``, candidates read off
the model's gradient, screened first when the ``invert`` parameter asks for restarts.

Besides the outcome, each trial records the policy's mean action entropy over the steps it
played (discrete-action agents): in one world a trigger's *outcome* did not separate a backdoor
from a clean agent that the transform confused into the trojan outcome, while how decided the policy
is along the way did better (docs/results/detectors.md). Features per model (the best confirmed
candidate, the screen's distribution, the clean baseline, those entropies) go to a logistic
regression per world (pooled across worlds otherwise); the trigger found is reported next to the
true one by ``detect score``.
"""

from __future__ import annotations

import importlib
import math
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from types import ModuleType
from typing import Any, ClassVar

import numpy as np
import torch

from rlbackdoors import worlds
from rlbackdoors.detect.api import FeatureDetector, Param, register
from rlbackdoors.detect.handle import DetectError, ModelHandle
from rlbackdoors.io import first_line


@dataclass
class Trial:
    """One candidate played: share of episodes ending in the trojan outcome, in the clean goal,
    mean episode length."""

    spec: str | None
    episodes: int
    trojan: float
    success: float
    steps: float
    error: str | None = None
    entropy: float | None = None  # mean action entropy (nats) over the steps played; None: not a discrete policy
    policy: tuple[float, ...] | None = None  # mean action distribution over the steps played; None: not a discrete policy


@dataclass
class SearchResult:
    clean: Trial
    screened: list[Trial]
    best: Trial
    seconds: float
    confirmed: list[Trial] = field(default_factory=list)  # the finalists played again, in rank order (mitigation restores these)

    def features(self) -> dict[str, float]:
        ok = [t for t in self.screened if t.error is None]
        rates = np.array([t.trojan for t in ok]) if ok else np.zeros(1)
        top = np.sort(rates)[::-1]
        return {
            "clean_trojan": self.clean.trojan,
            "clean_success": self.clean.success,
            "best_trojan": self.best.trojan,
            "best_excess": self.best.trojan - self.clean.trojan,
            "best_success_drop": self.clean.success - self.best.success,
            "best_log_steps_ratio": math.log((self.best.steps + 1.0) / (self.clean.steps + 1.0)),
            "screen_max": float(top[0]),
            "screen_top3_mean": float(top[:3].mean()),
            "screen_mean": float(rates.mean()),
            "screen_frac_half": float((rates >= 0.5).mean()),
            **self.entropy_features(ok),
        }

    def entropy_features(self, ok: list[Trial]) -> dict[str, float]:
        entropies = [t.entropy for t in ok if t.entropy is not None]
        if self.clean.entropy is None or self.best.entropy is None or not entropies:
            return {}
        return {
            "clean_entropy": self.clean.entropy,
            "best_entropy": self.best.entropy,
            "best_entropy_change": self.best.entropy - self.clean.entropy,
            "screen_entropy_mean": float(np.mean(entropies)),
        }


def family_module(world: worlds.World) -> ModuleType:
    """The search module of ``world``'s trigger family (module doc)."""
    trigger = world.parse_trigger(world.draw_trigger(None, 0, None))
    family = type(trigger).__module__.rpartition(".")[2]
    try:
        return importlib.import_module(f"rlbackdoors.detect.baselines.search_{family}")
    except ModuleNotFoundError:
        raise DetectError(
            f"no behavioural search for the trigger family {family!r} of world {world.name!r} (add detect/baselines/search_{family}.py)"
        ) from None


def family_unsupported(model: ModelHandle) -> str | None:
    """Why the trigger family's search cannot play this model's env (its settings), or None."""
    check = getattr(family_module(model.world), "unsupported", None)
    return check(model.env_config()) if check is not None else None


@contextmanager
def entropy_probe(agent) -> Iterator[list[np.ndarray] | None]:
    """Record the action distribution of every row of every forward pass of a discrete policy
    (one array of shape (rows, actions) per pass).

    The policy's ``forward`` is shadowed for the block (an instance attribute), so the agent
    acts exactly as before; yields None for a policy that is not a torch module (OPAC²)."""
    policy = getattr(agent, "policy", None)
    if not isinstance(policy, torch.nn.Module):
        yield None
        return
    calls: list[np.ndarray] = []
    original = policy.forward

    def forward(*args, **kwargs):
        out = original(*args, **kwargs)
        logits = out[0] if isinstance(out, tuple) else out
        probs = torch.softmax(logits.detach().double(), -1)
        calls.append(probs.reshape(-1, probs.shape[-1]).cpu().numpy())
        return out

    policy.forward = forward
    try:
        yield calls
    finally:
        del policy.forward


def _running_rows(calls: list[np.ndarray], steps: np.ndarray) -> np.ndarray:
    """The rows (action distributions) of the steps episodes were running. Where every pass saw
    one row per episode (the batched engines: pass t is step t of each), a row counts while its
    episode runs; where batches shrink with the running episodes, every row counts."""
    steps = np.asarray(steps)
    if all(len(c) == len(steps) for c in calls):
        running = np.arange(len(calls))[:, None] < steps[None, :]
        return np.stack(calls)[running]
    return np.concatenate(calls)


def entropies(probs: np.ndarray) -> np.ndarray:
    """Entropy (nats) of each row of action distributions."""
    logp = np.log(np.clip(probs, 1e-300, None))
    return -(probs * logp).sum(-1)


def mean_entropy(calls: list[np.ndarray] | None, steps: np.ndarray) -> float | None:
    """Mean action entropy over the steps episodes were running (:func:`_running_rows`)."""
    if not calls:
        return None
    rows = _running_rows(calls, steps)
    return float(entropies(rows).mean()) if len(rows) else None


def mean_policy(calls: list[np.ndarray] | None, steps: np.ndarray) -> tuple[float, ...] | None:
    """Mean action distribution over the steps episodes were running (:func:`_running_rows`)."""
    if not calls:
        return None
    rows = _running_rows(calls, steps)
    return tuple(float(x) for x in rows.mean(0)) if len(rows) else None


def run_trial(agent, world: worlds.World, env_cfg, spec: str | None, episodes: int, seed: int, policy: str) -> Trial:
    """``episodes`` episodes in E-bar with candidate ``spec`` (E if None)."""
    from rlbackdoors.evaluate.episodes import play

    try:
        with entropy_probe(agent) as calls:
            played = play(agent, env_cfg, spec, episodes, seed, policy)
    except (ValueError, RuntimeError) as err:  # a candidate the env cannot place (too many cells, no solvable layout)
        return Trial(spec, 0, 0.0, 0.0, 0.0, f"{type(err).__name__}: {first_line(err)}")
    return _trial(world, spec, episodes, played, calls)


def _trial(world: worlds.World, spec: str | None, episodes: int, played, calls: list[np.ndarray] | None) -> Trial:
    """A candidate's :class:`Trial` from its played episodes and its forwards' action distributions."""
    outcomes = np.asarray(played.outcomes)
    return Trial(
        spec,
        episodes,
        float(np.mean(outcomes == world.trojan_success)),
        float(np.mean(outcomes == world.clean_success)),
        float(np.mean(played.steps)),
        entropy=mean_entropy(calls, played.steps),
        policy=mean_policy(calls, played.steps),
    )


TOGETHER = 32  # candidates a screen plays at once (:func:`run_trials`)


def run_trials(agent, world: worlds.World, env_cfg, specs: list[str], episodes: int, seed: int, policy: str) -> list[Trial]:
    """:func:`run_trial` for each of ``specs``: at once where the agent is a torch policy in a
    batched-engine world (one forward for every candidate's episodes, each recurrent slot's memory its own,
    :func:`~rlbackdoors.evaluate.episodes.play_together`), else one after another. A candidate
    the env cannot place is tried alone, so it fails alone."""
    from rlbackdoors.evaluate.episodes import play_together, plays_together

    if len(specs) < 2 or not plays_together(agent, env_cfg):
        return [run_trial(agent, world, env_cfg, spec, episodes, seed, policy) for spec in specs]
    probs: list[list[np.ndarray]] = [[] for _ in specs]
    try:
        played = play_together(agent, env_cfg, list(specs), episodes, seed, policy, probs)
    except (ValueError, RuntimeError):  # one of them cannot be placed: each on its own, so only it fails
        return [run_trial(agent, world, env_cfg, spec, episodes, seed, policy) for spec in specs]
    return [_trial(world, spec, episodes, one, calls) for spec, one, calls in zip(specs, played, probs)]


def outcome_rank(trial: Trial) -> tuple:
    return (trial.error is None, trial.trojan, -trial.success, -trial.steps)


def search(
    agent,
    world: worlds.World,
    env_cfg,
    family: ModuleType,
    candidates: int = 0,
    refine: int = 12,
    confirm: int = 3,
    episodes: int = 0,
    confirm_episodes: int = 0,
    seconds: float = 0.0,
    seed: int = 4_000_000,
    policy: str = "sample",
    invert: int = 0,
    rank: Callable[[Trial, Trial], tuple] | None = None,
    whole_family: bool = False,
) -> SearchResult:
    """The budgeted search of the module doc on one agent. ``rank(trial, clean)`` orders the
    candidates for refinement and confirmation (default: by the trojan outcome, :func:`outcome_rank`).
    ``whole_family``: screen every member the family lists (its ``every(env_cfg)``) instead of
    ``candidates`` of them; a family without such a list is refused."""
    started = time.perf_counter()
    episodes = int(episodes) or int(family.EPISODES)
    candidates = int(candidates) or int(family.CANDIDATES)
    confirm_episodes = int(confirm_episodes) or 2 * episodes
    if whole_family and not hasattr(family, "every"):
        raise DetectError(f"the trigger family {family.__name__.rpartition('_')[2]!r} does not list its members: screen a sample of it")
    rng = np.random.default_rng(seed)
    with agent.evaluating():
        clean = run_trial(agent, world, env_cfg, None, confirm_episodes, seed + 1, policy)
        if clean.error is not None:
            raise DetectError(f"the clean env cannot be played: {clean.error}")
        key: Callable[[Trial], tuple] = outcome_rank if rank is None else (lambda t: rank(t, clean))
        screened: list[Trial] = []
        tried: set[str] = set()

        def screen(specs: list[str]) -> None:
            fresh = [s for s in dict.fromkeys(specs) if s not in tried]
            step = 1 if seconds else TOGETHER  # a time budget is checked before every candidate
            for start in range(0, len(fresh), step):
                if seconds and time.perf_counter() - started > seconds:
                    return
                chunk = fresh[start : start + step]
                tried.update(chunk)
                screened.extend(run_trials(agent, world, env_cfg, chunk, episodes, seed, policy))

        if invert > 0 and hasattr(family, "invert"):  # its own stream: the listed candidates stay the same
            screen(family.invert(agent, env_cfg, np.random.default_rng(seed + 3), int(invert)))
        if whole_family:
            screen(family.every(env_cfg))
        else:
            screen(family.candidates(env_cfg, rng, int(candidates)))
        if refine > 0:
            leaders = sorted((t for t in screened if t.error is None), key=key, reverse=True)[: max(1, confirm)]
            per = max(1, int(refine) // max(1, len(leaders)))
            for leader in leaders:
                assert leader.spec is not None
                screen(family.neighbours(leader.spec, env_cfg, rng, per))
        finalists = sorted((t for t in screened if t.error is None), key=key, reverse=True)[: max(1, confirm)]
        if not finalists:
            raise DetectError(f"no candidate trigger of the family could be played ({len(screened)} tried)")
        confirmed = run_trials(agent, world, env_cfg, [t.spec for t in finalists if t.spec is not None], confirm_episodes, seed + 2, policy)
        best = max(confirmed, key=key)
    return SearchResult(clean, screened, best, time.perf_counter() - started, sorted(confirmed, key=key, reverse=True))


def search_report(model: ModelHandle, params: dict, result: SearchResult, top: int = 5) -> dict[str, Any]:
    """A search as plain data (``detect search``): the clean baseline, the confirmed best
    candidate with its excess over clean, the ``top`` screened candidates by rank, and cost. Built
    from the handle, so the model's own trigger is not in it."""

    def trial(t: Trial) -> dict[str, Any]:
        return {k: v for k, v in asdict(t).items() if v is not None and k != "policy"}

    ranked = sorted(result.screened, key=outcome_rank, reverse=True)
    return {
        "model": model.name,
        "world": model.world.name,
        "arch": model.arch,
        "params": dict(params),
        "clean": trial(result.clean),
        "found": {**trial(result.best), "excess": result.best.trojan - result.clean.trojan},
        "top_screened": [trial(t) for t in ranked[:top]],
        "candidates_tried": len(result.screened),
        "failed_candidates": sum(t.error is not None for t in result.screened),
        "features": result.features(),
        "seconds": round(result.seconds, 3),
    }


@register
class BehaviourDetector(FeatureDetector):
    name = "behaviour"
    description = "budgeted search over the world's trigger family in its env; trojan-outcome rate -> logistic regression"
    defaults: ClassVar[dict[str, Any]] = {
        **FeatureDetector.defaults,
        "candidates": 0,  # 0: the family's default (48; every room pattern for wall colours)
        "refine": 12,
        "confirm": 3,
        "episodes": 0,  # 0: the family's default
        "confirm_episodes": 0,  # 0: twice the screening episodes
        "seconds": 0.0,  # 0: no time budget (deterministic); else screening stops after this many seconds
        "seed": 4_000_000,
        "policy": "sample",
        "max_steps": 0,  # 0: the family's default episode cut
        "invert": 0,  # restarts of the family's gradient inversion (families that have one); 0: off
    }
    rules: ClassVar[dict[str, Param]] = {
        **FeatureDetector.rules,
        "candidates": Param(0, 100_000, help="candidate triggers screened (0: the family's default)"),
        "refine": Param(0, 10_000, help="neighbours of the best candidates tried"),
        "confirm": Param(1, 1_000, help="best candidates confirmed with more episodes"),
        "episodes": Param(0, 100_000, help="screening episodes per candidate (0: the family's default)"),
        "confirm_episodes": Param(0, 100_000, help="episodes per confirmation (0: twice the screening episodes)"),
        "seconds": Param(0.0, 86_400.0, help="screening time budget in seconds (0: none, deterministic)"),
        "seed": Param(0, 2**31 - 1, help="seed of the search's episodes"),
        "policy": Param(choices=("sample", "greedy"), help="how the model acts in the search"),
        "max_steps": Param(0, 100_000, help="episode cut in the search (0: the family's default)"),
        "invert": Param(0, 1_000, help="restarts of the family's gradient inversion (0: off)"),
    }

    def group(self, model: ModelHandle) -> str:
        return model.world.name  # the features mean the same for every architecture of a world

    def unsupported(self, model: ModelHandle) -> str | None:
        why = family_unsupported(model)
        return f"detector 'behaviour' cannot play {model.world.name}: {why}" if why else None

    def run_search(self, model: ModelHandle, rank: Callable[[Trial, Trial], tuple] | None = None, whole_family: bool = False) -> SearchResult:
        """The search with this detector's parameters on one model (``rank``, ``whole_family``:
        :func:`search`'s)."""
        family = family_module(model.world)
        max_steps = int(self.params["max_steps"]) or family.MAX_STEPS
        env_cfg = model.env_config(**({"max_steps": int(max_steps)} if max_steps else {}))
        p = self.params
        return search(
            model.build_agent(),
            model.world,
            env_cfg,
            family,
            candidates=int(p["candidates"]),
            refine=int(p["refine"]),
            confirm=int(p["confirm"]),
            episodes=int(p["episodes"]),
            confirm_episodes=int(p["confirm_episodes"]),
            seconds=float(p["seconds"]),
            seed=int(p["seed"]),
            policy=str(p["policy"]),
            invert=int(p["invert"]),
            rank=rank,
            whole_family=whole_family,
        )

    def features(self, model: ModelHandle) -> dict[str, float]:
        result = self.run_search(model)
        self.last_info = {
            "found_trigger": result.best.spec,
            "found_trojan_rate": result.best.trojan,
            "clean_trojan_rate": result.clean.trojan,
            "candidates_tried": len(result.screened),
            "search_seconds": round(result.seconds, 3),
        }
        return result.features()


__all__ = [
    "BehaviourDetector",
    "SearchResult",
    "Trial",
    "entropies",
    "entropy_probe",
    "family_module",
    "mean_entropy",
    "mean_policy",
    "outcome_rank",
    "TOGETHER",
    "run_trial",
    "run_trials",
    "search",
    "search_report",
]
