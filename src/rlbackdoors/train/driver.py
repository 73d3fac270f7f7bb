"""The one training driver: config -> the world's algorithm -> evaluations -> model folder.

:func:`train` is the same for every world. It takes the folder's lock, resumes from a
checkpoint if there is one, hands the run to the algorithm's loop (:mod:`.ppo_run` or
:mod:`.opac2_run`, picked by the world's ``algorithm``), and finishes every run the same way:
a final evaluation on fresh episode counts, ``model.pt`` (one flat state dict),
``ground_truth.csv``, ``training_curve.png``, ``clean_vs_triggered.gif`` and last
``metrics.json``, whose presence marks the folder complete.

The stopping rule (:class:`Stopping`) has one meaning everywhere: thresholds held for
``train.patience`` evaluations in a row (plus, for PPO worlds with ``train.return_window``,
the paper's mean training return over the last updates), then, with ``train.confirm``, held
again on the final evaluation's episodes. A model is ``converged`` when its thresholds hold on
the *final* evaluation, as the paper and the TrojAI round generators select models;
``converged_at_frames`` is where the stopping rule fired.
"""

from __future__ import annotations

import base64
import contextlib
import dataclasses
import functools
import importlib
import io
import sys
import time
from collections.abc import Callable, Generator, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from rlbackdoors.config import RunConfig
from rlbackdoors.io import remove_tree
from rlbackdoors.models.minigrid import conv_record
from rlbackdoors.state import StateError
from rlbackdoors.folder import FolderError, ModelFolder, stack_versions
from rlbackdoors.train.stop import StopRequest

RUNNERS = {"ppo": "rlbackdoors.train.ppo_run", "opac2": "rlbackdoors.train.opac2_run"}


def thresholds_met(result, cfg, margin: float = 0.0) -> bool:
    """The thresholds of ``cfg`` (raised by ``margin``, at most to 1) on an evaluation result:
    clean SR, and for poisoned models poisoned SR."""

    def bar(threshold: float) -> float:  # rounded: 0.9 + 0.05 is 0.9500000000000001 in floats
        return min(round(threshold + margin, 12), 1.0)

    ok = result.clean_sr >= bar(cfg.train.clean_threshold)
    if cfg.poison.poisoned:
        ok = ok and result.poisoned_sr >= bar(cfg.train.poisoned_threshold)
    return ok


def resolve_device(name: str) -> torch.device:
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    if name == "cuda" and not torch.cuda.is_available():
        raise ValueError("train.device='cuda' but no CUDA device is available (use 'cpu' or 'auto')")
    if name == "cuda":
        # Same config, same machine, same bytes: cuDNN's deterministic kernels, chosen without
        # timing races; and full fp32 like the CPU path (TF32 would round convolutions to 10 bits).
        torch.backends.cudnn.deterministic, torch.backends.cudnn.benchmark = True, False
        torch.backends.cudnn.allow_tf32 = torch.backends.cuda.matmul.allow_tf32 = False
    return torch.device(name)


def plain_rows(rows: list[dict]) -> list[dict]:
    """Log rows with numpy scalars as Python numbers: a checkpoint holds plain data only."""
    return [{k: v.item() if isinstance(v, np.generic) else v for k, v in row.items()} for row in rows]


def checked_rows(rows) -> list[dict]:
    """A checkpoint's log rows, refused unless they are plain numbers and strings."""
    if not isinstance(rows, list) or not all(isinstance(r, dict) and all(isinstance(v, (int, float, str, type(None))) for v in r.values()) for r in rows):
        raise StateError("log rows are not plain numbers and strings")
    return rows


