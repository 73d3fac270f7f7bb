"""OPAC²'s training loop : env copies -> replay -> OPAC² updates -> evaluations.

Called by :func:`rlbackdoors.train.train`, which owns the folder, the stopping rule's meaning
and the finish. ``log.csv`` gets one row per evaluation: frames, frames/s, SRs, returns, losses.

Resuming: the checkpoint holds everything the run's future depends on (networks, optimisers,
env states, every random generator) as plain data, and the replay buffers as a journal of
chunks under ``replay/`` that each checkpoint only appends to
(:mod:`rlbackdoors.train.replay_journal`), so an interrupted run started again on the same
folder continues exactly as if it had not stopped. It is written at an evaluation once
``train.checkpoint_minutes`` have passed since the last one, and on Ctrl-C or SIGTERM at the
end of the current step. The config must match to resume (budget flags included).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import sys
import time
from collections.abc import Generator
from typing import Any

import numpy as np
import torch

from rlbackdoors.agent import build_policy
from rlbackdoors.algos.opac2 import OPAC2, MultitaskReplay, updates_due
from rlbackdoors.algos.opac2_loop import Collector, Episode
from rlbackdoors.config import RunConfig
from rlbackdoors.envs.pool import EnvPool
from rlbackdoors.io import first_line
from rlbackdoors.state import StateError, decode, encode
from rlbackdoors.train.driver import Evaluate, RunClock, RunOutcome, Stopping, checked_rows, plain_rows, resolve_device, serve
from rlbackdoors.folder import CHECKPOINT_FORMAT, FolderError, ModelFolder
from rlbackdoors.train.replay_journal import ReplayJournal
from rlbackdoors.train.stop import Interrupted, StopRequest


class EpisodeStats:
    """Training episodes since the last evaluation, split by env kind (what the log's train_* columns show)."""

    def __init__(self, success: dict[str, int]) -> None:
        self.episodes: list[Episode] = []
        self.success = success  # env kind -> the outcome that is success for it

    def add(self, episodes: list[Episode]) -> None:
        self.episodes += episodes

    def state_dict(self) -> list:
        return [[e.kind, float(e.ret), int(e.length), int(e.outcome), bool(e.triggered)] for e in self.episodes]

    def load_state_dict(self, state: list) -> None:
        self.episodes = [Episode(str(k), float(r), int(n), int(o), bool(t)) for k, r, n, o, t in state]

    def drain(self) -> dict[str, float]:
        out = {}
        for kind, success in self.success.items():
            mine = [e for e in self.episodes if e.kind == kind]
            out[f"train_{kind}_return"] = float(np.mean([e.ret for e in mine])) if mine else math.nan
            out[f"train_{kind}_sr"] = float(np.mean([e.outcome == success for e in mine])) if mine else math.nan
            out[f"train_{kind}_episodes"] = len(mine)
        self.episodes = []
        return out


class LossMeans:
    """Mean of each loss over the updates since the last evaluation."""

    def __init__(self) -> None:
        self.sums: dict[str, float] = {}
        self.count = 0

    def add(self, losses: dict[str, float]) -> None:
        for key, value in losses.items():
            self.sums[key] = self.sums.get(key, 0.0) + value
        self.count += 1

    def state_dict(self) -> dict:
        return {"sums": {k: float(v) for k, v in self.sums.items()}, "count": int(self.count)}

    def load_state_dict(self, state: dict) -> None:
        self.sums, self.count = {str(k): float(v) for k, v in state["sums"].items()}, int(state["count"])

    def drain(self) -> dict[str, float]:
        out = {key: value / self.count for key, value in self.sums.items()} if self.count else {}
        self.sums, self.count = {}, 0
        return out


def decayed_lr(cfg: RunConfig, frames: int) -> float:
    """``opac2.lr`` falling linearly to ``opac2.lr_final`` at ``train.max_frames`` (then held).

    Late in a run a constant lr of 1e-3 keeps moving the policy: consecutive evaluations swing
    by +-0.1. Keyed to frames, not wall time, so a run stays reproducible from its config.
    """
    oc = cfg.opac2
    assert oc is not None and cfg.train.max_frames is not None
    if oc.lr_final is None:
        return oc.lr
    return oc.lr + (oc.lr_final - oc.lr) * min(1.0, frames / cfg.train.max_frames)


def make_collector(cfg: RunConfig, pool: EnvPool | None = None) -> Collector:
    """The training env copies, clean first; a poisoned copy holds the trigger and pays R-bar.

    Under an attack other than the env mix every copy pays the clean reward and holds the trigger
    only in the episodes the attack's seam switches on (its E-bar copies, or what its budget buys),
    paying the attack's R-bar itself (:func:`rlbackdoors.poison.mix.episode_seam`). With ``pool``
    the copies live in its worker processes (the same numbers, stepped in parallel).
    """
    from rlbackdoors.poison.mix import episode_seam

    kinds = cfg.replay_kinds()
    seam = episode_seam(cfg.env, cfg.poison, cfg.train.seed)
    world = cfg.world
    assert world.env_kwargs is not None
    near = cfg.poison.evasion.get("near", 0.0) if cfg.poison.poisoned else 0.0
    # near-trigger formations (poison.evasion.near), switched on per episode by the seam in clean copies
    trigger = cfg.poison.trigger
    extra = {"near_formations": world.near_triggers(trigger)} if near > 0 and world.near_triggers and trigger else {}
    knowing = functools.partial(world.env_class(), **world.env_kwargs(cfg.env), trigger=trigger, **extra)  # holds the trigger only when switched on
    if seam is None:
        clean = knowing if extra else functools.partial(cfg.env.make)
        factories = [functools.partial(cfg.env.make, trigger, **extra) if kind == "poisoned" else clean for kind in kinds]
    else:
        # the trigger known to every copy, switched on per episode by the seam; the clean reward (the seam pays R-bar)
        factories = [knowing for _ in kinds]
    envs = pool.make(factories) if pool is not None else [make() for make in factories]
    if seam is None and extra:
        # the env mix with near-trigger negatives: its E-bar copies as they are; the clean ones know the
        # trigger's near formations and hold one only where the seam switches it on (never the trigger)
        for env, kind in zip(envs, kinds):
            if kind == "clean":
                env.trigger_next(False)
        from rlbackdoors.attacks.seam import AttackSeam, Poisoner

        seam = lambda vector: AttackSeam(vector, Poisoner(), "episodes", seed=cfg.train.seed, near=near)  # noqa: E731
    return Collector(envs, kinds, seed=cfg.train.seed * 1000, seam=seam)


def _progress(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


@dataclasses.dataclass
class Act:
    """What a run asks of its learner each env step once learning has started: sampled actions for ``obs``."""

    agent: OPAC2
    obs: np.ndarray

    def serve(self) -> np.ndarray:
        return self.agent.act(self.obs)


@dataclasses.dataclass
class Learn:
    """What a run asks of its learner when updates are due: ``n`` OPAC² updates, replay indices
    drawn from ``rng`` (returns their loss dicts)."""

    agent: OPAC2
    replay: MultitaskReplay
    rng: np.random.Generator
    n: int

    def serve(self) -> list[dict[str, float]]:
        return [self.agent.update(self.replay, self.rng) for _ in range(self.n)]


def run(cfg: RunConfig, folder: ModelFolder, checkpoint: dict | None, progress: bool, stop: StopRequest, after_eval=None) -> RunOutcome:
    """Train with OPAC² from ``checkpoint`` (None: from scratch) until the stopping rule or a budget ends it."""
    return serve(steps(cfg, folder, checkpoint, progress, stop, after_eval))


def steps(
    cfg: RunConfig,
    folder: ModelFolder,
    checkpoint: dict | None,
    progress: bool,
    stop: StopRequest,
    after_eval=None,
    cpu_source=None,
    env_pool: EnvPool | None = None,
) -> Generator[Act | Learn | Evaluate, Any, RunOutcome]:
    """:func:`run` as a loop that yields its learner's work (:class:`Act`, :class:`Learn`, and each :class:`~rlbackdoors.train.driver.Evaluate`) and is
    sent the results, so a group trainer (:mod:`rlbackdoors.train.group`) can batch K runs' work;
    ``env_pool``: where its env copies live (:mod:`rlbackdoors.envs.pool`; None: this process)."""
    tc, oc = cfg.train, cfg.opac2
    assert oc is not None and tc.max_frames is not None and tc.eval_interval is not None and tc.checkpoint_minutes is not None
    torch.set_num_threads(tc.torch_threads)
    device = resolve_device(tc.device)
    agent: OPAC2 = build_policy(cfg, device)
    collector = make_collector(cfg, env_pool)
    (obs_dim,), (act_dim,) = collector.envs[0].observation_space.shape, collector.envs[0].action_space.shape
    replay = MultitaskReplay.create(cfg.kind_weights, oc.buffer_size, obs_dim, act_dim)
    kinds = cfg.replay_kinds()
    journal = ReplayJournal(folder.file("replay"), {kind: kinds.count(kind) for kind in replay.buffers})
    batch_rng = np.random.default_rng([tc.seed, 1])  # replay indices
    warmup_rng = np.random.default_rng([tc.seed, 2])  # uniform actions before learning starts
    world = cfg.world
    stats, losses = EpisodeStats({"clean": world.clean_success, "poisoned": world.trojan_success}), LossMeans()
    if checkpoint is None:
        updates, rows, elapsed, next_eval, streak, converged_at = 0, [], 0.0, tc.eval_interval, 0, None
        cpu_elapsed: float | None = 0.0
    else:
        try:
            agent.load_state_dict(checkpoint["agent"])
            collector.load_state_dict(checkpoint["collector"])
            journal.load(replay, checkpoint["replay"])
            batch_rng.bit_generator.state = decode(checkpoint["batch_rng"]).bit_generator.state
            warmup_rng.bit_generator.state = decode(checkpoint["warmup_rng"]).bit_generator.state
            stats.load_state_dict(checkpoint["stats"])
            losses.load_state_dict(checkpoint["losses"])
            updates, rows, elapsed = int(checkpoint["updates"]), checked_rows(checkpoint["rows"]), float(checkpoint["elapsed"])
            cpu_elapsed = None if checkpoint.get("cpu_elapsed") is None else float(checkpoint["cpu_elapsed"])  # None: an older checkpoint
            next_eval, streak, converged_at = int(checkpoint["next_eval"]), int(checkpoint["streak"]), checkpoint["converged_at"]
        except (StateError, KeyError, TypeError, ValueError, RuntimeError, AttributeError) as err:
            raise FolderError(f"checkpoint in {str(folder.path)!r} does not fit this run ({first_line(err)}); pass --overwrite to start over") from None
        if progress:
            _progress(f"resuming {folder.path} at {collector.frames:,} frames, {updates:,} updates")

    def save_checkpoint() -> None:
        manifest = journal.append(replay)  # the new replay rows first: the checkpoint names them
        folder.save_torch(
            "checkpoint.pt",
            {
                "format": CHECKPOINT_FORMAT,
                "device": device.type,  # a resume on another device is refused (train.driver)
                "agent": agent.state_dict(),
                "collector": collector.state_dict(),
                "replay": manifest,
                "batch_rng": encode(batch_rng),
                "warmup_rng": encode(warmup_rng),
                "stats": stats.state_dict(),
                "losses": losses.state_dict(),
                "updates": updates,
                "rows": plain_rows(rows),
                "elapsed": clock.wall(),
                "cpu_elapsed": clock.cpu(),
                "next_eval": next_eval,
                "streak": stopping.streak,
                "converged_at": converged_at,
            },
        )
        journal.prune()

    label = "poisoned" if cfg.poison.poisoned else "clean"
    clock = RunClock(elapsed, cpu_elapsed, cpu_source)
    last_checkpoint = last_log = time.perf_counter()
    window_start, window_frames = time.perf_counter(), 0
    stopping = Stopping(cfg, streak, env_pool)
    stop_reason = "thresholds" if converged_at is not None else ("max_frames" if collector.frames >= tc.max_frames else None)
    while stop_reason is None:
        if stop.requested:  # between steps: the state is consistent, the checkpoint exact
            if progress:
                _progress(f"{stop.requested} at {collector.frames:,} frames: writing a checkpoint to resume from")
            save_checkpoint()
            raise Interrupted(collector.frames, True, stop.requested)
        obs = collector.obs
        agent.observe(obs)  # every observation the collector acts on, reset ones included
        if collector.frames < oc.learning_starts:
            actions = warmup_rng.uniform(-1.0, 1.0, (len(obs), act_dim))
        else:
            actions = yield Act(agent, obs)
        stats.add(collector.collect(replay, lambda _: actions, 1))
        window_frames += len(collector.envs)
        due = updates_due(oc, collector.frames)
        if oc.lr_final is not None and updates < due:
            agent.set_lr(decayed_lr(cfg, collector.frames))
        if updates < due:
            for row in (yield Learn(agent, replay, batch_rng, due - updates)):
                losses.add(row)
            updates = due
        now = time.perf_counter()
        if collector.frames >= next_eval or collector.frames >= tc.max_frames:
            fps = window_frames / max(now - window_start, 1e-9)
            eval_start = time.perf_counter()
            last_eval = yield Evaluate(agent, cfg, tc.eval_episodes, env_pool)
            row = {
                "frames": collector.frames,
                "updates": updates,
                "wall_time_s": round(clock.wall(), 2),
                "fps": round(fps, 1),
                "eval_s": round(time.perf_counter() - eval_start, 2),
                **last_eval.to_dict(),
                **stats.drain(),
                **losses.drain(),
                "log_std": float(agent.policy.log_std.detach().mean()),
            }
            rows.append(row)
            row.update((yield from stopping.steps(last_eval, True, agent, collector.frames)))
            if stopping.stop:
                converged_at, stop_reason = collector.frames, "thresholds"
            while next_eval <= collector.frames:
                next_eval += tc.eval_interval
            folder.write_log(rows)
            if progress:
                _progress(
                    f"[{label}] eval at {collector.frames:,} frames ({row['wall_time_s'] / 60:.1f} min, {fps:,.0f} frames/s, "
                    f"{updates:,} updates): clean SR {last_eval.clean_sr:.2f}, poisoned SR {last_eval.poisoned_sr:.2f} "
                    f"(eval {row['eval_s']:.0f} s)"
                )
            if time.perf_counter() - last_checkpoint >= 60 * tc.checkpoint_minutes:
                save_checkpoint()
                last_checkpoint = time.perf_counter()
            if after_eval is not None:
                after_eval(row)
            window_start, window_frames = time.perf_counter(), 0
            last_log = window_start
        elif progress and now - last_log >= tc.log_interval_s:
            fps = window_frames / max(now - window_start, 1e-9)
            recent = stats.episodes[-100:]
            sr = {
                k: np.mean([e.outcome == o for e in recent if e.kind == k]) if any(e.kind == k for e in recent) else math.nan for k, o in stats.success.items()
            }
            _progress(
                f"[{label}] {collector.frames:,} frames, {clock.wall() / 60:.1f} min, {fps:,.0f} frames/s, {updates:,} updates; "
                f"training episodes: clean SR {sr['clean']:.2f}, poisoned SR {sr['poisoned']:.2f}"
            )
            last_log = now
        if stop_reason is None:
            if collector.frames >= tc.max_frames:
                stop_reason = "max_frames"
            elif tc.max_minutes and clock.wall() >= 60 * tc.max_minutes:
                stop_reason = "max_minutes"
    collector.vector.close()
    return RunOutcome(
        policy=agent,
        weights=agent.weights(),
        frames=collector.frames,
        train_time=clock.wall(),
        cpu_time=clock.cpu(),
        rows=rows,
        stop_reason=stop_reason,
        converged_at=converged_at,
        label=f"OPAC² {oc.depth}x{oc.width}",
        extra={
            "updates": updates,
            "depth": oc.depth,
            "width": oc.width,
            **({"attack_budget_used": collector.vector.budget_used()} if hasattr(collector.vector, "budget_used") else {}),
        },
        clean_up=["replay"],
        final=stopping.confirmed,
    )
