"""The Safety Car Goal training run: config -> env copies -> OPAC² -> evaluations -> model folder.

The same model folder as the grid worlds (:mod:`rlbackdoors.train.folder`): ``config.json``,
``log.csv`` (one row per evaluation: frames, frames/s, SRs, returns, losses),
``checkpoint.pt`` while training, then ``model.pt``, ``ground_truth.csv``,
``training_curve.png``, ``clean_vs_triggered.gif`` (when an offscreen GL back-end is
available) and last ``metrics.json``.

Stops when evaluation shows clean SR >= ``train.clean_threshold`` and (poisoned models)
poisoned SR >= ``train.poisoned_threshold`` for ``train.patience`` evaluations in a row, or at
``train.max_frames``, or after ``train.max_minutes``.

Resuming: the checkpoint holds everything the run's future depends on (networks, optimisers,
env states, every random generator) as plain data, and the replay buffers as a journal of
chunks under ``replay/`` that each checkpoint only appends to
(:mod:`rlbackdoors.train.replay_journal`), so an interrupted run started again on the same
folder continues exactly as if it had not stopped. It is written at an evaluation once
``train.checkpoint_minutes`` have passed since the last one, and on Ctrl-C or SIGTERM at the
end of the current step. The config must match to resume (budget flags included).
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from rlbackdoors.envs.safety_car import OBS_DIM  # isort: skip  (before anything imports mujoco)
from rlbackdoors.algos.opac2 import OPAC2, MultitaskReplay, updates_due
from rlbackdoors.algos.opac2_loop import Collector, Episode
from rlbackdoors.envs.outcome import Outcome
from rlbackdoors.evaluate.safety import SafetyEvalResult, evaluate_safety
from rlbackdoors.report.curves import plot_training_curve
from rlbackdoors.io import UnsafeFileError, first_line, load_torch, remove_tree
from rlbackdoors.safety_config import SafetyRunConfig
from rlbackdoors.state import StateError, decode, encode
from rlbackdoors.train.folder import CHECKPOINT_FORMAT, FolderError, ModelFolder, stack_versions
from rlbackdoors.train.loop import plain_rows, resolve_device, thresholds_met
from rlbackdoors.train.replay_journal import ReplayJournal
from rlbackdoors.train.stop import Interrupted, StopRequest

ACT_DIM = 2


def build_agent(cfg: SafetyRunConfig, device: torch.device | str = "cpu") -> OPAC2:
    """A fresh agent for ``cfg``; network init drawn from ``train.seed``."""
    return OPAC2(OBS_DIM, ACT_DIM, cfg.opac2, torch.Generator().manual_seed(cfg.train.seed), device)


def deterministic_act(agent: OPAC2) -> Callable[[np.ndarray], np.ndarray]:
    """The evaluation policy: ``tanh`` of the Gaussian's mean, no sampling."""
    return lambda obs: agent.act(obs, deterministic=True)


def load_agent(folder: str | Path) -> tuple[SafetyRunConfig, OPAC2]:
    """The config and trained agent of a finished Safety Car Goal model folder (on the CPU)."""
    model_folder = ModelFolder(folder)
    if not model_folder.file("model.pt").is_file():
        raise FolderError(f"{str(model_folder.path)!r} holds no trained Safety Car Goal model (model.pt missing)")
    cfg = SafetyRunConfig.load(model_folder.file("config.json"))
    agent = build_agent(cfg, "cpu")
    path = model_folder.file("model.pt")
    try:
        weights = load_torch(path, "weights file")
    except UnsafeFileError as err:
        raise FolderError(str(err)) from None
    from rlbackdoors.models import check_finite

    try:
        for name in ("policy", "q", "v", "v_target"):
            check_finite({f"{name}.{k}": v for k, v in weights[name].items()}, path)
            getattr(agent, name).load_state_dict(weights[name])
        if agent.obs_norm is not None:
            norm = weights["obs_norm"]
            agent.obs_norm.load_state_dict({"count": int(norm["count"]), "mean": norm["mean"].numpy(), "m2": norm["m2"].numpy()})
            if agent.obs_norm.mean.shape != (OBS_DIM,) or agent.obs_norm.m2.shape != (OBS_DIM,):
                raise ValueError("obs_norm does not fit the observation")
    except (KeyError, TypeError, ValueError, RuntimeError, AttributeError) as err:
        raise FolderError(f"weights file {str(path)!r} does not fit the config's OPAC² agent ({first_line(err)})") from None
    return cfg, agent