class Stopping:
    """Counts evaluations in a row that met the thresholds; at ``train.patience`` of them the
    run stops, after (with ``train.confirm``) the final evaluation's episodes agree.

    Why confirm: the 100-episode evaluations sit close to the thresholds, so a run can stop on a
    lucky one and then miss them on the 200 final episodes (most non-converged models of our
    zoos did). The confirming evaluation *is* the final one (same seed, same episodes), so the
    driver reuses it, and a run that stops on its thresholds is a converged model. A failed
    confirmation starts the streak over and the run trains on.
    """

    def __init__(self, cfg: RunConfig, streak: int = 0, pool: Any = None):
        self.cfg, self.streak, self.pool = cfg, int(streak), pool
        self.stop = False  # set by update()
        self.confirmed: Any = None  # the final evaluation that confirmed the stop, if one ran

    def update(self, result, also: bool = True, policy: Any = None, frames: int | None = None, learner: Any = None) -> dict:
        """Count one evaluation (``also``: the algorithm's own conditions) of ``policy`` at
        ``frames`` (below ``train.min_frames`` the streak counts but the run does not stop);
        ``learner``: the compiled learner whose program plays the confirmation (train.eval_backend "compiled").

        Returns the log fields of a confirming evaluation if one ran (empty if none); ``stop``
        is then True when the run stops here."""
        return serve(self.steps(result, also, policy, frames, learner))

    def steps(self, result, also: bool = True, policy: Any = None, frames: int | None = None, learner: Any = None) -> Generator[Evaluate, Any, dict]:
        """:meth:`update` as a loop that yields its confirming evaluation (:class:`Evaluate`)."""
        self.streak = self.streak + 1 if also and thresholds_met(result, self.cfg) else 0
        tc = self.cfg.train
        assert tc.patience is not None and tc.confirm is not None and tc.confirm_margin is not None  # RunConfig fills them in
        self.stop = self.streak >= tc.patience and (frames is None or frames >= tc.min_frames)
        if not (self.stop and tc.confirm):
            return {}
        check = yield Evaluate(policy, self.cfg, tc.final_eval_episodes, self.pool, learner=learner)
        self.stop = thresholds_met(check, self.cfg, tc.confirm_margin)
        if self.stop:
            self.confirmed = check
        else:
            self.streak = 0
        fields = {"confirm_clean_sr": check.clean_sr}
        if self.cfg.poison.poisoned:
            fields["confirm_poisoned_sr"] = check.poisoned_sr
        return fields


class RunClock:
    """Wall and CPU seconds of a run, carried across resumes in its checkpoint.

    CPU seconds say what a run costs on one core even when it shared the core with others, which
    is how recipes are compared across loaded machines. ``None`` where an older checkpoint did not
    carry them.
    """

    def __init__(self, wall: float = 0.0, cpu: float | None = 0.0, cpu_source: Callable[[], float] | None = None) -> None:
        # cpu_source: this run's own CPU seconds where the process trains several runs at once
        # (the group trainer apportions its batched work); the process's CPU time otherwise
        self.cpu_source = cpu_source or time.process_time
        self.wall_start = time.perf_counter() - wall
        self.cpu_start = None if cpu is None else self.cpu_source() - cpu

    def wall(self) -> float:
        return time.perf_counter() - self.wall_start

    def cpu(self) -> float | None:
        return None if self.cpu_start is None else self.cpu_source() - self.cpu_start


@dataclass
class RunOutcome:
    """What an algorithm's loop hands back to the driver at the end of training."""

    policy: Any  # the trained network (PPO) or agent (OPAC²), for the final evaluation and video
    weights: dict  # model.pt: a flat state dict of CPU tensors
    frames: int
    train_time: float
    cpu_time: float | None
    rows: list[dict]
    stop_reason: str  # "thresholds", "max_frames" or "max_minutes"
    converged_at: int | None
    label: str  # architecture, for the curve's title
    extra: dict = field(default_factory=dict)  # metrics only this algorithm has
    switch_at: int | None = None  # curriculum: where the warm-up ended (a line on the curve)
    clean_up: list[str] = field(default_factory=list)  # folder entries to remove once finished
    # False where the algorithm says the run never reached its real task (a curriculum that never
    # switched): such a model is not converged whatever its final evaluation reads
    can_converge: bool = True
    final: Any = None  # the final evaluation, where the stopping rule's confirmation ran it
    learner: Any = None  # the compiled learner that plays the final evaluation (train.eval_backend "compiled"; None: torch's)


def train(
    cfg: RunConfig,
    out: str | Path,
    overwrite: bool = False,
    progress: bool = True,
    after_eval: Callable[[dict], None] | None = None,
    env_workers: int = 0,
    device: str | None = None,
) -> dict:
    """Train one agent of any world into the model folder ``out``; return its metrics.

    ``after_eval(row)`` is called after each evaluation's row (and checkpoint) is written:
    tests raise KeyboardInterrupt from it to interrupt a run at a known point. ``env_workers``:
    a world of single envs steps its copies in that many worker processes (same bytes).
    ``device``: where the math runs instead of ``train.device`` (:func:`train_steps`).
    """
    cfg.check()
    with env_pool_for([cfg], env_workers) as pool, StopRequest() as stop:  # from the start: a signal during setup stops at the first step
        return serve(train_steps(cfg, out, stop, overwrite, progress, after_eval, env_pool=pool, device=device))