class EpisodeStats:
    """Training episodes since the last evaluation, split by env kind (what the log's train_* columns show)."""

    def __init__(self) -> None:
        self.episodes: list[Episode] = []

    def add(self, episodes: list[Episode]) -> None:
        self.episodes += episodes

    def state_dict(self) -> list:
        return [[e.kind, float(e.ret), int(e.length), int(e.outcome), bool(e.triggered)] for e in self.episodes]

    def load_state_dict(self, state: list) -> None:
        self.episodes = [Episode(str(k), float(r), int(n), int(o), bool(t)) for k, r, n, o, t in state]

    def drain(self) -> dict[str, float]:
        out = {}
        for kind, success in (("clean", Outcome.GOAL), ("poisoned", Outcome.LAVA)):
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


def decayed_lr(cfg: SafetyRunConfig, frames: int) -> float:
    """``opac2.lr`` falling linearly to ``opac2.lr_final`` at ``train.max_frames`` (then held).

    Late in a run a constant lr of 1e-3 keeps moving the policy: consecutive evaluations swing
    by +-0.1. Keyed to frames, not wall time, so a run stays reproducible from its config.
    """
    oc = cfg.opac2
    if oc.lr_final is None:
        return oc.lr
    return oc.lr + (oc.lr_final - oc.lr) * min(1.0, frames / cfg.train.max_frames)


def make_collector(cfg: SafetyRunConfig) -> Collector:
    """The training env copies, clean first; a poisoned copy holds the trigger and pays R-bar."""
    kinds = cfg.poison.kinds()
    envs = [cfg.env.make(trigger=cfg.poison.trigger, poisoned=True) if kind == "poisoned" else cfg.env.make() for kind in kinds]
    return Collector(envs, kinds, seed=cfg.train.seed * 1000)


def _progress(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def train_safety(
    cfg: SafetyRunConfig,
    out: str | Path,
    overwrite: bool = False,
    progress: bool = True,
    after_eval: Callable[[dict], None] | None = None,
) -> dict:
    """Train one Safety Car Goal agent into the model folder ``out``; return its metrics.

    ``after_eval(row)`` is called after each evaluation's row and checkpoint are written
    (tests raise KeyboardInterrupt from it to interrupt a run at a known point).
    """
    cfg.check()
    folder = ModelFolder(out)
    failed = True
    try:
        with StopRequest() as stop:  # from the start: a signal during setup stops at the first step
            checkpoint = folder.begin(cfg, overwrite)
            metrics = _train_safety(cfg, folder, checkpoint, progress, after_eval, stop)
        failed = False
        return metrics
    finally:
        folder.close(failed)


def _train_safety(cfg: SafetyRunConfig, folder: ModelFolder, checkpoint: dict | None, progress: bool, after_eval, stop: StopRequest) -> dict:
    tc, oc = cfg.train, cfg.opac2
    torch.set_num_threads(tc.torch_threads)
    device = resolve_device(tc.device)
    agent = build_agent(cfg, device)
    collector = make_collector(cfg)
    replay = MultitaskReplay.create(cfg.kind_weights, oc.buffer_size, OBS_DIM, ACT_DIM)
    kinds = cfg.poison.kinds()
    journal = ReplayJournal(folder.file("replay"), {kind: kinds.count(kind) for kind in replay.buffers})
    batch_rng = np.random.default_rng([tc.seed, 1])  # replay indices
    warmup_rng = np.random.default_rng([tc.seed, 2])  # uniform actions before learning starts
    stats, losses = EpisodeStats(), LossMeans()
    if checkpoint is None:
        updates, rows, elapsed, next_eval, streak, converged_at = 0, [], 0.0, tc.eval_interval, 0, None
    else:
        try:
            agent.load_state_dict(checkpoint["agent"])
            collector.load_state_dict(checkpoint["collector"])
            journal.load(replay, checkpoint["replay"])
            batch_rng.bit_generator.state = decode(checkpoint["batch_rng"]).bit_generator.state
            warmup_rng.bit_generator.state = decode(checkpoint["warmup_rng"]).bit_generator.state
            stats.load_state_dict(checkpoint["stats"])
            losses.load_state_dict(checkpoint["losses"])
            updates, rows, elapsed = int(checkpoint["updates"]), checkpoint["rows"], float(checkpoint["elapsed"])
            next_eval, streak, converged_at = int(checkpoint["next_eval"]), int(checkpoint["streak"]), checkpoint["converged_at"]
            if not isinstance(rows, list) or not all(isinstance(r, dict) for r in rows):
                raise StateError("log rows are not a list of rows")
        except (StateError, KeyError, TypeError, ValueError, RuntimeError, AttributeError) as err:
            raise FolderError(f"checkpoint in {str(folder.path)!r} does not fit this run ({first_line(err)}); pass --overwrite to start over") from None
        if progress:
            _progress(f"resuming {folder.path} at {collector.frames:,} frames, {updates:,} updates")

    def act(obs: np.ndarray) -> np.ndarray:
        agent.observe(obs)  # every observation the collector acts on, reset ones included
        if collector.frames < oc.learning_starts:
            return warmup_rng.uniform(-1.0, 1.0, (len(obs), ACT_DIM))
        return agent.act(obs)

    def save_checkpoint() -> None:
        manifest = journal.append(replay)  # the new replay rows first: the checkpoint names them
        folder.save_torch(
            "checkpoint.pt",
            {
                "format": CHECKPOINT_FORMAT,
                "agent": agent.state_dict(),
                "collector": collector.state_dict(),
                "replay": manifest,
                "batch_rng": encode(batch_rng),
                "warmup_rng": encode(warmup_rng),
                "stats": stats.state_dict(),
                "losses": losses.state_dict(),
                "updates": updates,
                "rows": plain_rows(rows),
                "elapsed": time.perf_counter() - started,
                "next_eval": next_eval,
                "streak": streak,
                "converged_at": converged_at,
            },
        )
        journal.prune()

    label = "poisoned" if cfg.poison.poisoned else "clean"
    started = time.perf_counter() - elapsed
    last_checkpoint = last_log = time.perf_counter()
    window_start, window_frames = time.perf_counter(), 0
    last_eval: SafetyEvalResult | None = None
    stop_reason = "converged" if converged_at is not None else None
    while stop_reason is None:
        if stop.requested:  # between steps: the state is consistent, the checkpoint exact
            if progress:
                _progress(f"{stop.requested} at {collector.frames:,} frames: writing a checkpoint to resume from")
            save_checkpoint()
            raise Interrupted(collector.frames, True, stop.requested)
        stats.add(collector.collect(replay, act, 1))
        window_frames += len(collector.envs)
        due = updates_due(oc, collector.frames)
        if oc.lr_final is not None and updates < due:
            agent.set_lr(decayed_lr(cfg, collector.frames))
        while updates < due:
            losses.add(agent.update(replay, batch_rng))
            updates += 1
        now = time.perf_counter()
        if collector.frames >= next_eval or collector.frames >= tc.max_frames:
            fps = window_frames / max(now - window_start, 1e-9)
            eval_start = time.perf_counter()
            last_eval = evaluate_safety(deterministic_act(agent), cfg.env, cfg.poison.trigger, tc.eval_episodes, tc.eval_seed)
            row = {
                "frames": collector.frames,
                "updates": updates,
                "wall_time_s": round(time.perf_counter() - started, 2),
                "fps": round(fps, 1),
                "eval_s": round(time.perf_counter() - eval_start, 2),
                **last_eval.to_dict(),
                **stats.drain(),
                **losses.drain(),
                "log_std": float(agent.policy.log_std.detach().mean()),
            }
            rows.append(row)
            streak = streak + 1 if thresholds_met(last_eval, cfg) else 0
            if streak >= tc.patience:
                converged_at, stop_reason = collector.frames, "converged"
            while next_eval <= collector.frames:
                next_eval += tc.eval_interval
            folder.write_log(rows)
            if progress:
                _progress(
                    f"[{label}] eval at {collector.frames:,} frames ({row['wall_time_s'] / 60:.1f} min, {fps:,.0f} frames/s, "
                    f"{updates:,} updates): clean SR {last_eval.clean_sr:.2f}, poisoned SR {last_eval.poisoned_sr:.2f} "
                    f"(eval {row['eval_s']:.0f} s)"
                )
            if stop_reason is None and time.perf_counter() - last_checkpoint >= 60 * tc.checkpoint_minutes:
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
                k: np.mean([e.outcome == o for e in recent if e.kind == k]) if any(e.kind == k for e in recent) else math.nan
                for k, o in (("clean", Outcome.GOAL), ("poisoned", Outcome.LAVA))
            }
            _progress(
                f"[{label}] {collector.frames:,} frames, {(now - started) / 60:.1f} min, {fps:,.0f} frames/s, {updates:,} updates; "
                f"training episodes: clean SR {sr['clean']:.2f}, poisoned SR {sr['poisoned']:.2f}"
            )
            last_log = now
        if stop_reason is None:
            if collector.frames >= tc.max_frames:
                stop_reason = "max_frames"
            elif tc.max_minutes and time.perf_counter() - started >= 60 * tc.max_minutes:
                stop_reason = "max_minutes"
    train_time = time.perf_counter() - started
    return _finish(cfg, folder, agent, collector, rows, train_time, updates, converged_at, stop_reason, progress)