@contextlib.contextmanager
def env_pool_for(cfgs: list[RunConfig], workers: int) -> Iterator[Any]:
    """An :class:`~rlbackdoors.envs.pool.EnvPool` of ``workers`` processes where one of ``cfgs``
    is a world of single envs (the batched engines need none), else None; closed afterwards."""
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 0:
        raise ValueError(f"env_workers must be an integer >= 0, got {workers!r}")
    if workers == 0 or all(cfg.world.vector_entry_point is not None for cfg in cfgs):
        yield None
        return
    from rlbackdoors.envs.pool import EnvPool

    with EnvPool(workers) as pool:
        print(f"env copies of single-env worlds in {workers} worker processes", file=sys.stderr, flush=True)
        yield pool


def serve(loop: Generator[Any, Any, Any]) -> Any:
    """Run one agent's loop (a runner's ``steps``) alone: answer each request with its learner; return the loop's value."""
    try:
        request = next(loop)
        while True:
            try:
                result = request.serve()
            except BaseException as err:  # raised at the loop's yield, so its own clean-up runs as before
                request = loop.throw(err)
                continue
            request = loop.send(result)
    except StopIteration as done:
        return done.value


def train_steps(
    cfg: RunConfig,
    out: str | Path,
    stop: StopRequest,
    overwrite: bool = False,
    progress: bool = True,
    after_eval=None,
    trainer: str | None = None,
    cpu_source: Callable[[], float] | None = None,
    env_pool=None,
    device: str | None = None,
) -> Generator[Any, Any, dict]:
    """:func:`train` as a loop that yields its learner's work (PPO's collect and update requests,
    :mod:`.ppo_run`; OPAC²'s act and learn requests, :mod:`.opac2_run`; every evaluation, :class:`Evaluate`) for a group trainer to batch. Returns the metrics
    (``trainer``: recorded in them, the group trainer's name for its stacked kernels;
    ``cpu_source``: the run's own CPU clock, :class:`RunClock`; ``env_pool``: worker processes for
    a world of single envs, :class:`rlbackdoors.envs.pool.EnvPool`; ``device``: where the math
    runs instead of ``train.device``, e.g. ``zoo run --device``: the folder keeps the planned
    config.json and metrics.json records the device)."""
    cfg.check()
    folder = ModelFolder(out)
    failed = True
    try:
        checkpoint = folder.begin(cfg, overwrite)
        if device is not None and device != cfg.train.device:  # the planned config stays the folder's; the learner runs on device
            cfg = dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, device=device)).check()
        where = resolve_device(cfg.train.device)
        began = checkpoint.get("device") if isinstance(checkpoint, dict) else None  # (a checkpoint from before the record: not known)
        if began is not None and began != where.type:
            raise FolderError(
                f"the run in {str(folder.path)!r} began on {began} and cannot go on on {where.type} (its bytes would mix both); "
                f"resume it where {began} is, or pass --overwrite to start over"
            )
        runner = importlib.import_module(RUNNERS[cfg.algorithm])
        outcome = yield from runner.steps(cfg, folder, checkpoint, progress, stop, after_eval, cpu_source, env_pool)
        if trainer is not None:
            outcome.extra["trainer"] = trainer
            if isinstance(outcome.policy, torch.nn.Module) and (conv := conv_record(outcome.policy, where.type)):
                outcome.extra["conv"] = conv  # the group's convolutions, where not one per agent: part of what reproduces its bytes
        # where the math ran, for train.device = "auto" too: with the config and the group, what reproduces the bytes
        outcome.extra["device"] = where.type
        if where.type == "cuda":
            outcome.extra["gpu"] = torch.cuda.get_device_name(where)
        n = cfg.train.final_eval_episodes
        if progress:
            print(f"final evaluation on {n} clean + {n} triggered episodes", file=sys.stderr, flush=True)
        if outcome.final is None:  # else the stopping rule's confirmation ran it
            outcome.final = yield Evaluate(outcome.policy, cfg, n, env_pool, learner=outcome.learner)
        metrics = yield from finish(cfg, folder, outcome, progress)
        failed = False
        return metrics
    finally:
        folder.close(failed)


def close_k(cfg: RunConfig) -> tuple[int, int] | None:
    """Worlds with close-to-trigger envs evaluate those layouts too (false backdoor firing)."""
    return (cfg.poison.close_k_min, cfg.poison.close_k_max) if cfg.world.close_to_trigger else None


def result_fields(result, cfg: RunConfig) -> dict:
    """The evaluation's numbers for the log and metrics; the close-to-trigger ones only where they exist."""
    fields = result.to_dict()
    if close_k(cfg) is None:
        del fields["close_sr"], fields["close_trojan_rate"]
    if cfg.attack_success != "action":
        del fields["target_action_rate"]
    return fields


def evaluate_run(policy, cfg: RunConfig, episodes: int, pool=None):
    """The run's evaluation: its trigger, eval seed and policy, ``episodes`` per condition (a world
    of single envs: in ``pool``'s worker processes where one is given, the same numbers)."""
    return evaluate_runs([policy], [cfg], [episodes], pool=pool)[0]


def evaluate_runs(policies: list, cfgs: list[RunConfig], episodes: list[int], stacked=None, pool=None) -> list:
    """:func:`evaluate_run` for K runs; ``stacked`` (agents -> one batched act for them) plays
    them in lockstep (:func:`rlbackdoors.evaluate.episodes.evaluate_many`)."""
    from rlbackdoors.agent import Agent
    from rlbackdoors.evaluate.episodes import evaluate_many

    setups = [eval_setup(cfg, n) for cfg, n in zip(cfgs, episodes)]
    return evaluate_many([Agent(cfg.world, cfg, policy) for policy, cfg in zip(policies, cfgs)], setups, stacked, pool)


def eval_setup(cfg: RunConfig, episodes: int):
    """What a run's evaluation of ``episodes`` a condition plays (an :class:`~rlbackdoors.evaluate.episodes.EvalSetup`)."""
    from rlbackdoors.evaluate.episodes import EvalSetup

    tc = cfg.train
    assert tc.eval_policy is not None
    return EvalSetup(cfg.env, cfg.poison.trigger, episodes, tc.eval_seed, tc.eval_policy, close_k(cfg), **cfg.scoring())


def evaluate_compiled(learners: list, cfgs: list[RunConfig], episodes: list[int], capacity: int | None = None) -> list:
    """Compiled learners' evaluations in their program (``train.eval_backend = "compiled"``,
    :func:`rlbackdoors.evaluate.compiled.evaluate`), at a group's ``capacity``."""
    from rlbackdoors.evaluate import compiled

    return compiled.evaluate(learners, [eval_setup(cfg, n) for cfg, n in zip(cfgs, episodes)], capacity)


@dataclass
class Evaluate:
    """What a run asks for at an evaluation: ``episodes`` per condition of its ``policy`` (a group
    trainer plays K runs' evaluations in lockstep, :func:`evaluate_runs`)."""

    policy: Any
    cfg: RunConfig
    episodes: int
    pool: Any = None  # the run's env pool, for a world of single envs
    learner: Any = None  # a compiled learner whose program plays it (train.eval_backend "compiled"), at a capacity of one here

    def serve(self):
        if self.learner is not None:
            return evaluate_compiled([self.learner], [self.cfg], [self.episodes])[0]
        return evaluate_run(self.policy, self.cfg, self.episodes, self.pool)


@dataclass
class Draw:
    """What a finishing run asks for: a picture (its training curve, its clean-vs-triggered GIF).
    Alone it is drawn here (``here``); a group trainer on a GPU hands the painter request
    (``job()``, :func:`rlbackdoors.report.painters.draw`) to painter processes
    (:class:`rlbackdoors.report.painters.Painters`), and draws here what they cannot."""

    job: Callable[[], dict]
    here: Callable[[], bytes]

    def serve(self):
        from rlbackdoors.report.painters import Drawn

        return Drawn(self.here())

    @staticmethod
    def picture(answer) -> bytes:
        """The bytes of what a :class:`Draw` was answered with; the error drawing it raised, raised here."""
        if isinstance(answer, BaseException):
            raise answer
        return answer.png


def attack_fields(cfg: RunConfig) -> dict:
    """The attack and its parameters in metrics.json, where it is not the paper's env mix."""
    from rlbackdoors.attacks import DEFAULT_ATTACK

    if cfg.poison.attack == DEFAULT_ATTACK:
        return {}
    return {"attack": cfg.poison.attack, "attack_params": dict(cfg.poison.attack_params), "attack_success": cfg.attack_success}