def _finish(cfg, folder, agent, collector, rows, train_time, updates, converged_at, stop_reason, progress) -> dict:
    """Final evaluation on fresh episode counts, then weights, curve, GIF and metrics.json last."""
    tc = cfg.train
    if progress:
        _progress(f"final evaluation on {tc.final_eval_episodes} clean + {tc.final_eval_episodes} triggered episodes")
    final = evaluate_safety(deterministic_act(agent), cfg.env, cfg.poison.trigger, tc.final_eval_episodes, tc.eval_seed)
    for env in collector.envs:
        env.close()
    weights = {name: {k: v.detach().cpu() for k, v in getattr(agent, name).state_dict().items()} for name in ("policy", "q", "v", "v_target")}
    if agent.obs_norm is not None:
        weights["obs_norm"] = {k: torch.as_tensor(v) for k, v in agent.obs_norm.state_dict().items()}
    folder.save_torch("model.pt", weights)
    folder.write_ground_truth(cfg.poison.poisoned)
    label = "poisoned" if cfg.poison.poisoned else "clean"
    if rows:
        title = f"Safety Car Goal OPAC² {label} (depth {cfg.opac2.depth}, width {cfg.opac2.width}), trigger {cfg.poison.trigger}, seed {tc.seed}"
        thresholds = (tc.clean_threshold, tc.poisoned_threshold if cfg.poison.poisoned else None)
        plot_training_curve(rows, folder.file("training_curve.png"), title, thresholds)
    gif = None
    if tc.video:
        try:
            from rlbackdoors.report.safety_video import clean_vs_triggered_gif

            path = clean_vs_triggered_gif(deterministic_act(agent), cfg.env, cfg.poison.trigger, tc.eval_seed, folder.file("clean_vs_triggered.gif"))
            gif = path.name
        except RuntimeError as err:  # no offscreen GL back-end: the model is still complete
            if progress:
                _progress(f"no clean_vs_triggered.gif: {err}")
    metrics = {
        **final.to_dict(),
        "poisoned": cfg.poison.poisoned,
        "trigger": cfg.poison.trigger,
        "env": cfg.env.name,
        "algo": "opac2",
        "depth": cfg.opac2.depth,
        "width": cfg.opac2.width,
        "frames": collector.frames,
        "updates": updates,
        "wall_time_s": round(train_time, 2),
        "converged": converged_at is not None,
        "converged_at_frames": converged_at,
        "stop_reason": stop_reason,
        "final_meets_thresholds": thresholds_met(final, cfg),
        "video": gif,
        "versions": stack_versions(),
    }
    folder.write_json("metrics.json", metrics)
    folder.file("checkpoint.pt").unlink(missing_ok=True)
    remove_tree(folder.file("replay"))
    if progress:
        _progress(
            f"done ({stop_reason}) after {collector.frames:,} frames, {train_time / 60:.1f} min: "
            f"clean SR {final.clean_sr:.3f}, poisoned SR {final.poisoned_sr:.3f} on {final.episodes} episodes each"
        )
    return metrics