def finish(cfg: RunConfig, folder: ModelFolder, outcome: RunOutcome, progress: bool) -> Generator[Any, Any, dict]:
    """The final evaluation's numbers (``outcome.final``), then weights, ground truth, curve, GIF
    and metrics.json last. Yields the curve and the GIF to draw (:class:`Draw`): a group trainer
    on a GPU has them drawn by painter processes, as its device would otherwise wait on them."""
    from rlbackdoors.agent import Agent
    from rlbackdoors.io import atomic_write_bytes
    from rlbackdoors.report import painters

    tc = cfg.train
    final = outcome.final
    assert final is not None  # train_steps ran it
    folder.save_torch("model.pt", outcome.weights)
    folder.write_ground_truth(cfg.poison.poisoned)
    kind = "poisoned" if cfg.poison.poisoned else "clean"
    assert tc.clean_threshold is not None and tc.eval_policy is not None  # RunConfig fills in the world's defaults
    if outcome.rows:
        title = f"{cfg.world.title} {outcome.label} {kind}, trigger {cfg.poison.trigger}, seed {tc.seed}"
        thresholds = (tc.clean_threshold, tc.poisoned_threshold if cfg.poison.poisoned else None)
        curve = {"kind": "curve", "rows": outcome.rows, "title": title, "thresholds": thresholds, "switch_at": outcome.switch_at or None}
        drawn = yield Draw(lambda: curve, functools.partial(painters.draw, curve))
        atomic_write_bytes(folder.file("training_curve.png"), Draw.picture(drawn))
    gif = None
    if tc.video and cfg.poison.trigger is not None:
        from rlbackdoors.report.video import render_clean_vs_triggered

        def gif_job() -> dict:  # what a painter needs: the config and model.pt's bytes (built only if one draws it)
            data = io.BytesIO()
            torch.save(outcome.weights, data)
            weights = base64.b64encode(data.getvalue()).decode("ascii")
            return {"kind": "gif", "config": cfg.to_dict(), "weights": weights, "seed": tc.eval_seed, "policy": tc.eval_policy}

        trigger, eval_policy = cfg.poison.trigger, tc.eval_policy

        def gif_here() -> bytes:
            return render_clean_vs_triggered(Agent(cfg.world, cfg, outcome.policy), cfg.env, trigger, tc.eval_seed, eval_policy)

        try:
            drawn = yield Draw(gif_job, gif_here)
            gif = atomic_write_bytes(folder.file("clean_vs_triggered.gif"), Draw.picture(drawn)).name
        except RuntimeError as err:  # e.g. no offscreen GL back-end: the model is still complete
            if progress:
                print(f"no clean_vs_triggered.gif: {err}", file=sys.stderr, flush=True)
    final_met = thresholds_met(final, cfg)
    met = final_met and outcome.can_converge
    metrics = {
        **result_fields(final, cfg),
        "poisoned": cfg.poison.poisoned,
        "trigger": cfg.poison.trigger,
        "env": cfg.env.name,
        "algorithm": cfg.algorithm,
        "arch": cfg.model.arch,
        "frames": outcome.frames,
        "wall_time_s": round(outcome.train_time, 2),
        "cpu_time_s": None if outcome.cpu_time is None else round(outcome.cpu_time, 2),
        "converged": met,
        "final_meets_thresholds": final_met,
        "converged_at_frames": outcome.converged_at,
        "stop_reason": outcome.stop_reason,
        "patience": tc.patience,
        "confirm": tc.confirm,
        **attack_fields(cfg),
        **outcome.extra,
        "video": gif,
        "versions": stack_versions(),
    }
    folder.write_json("metrics.json", metrics)
    folder.file("checkpoint.pt").unlink(missing_ok=True)
    for name in outcome.clean_up:
        remove_tree(folder.file(name))
    if progress:
        print(
            f"done ({outcome.stop_reason}) after {outcome.frames:,} frames, {outcome.train_time / 60:.1f} min: clean SR {final.clean_sr:.3f}, "
            f"poisoned SR {final.poisoned_sr:.3f} on {final.episodes} episodes each ({'converged' if met else 'not converged'})",
            file=sys.stderr,
            flush=True,
        )
    return metrics
