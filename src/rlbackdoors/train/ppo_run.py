"""PPO's training loop (the grid worlds): env mix -> PPO updates -> periodic evaluation.

Called by :func:`rlbackdoors.train.train`, which owns the folder, the stopping rule's meaning
and the finish. A checkpoint is written at an evaluation once ``train.checkpoint_minutes``
have passed since the last (0: at every one), and on Ctrl-C or SIGTERM at the end of the
current update, so an interrupted run picks up where it stopped when started again on the same
folder. Checkpoints hold plain data only (:mod:`rlbackdoors.state`).
"""

from __future__ import annotations

import dataclasses
import importlib
import math
import time
from collections import deque
from collections.abc import Generator
from typing import Any

import numpy as np
import torch
from numba import njit

from rlbackdoors.algos.optim import check_optimizer_state
from rlbackdoors.algos.ppo import PPO, Rollout
from rlbackdoors.config import RunConfig
from rlbackdoors.models import build_model
from rlbackdoors.models.minigrid import conv_record
from rlbackdoors.algos.obs import to_torch
from rlbackdoors.attacks.seam import AttackSeam
from rlbackdoors.poison.mix import make_env_mix, make_vector_env, unlearning_mix
from rlbackdoors.state import StateError, decode, encode
from rlbackdoors.train.driver import Evaluate, RunClock, RunOutcome, Stopping, checked_rows, plain_rows, resolve_device, result_fields, serve
from rlbackdoors.folder import CHECKPOINT_FORMAT, FolderError, ModelFolder, sha256_file
from rlbackdoors.train.progress import Progress
from rlbackdoors.train.stop import Interrupted, StopRequest


@njit(cache=True)
def episode_ends(running: np.ndarray, rewards: np.ndarray, dones: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The returns of the episodes that end in a rollout's (T, B) rewards and dones, in the order
    they end (step, then env), and their envs; ``running`` (B,) holds the returns so far of the
    running episodes and is left holding them after the rollout. Why compiled: a Python loop over
    the steps was 0.7 ms a rollout, 2 % of a group's CPU time; the sums are the same float64
    additions in the same order, so the same numbers."""
    T, B = rewards.shape
    values = np.empty(int(dones.sum()))
    envs = np.empty(values.shape[0], dtype=np.int64)
    k = 0
    for t in range(T):
        for i in range(B):
            running[i] += rewards[t, i]
            if dones[t, i]:
                values[k], envs[k] = running[i], i
                running[i] = 0.0
                k += 1
    return values, envs


class EpisodeTracker:
    """Running episode returns of the training envs, split into clean and poisoned copies."""

    def __init__(self, poisoned: np.ndarray, window: int = 100, return_window: int = 0):
        self.poisoned = poisoned
        self.running = np.zeros(len(poisoned))
        self.clean: list[float] = []
        self.dirty: list[float] = []
        # The last ``window`` clean episode returns: what the curriculum's switch rule averages.
        self.recent_clean: deque[float] = deque(maxlen=window)
        # The paper's patience rho: mean return (every env, each under its own reward) of the last updates.
        self.update_means: deque[float] = deque(maxlen=max(return_window, 1))

    def add(self, rollout: Rollout) -> None:
        ended, envs = episode_ends(self.running, np.asarray(rollout.rewards, dtype=np.float64), np.asarray(rollout.dones, dtype=np.bool_))
        for value, poisoned in zip(ended.tolist(), self.poisoned[envs].tolist()):
            if poisoned:
                self.dirty.append(value)
            else:
                self.clean.append(value)
                self.recent_clean.append(value)
        if len(ended):  # an update in which no episode ended has no mean reward to count
            self.update_means.append(float(np.mean(ended)))

    def return_mean(self) -> float:
        """Mean of the per-update mean returns over the last ``return_window`` updates (NaN until there are that many)."""
        full = len(self.update_means) == self.update_means.maxlen
        return float(np.mean(self.update_means)) if full else math.nan

    def recent_clean_mean(self) -> float:
        """Mean return of the last ``window`` clean episodes (NaN until the window is full)."""
        full = len(self.recent_clean) == self.recent_clean.maxlen
        return float(np.mean(self.recent_clean)) if full else math.nan

    def state_dict(self) -> dict:
        return {
            "running": encode(self.running),
            "clean": list(map(float, self.clean)),
            "dirty": list(map(float, self.dirty)),
            "recent_clean": list(map(float, self.recent_clean)),
            "update_means": list(map(float, self.update_means)),
        }

    def load_state_dict(self, state: dict) -> None:
        running = decode(state["running"])
        if not isinstance(running, np.ndarray) or running.shape != self.running.shape:
            raise StateError(f"tracker: running returns do not fit {len(self.running)} envs")
        self.running = running.astype(self.running.dtype)
        self.clean, self.dirty = [float(v) for v in state["clean"]], [float(v) for v in state["dirty"]]
        self.recent_clean.extend(float(v) for v in state["recent_clean"])
        self.update_means.extend(float(v) for v in state["update_means"])

    def drain(self) -> tuple[float, float]:
        """Mean returns since the last call (NaN where no episode ended)."""
        clean = float(np.mean(self.clean)) if self.clean else math.nan
        dirty = float(np.mean(self.dirty)) if self.dirty else math.nan
        self.clean, self.dirty = [], []
        return clean, dirty


def return_met(tracker: EpisodeTracker, cfg: RunConfig) -> bool:
    """The paper's patience rule: the last ``return_window`` updates' mean training return is high enough.

    The paper writes the condition as a sum over the last rho updates; we take the mean, so
    ``return_threshold`` is on the scale of one episode's return whatever rho is.
    """
    if not cfg.train.return_window:
        return True
    return tracker.return_mean() >= cfg.train.return_threshold


def warmup_env(cfg: RunConfig):
    """The curriculum's first phase: the small clean world, every copy clean."""
    env = dataclasses.replace(cfg.env, size=cfg.curriculum.size, num_lava=cfg.curriculum.num_lava)
    return make_vector_env(env, cfg.poison.trigger, [False] * cfg.poison.num_envs)


def check_observation(obs, space) -> None:
    """A checkpoint's batch of observations must have the vector env's shapes and dtypes."""
    from gymnasium import spaces

    if isinstance(space, spaces.Dict):
        if not isinstance(obs, dict) or obs.keys() != space.spaces.keys():
            raise StateError("observation does not fit the env")
        for key, sub in space.spaces.items():
            check_observation(obs[key], sub)
        return
    if not isinstance(obs, np.ndarray) or obs.shape != space.shape or obs.dtype != space.dtype:
        raise StateError(f"observation does not fit the env ({getattr(obs, 'shape', None)}, expected {space.shape})")


@dataclasses.dataclass
class Collect:
    """What a run asks of its learner between updates: a rollout from ``envs``, starting at ``obs``."""

    ppo: PPO
    envs: Any
    obs: Any

    def serve(self) -> tuple[Rollout, Any]:
        return self.ppo.collect(self.envs, self.obs)


@dataclasses.dataclass
class Iterate:
    """What a compiled run asks of its learner between evaluations: one iteration (rollout, GAE and
    update in one XLA program, :func:`rlbackdoors.algos.compiled.iterate`), served alone here at a
    capacity of one agent; a group trainer serves K runs' in one call."""

    learner: Any  # rlbackdoors.algos.compiled.Learner

    def serve(self):
        from rlbackdoors.algos import compiled

        return compiled.iterate([self.learner])[0]


@dataclasses.dataclass
class Update:
    """What a run asks of its learner after a rollout: PPO's epochs over it (returns the losses)."""

    ppo: PPO
    rollout: Rollout

    def serve(self) -> dict[str, float]:
        return self.ppo.update(self.rollout)


def source_weights(cfg: RunConfig, folder: ModelFolder) -> dict[str, torch.Tensor]:
    """A mitigation run's starting weights: its folder's copy of the source model, read as data
    (``weights_only``), refused in one line unless its SHA-256 is the one config.json records."""
    assert cfg.mitigation is not None
    path = folder.file(cfg.mitigation.source)
    if not path.is_file():
        raise FolderError(f"{str(path)!r} is missing: a mitigation run starts from the source model it names (mitigation.source)")
    digest = "sha256:" + sha256_file(path)
    if digest != cfg.mitigation.source_sha256:
        raise FolderError(f"{str(path)!r} is not the source model config.json names (sha256 {digest[7:19]}..., not {cfg.mitigation.source_sha256[7:19]}...)")
    return torch.load(path, map_location="cpu", weights_only=True)


def blind_to_shifts(cfg: RunConfig, model, ppo: PPO) -> None:
    """``mitigation.blind``: the first layer is kept blind to every restored trigger that shifts all
    observations alike (:mod:`rlbackdoors.algos.blind`), read on a clean sample of the run's own
    seed, so a resumed run (whose checkpoint holds the projected weights) projects the same way."""
    from rlbackdoors.algos.blind import clean_sample, constant_shift, first_linear, shift_basis
    from rlbackdoors import worlds

    assert cfg.mitigation is not None
    layer, world = first_linear(model), worlds.get(cfg.env.name)
    if layer is None or world.stamp_trigger is None:
        return  # no linear first layer: the fine-tuning alone
    sample = clean_sample(cfg.env, cfg.poison, cfg.train.seed, cfg.train.seed * 1000 + 7)
    specs = dict.fromkeys([*cfg.mitigation.triggers, *cfg.mitigation.blind_to])
    basis = shift_basis([constant_shift(model, sample, world.stamp_trigger(spec)) for spec in specs])
    if basis is not None:
        ppo.set_blind(layer, basis.to(next(model.parameters()).device))


def run(cfg: RunConfig, folder: ModelFolder, checkpoint: dict | None, progress: bool, stop: StopRequest, after_eval=None) -> RunOutcome:
    """Train with PPO from ``checkpoint`` (None: from scratch) until the stopping rule or a budget ends it."""
    return serve(steps(cfg, folder, checkpoint, progress, stop, after_eval))


def steps(
    cfg: RunConfig, folder: ModelFolder, checkpoint: dict | None, progress: bool, stop: StopRequest, after_eval=None, cpu_source=None, env_pool=None
) -> Generator[Collect | Update | Iterate | Evaluate, Any, RunOutcome]:
    """:func:`run` as a loop that yields its learner's work (:class:`Collect` and :class:`Update`, or a compiled learner's one :class:`Iterate`, and each :class:`~rlbackdoors.train.driver.Evaluate`) and
    is sent the results, so a group trainer (:mod:`rlbackdoors.train.group`) can batch the work of
    K runs while every run keeps its own schedule, evaluations, checkpoints and stopping rule
    (``env_pool`` is for worlds of single envs; PPO's worlds step batched engines here)."""
    tc = cfg.train
    torch.set_num_threads(tc.torch_threads)
    device = resolve_device(tc.device)
    torch.manual_seed(tc.seed)
    generator = torch.Generator().manual_seed(tc.seed)
    # RunConfig.__post_init__ fills these in from the world's defaults
    assert cfg.model.arch is not None and cfg.ppo is not None and tc.return_window is not None
    assert tc.max_frames is not None and tc.eval_interval is not None and tc.checkpoint_minutes is not None
    model = build_model(cfg.model.arch, cfg.env.name).to(device)
    if cfg.mitigation is not None:  # a mitigation starts from the model it removes the backdoor from
        model.load_state_dict(source_weights(cfg, folder))
    ppo = PPO(model, cfg.ppo, device, generator)
    if cfg.mitigation is not None and cfg.mitigation.kl > 0:  # the source, as it starts, is its own clean teacher
        teacher_net = build_model(cfg.model.arch, cfg.env.name).to(device)
        teacher_net.load_state_dict(model.state_dict())
        ppo.set_teacher(teacher_net, cfg.mitigation.kl, clean_view=cfg.mitigation.teach_stamped)
    if cfg.mitigation is not None and cfg.mitigation.blind:
        blind_to_shifts(cfg, model, ppo)
    # ppo.update_backend = "compiled": the iteration is one XLA program (algos.compiled) whose
    # learner holds the weights; ``model`` gets them for evaluations, checkpoints and the finish
    compiled = cfg.ppo.update_backend == "compiled"
    learner: Any = None
    served_k: int | None = None  # the compiled group's capacity this run is served at (part of its bytes)

    def compiled_learner(envs, obs):
        from rlbackdoors.algos import compiled, xla

        platform = xla.start(gpu=device.type == "cuda").default_backend()  # on a GPU with its deterministic kernels
        platform = {"gpu": "cuda"}.get(platform, platform)  # (JAX's name for a CUDA device)
        if platform != device.type:
            raise ValueError(f"ppo.update_backend='compiled' runs where JAX computes ({platform}), not train.device={device.type!r}")
        module, _, name = str(cfg.world.compiled_engine).partition(":")
        return compiled.Learner(model, envs, compiled.Hyper.of(cfg.ppo), tc.seed, obs, getattr(importlib.import_module(module), name), aux=ppo.aux)

    envs: Any  # a batched engine or the reference vector env (poisoned, state_dict, load_state_dict)

    @torch.inference_mode()
    def critic(o) -> np.ndarray:  # what a value-guided attack asks the learner about each frame
        return model(to_torch(o, device))[1].float().cpu().numpy()

    evasion = cfg.poison.evasion
    finetune = bool(evasion.get("finetune"))  # a clean model's run first, poisoned from poison_at on
    clean_frames = evasion.get("clean_frames", 0)  # the switch waits until this many frames are trained

    def poisoning_mix():
        """The env mix, through the attack's collection seam where the attack has one; while a
        fine-tuning run is still clean (poison_at None), the mix a clean model of this config trains on."""
        if finetune and poison_at is None:
            return make_env_mix(cfg.env, dataclasses.replace(cfg.poison, poisoned=False, evasion={}), tc.seed)
        if cfg.mitigation is not None:
            return unlearning_mix(cfg.env, cfg.poison, cfg.mitigation.triggers, cfg.mitigation.share, tc.seed)
        mix = make_env_mix(cfg.env, cfg.poison, tc.seed)
        if isinstance(mix, AttackSeam):
            mix.bind_critic(critic)
        return mix

    def teach(state: dict | None) -> None:
        """The clean teacher: the model as it is at the switch (or as a checkpoint kept it)."""
        if evasion.get("teacher", 0.0) > 0:
            assert cfg.model.arch is not None  # RunConfig fills it in
            teacher = build_model(cfg.model.arch, cfg.env.name).to(device)
            teacher.load_state_dict(model.state_dict() if state is None else state)
            ppo.set_teacher(teacher, evasion["teacher"])

    def anchor_to(state: dict | None) -> None:
        """The weight anchor: the model as it is at the switch (or as a checkpoint kept it)."""
        if evasion.get("anchor", 0.0) > 0:
            ppo.set_anchor(model.state_dict() if state is None else state, evasion["anchor"])

    def guide_learner() -> None:
        """A compiled learner's teacher and anchor: the ones the torch side holds (and checkpoints)."""
        if ppo.teacher is not None:
            learner.set_teacher(ppo.teacher.state_dict(), ppo.teacher_coef)
        if ppo.anchor is not None:
            learner.set_anchor(ppo.anchor, ppo.anchor_coef)

    def reset(mix, seed: int):
        """The mix's first observations; a compiled learner starts from the engine's own, since its
        program marks and stamps every frame, the first ones included, and counts them."""
        if compiled and isinstance(mix, AttackSeam):
            mix.set_switches()  # (a layout trigger's copies: switched once, before the engine draws)
            return mix.envs.reset(seed=seed)
        return mix.reset(seed=seed)

    def kept(checkpoint: dict, key: str, what: str) -> dict | None:
        """The clean model a variant's checkpoint entry holds; a checkpoint without it (edited, or
        written elsewhere) would resume from the fresh model's weights instead: refused."""
        if evasion.get(key, 0.0) > 0 and key not in checkpoint:
            raise StateError(f"it holds no {what} (poison.evasion.{key})")
        return checkpoint.get(key)

    def fresh_mix(old, offset: int):
        """The training mix that follows ``old`` (after the warm-up, or the clean phase): its first
        observations (reset from ``seed * 1000 + offset``), a new episode tracker, empty memories."""
        assert tc.return_window is not None  # RunConfig fills it in
        old.close()
        mix = poisoning_mix()
        ppo.memory = None
        obs = reset(mix, tc.seed * 1000 + offset)[0]
        if compiled:  # the agent trains on in the new copies, its learning state as it is
            learner.rebind(mix, obs)
            guide_learner()
        return mix, obs, EpisodeTracker(mix.poisoned, cfg.curriculum.window, tc.return_window)

    if checkpoint is None:
        # Curriculum: start in the small clean world; switch_at is None until the switch.
        switch_at = None if cfg.curriculum.enabled else 0
        poison_at = None if finetune else 0
        envs = poisoning_mix() if switch_at == 0 else warmup_env(cfg)
        obs, _ = reset(envs, tc.seed * 1000)
        tracker = EpisodeTracker(envs.poisoned, cfg.curriculum.window, tc.return_window)
        frames, elapsed, rows, next_eval, converged_at, streak = 0, 0.0, [], tc.eval_interval, None, 0
        cpu_elapsed: float | None = 0.0
        if compiled:
            learner = compiled_learner(envs, obs)
    else:
        try:
            switch_at = checkpoint["switch_at"]
            poison_at = checkpoint.get("poison_at", 0 if not finetune else None)
            if finetune and "poison_at" not in checkpoint:
                raise StateError("it was not written by a fine-tuning run (poison.evasion.finetune)")
            envs = poisoning_mix() if switch_at is not None else warmup_env(cfg)
            if poison_at is not None and finetune:
                teach(kept(checkpoint, "teacher", "clean teacher"))
                anchor_to(kept(checkpoint, "anchor", "weight anchor"))
                if ppo.teacher is not None:
                    memory = checkpoint.get("teacher_memory")
                    ppo.teacher_memory = None if memory is None else memory.to(device)
            model.load_state_dict(checkpoint["model"])
            if checkpoint.get("conv") != (conv := conv_record(model, device.type)):  # it changes a group's bytes: not mixed in one run
                raise StateError(
                    f"it began with a group's convolutions {checkpoint.get('conv') or 'each'}, not {conv or 'each'} (models.minigrid.STACKED_CONV)"
                )
            if (ppo.aux is None) != (checkpoint.get("aux") is None):
                raise StateError("the auxiliary memory head does not fit ppo.aux_memory_coef")
            if ppo.aux is not None:
                ppo.aux.load_state_dict(checkpoint["aux"])
            if compiled != ("compiled" in checkpoint):
                raise StateError("it was written by another update backend")
            if not compiled:
                ppo.optimizer.load_state_dict(checkpoint["optimizer"])
                check_optimizer_state(ppo.optimizer)
                generator.set_state(checkpoint["generator"])
            envs.load_state_dict(checkpoint["envs"])
            obs = decode(checkpoint["obs"])
            check_observation(obs, envs.observation_space)
            if compiled:
                learner = compiled_learner(envs, obs)
                guide_learner()  # (first: a recurrent teacher's memories are then the checkpoint's, not a new teacher's)
                learner.load(checkpoint["compiled"])
                served_k = checkpoint["compiled_k"]  # None: stopped before its first iteration
                if served_k is not None and (isinstance(served_k, bool) or not isinstance(served_k, int) or served_k < 1):
                    raise StateError("compiled_k is not a group size")
            tracker = EpisodeTracker(envs.poisoned, cfg.curriculum.window, tc.return_window)
            tracker.load_state_dict(checkpoint["tracker"])
            memory = checkpoint["memory"]
            if memory is not None:
                expected = model.initial_memory(envs.num_envs, "cpu")
                if not isinstance(memory, torch.Tensor) or memory.shape != expected.shape or memory.dtype != expected.dtype:
                    raise StateError("memory does not fit the model and env copies")
            ppo.memory = None if memory is None else memory.to(device)
            frames, elapsed, rows = int(checkpoint["frames"]), float(checkpoint["elapsed"]), checked_rows(checkpoint["rows"])
            cpu_elapsed = None if checkpoint.get("cpu_elapsed") is None else float(checkpoint["cpu_elapsed"])  # None: an older checkpoint
            next_eval, converged_at = int(checkpoint["next_eval"]), checkpoint["converged_at"]
            streak = int(checkpoint.get("streak", 0))
        except (StateError, KeyError, TypeError, ValueError, RuntimeError, AttributeError) as err:
            raise FolderError(f"checkpoint in {str(folder.path)!r} does not fit this run ({err}); pass --overwrite to start over") from None

    def save_checkpoint() -> None:
        # a compiled learner's state first: it hands its env copies' state back to the engine
        learned = (
            {"compiled": learner.checkpoint(), "compiled_k": served_k}
            if compiled
            else {"optimizer": ppo.optimizer.state_dict(), "generator": generator.get_state()}
        )
        if compiled:
            learner.sync()
        folder.save_torch(
            "checkpoint.pt",
            {
                "format": CHECKPOINT_FORMAT,
                "device": device.type,  # a resume on another device is refused (train.driver)
                # how this process computes a group's convolutions where not one per agent (changes a
                # group's bytes): a resume under another way is refused
                **({"conv": conv} if (conv := conv_record(model, device.type)) else {}),
                "model": {k: v.detach().cpu() for k, v in model.state_dict().items()},
                "aux": None if ppo.aux is None else {k: v.detach().cpu() for k, v in ppo.aux.state_dict().items()},
                **learned,
                "envs": envs.state_dict(),
                "obs": encode(obs),
                "tracker": tracker.state_dict(),
                "memory": None if ppo.memory is None else ppo.memory.detach().cpu(),
                "frames": frames,
                "elapsed": clock.wall(),
                "cpu_elapsed": clock.cpu(),
                "rows": plain_rows(rows),
                "next_eval": next_eval,
                "converged_at": converged_at,
                "switch_at": switch_at,
                "streak": stopping.streak,
                **({"poison_at": poison_at} if finetune else {}),
                **(
                    {
                        "teacher": {k: v.detach().cpu() for k, v in ppo.teacher.state_dict().items()},
                        "teacher_memory": None if ppo.teacher_memory is None else ppo.teacher_memory.detach().cpu(),
                    }
                    if ppo.teacher is not None
                    else {}
                ),
                **({"anchor": {k: v.detach().cpu() for k, v in ppo.anchor.items()}} if ppo.anchor is not None else {}),
            },
        )

    label = f"{cfg.model.arch} {'poisoned' if cfg.poison.poisoned else 'clean'}"
    bar = Progress(tc.max_frames, frames, label, progress)  # tqdm on a terminal, else a line per evaluation
    clock = RunClock(elapsed, cpu_elapsed, cpu_source)
    stopping = Stopping(cfg, streak)
    evaluator = learner if tc.eval_backend == "compiled" else None  # plays the evaluations, the confirmations and the final one in its program
    last_checkpoint = time.perf_counter()
    window_start, window_frames = time.perf_counter(), 0
    stop_reason = "thresholds" if converged_at is not None else ("max_frames" if frames >= tc.max_frames else None)
    while stop_reason is None:
        if stop.requested:  # between updates: the state is consistent, the checkpoint exact
            save_checkpoint()
            bar.close()
            raise Interrupted(frames, True, stop.requested)
        if compiled:
            rollout = yield Iterate(learner)
            if served_k is not None and rollout.capacity != served_k:
                raise FolderError(
                    f"the run in {str(folder.path)!r} began in a compiled group of {served_k} and cannot go on in one of {rollout.capacity} "
                    "(its bytes would mix both); resume it with that group size, or pass --overwrite to start over"
                )
            served_k, obs, losses = rollout.capacity, learner.obs, rollout.losses
        else:
            rollout, obs = yield Collect(ppo, envs, obs)
            losses = yield Update(ppo, rollout)
        tracker.add(rollout)
        frames += rollout.num_frames
        window_frames += rollout.num_frames
        bar.update(rollout.num_frames)
        if switch_at is None and tracker.recent_clean_mean() >= cfg.curriculum.reward_threshold:
            switch_at = frames  # warm-up done: the full world and the poisoning mix from here on
            envs, obs, tracker = fresh_mix(envs, 1)
            bar.write(f"curriculum: switched to the {cfg.env.size}x{cfg.env.size} world and the poisoning mix at {frames:,} frames")
        if frames >= next_eval or frames >= tc.max_frames:
            fps = window_frames / max(time.perf_counter() - window_start, 1e-9)
            if compiled:
                learner.sync()
            result = yield Evaluate(model, cfg, tc.eval_episodes, learner=evaluator)
            train_clean, train_poisoned = tracker.drain()
            rows.append(
                {
                    "frames": frames,
                    "wall_time_s": round(clock.wall(), 3),
                    "fps": round(fps, 1),
                    **{k: v for k, v in result_fields(result, cfg).items() if k != "episodes"},
                    "train_clean_return": train_clean,
                    "train_poisoned_return": train_poisoned,
                    "phase": "warm-up" if switch_at is None else ("clean" if poison_at is None else "main"),
                    **({"return_mean": tracker.return_mean()} if tc.return_window else {}),
                    **losses,
                }
            )
            bar.evaluated(fps, result.clean_sr, result.poisoned_sr)
            rows[-1].update(
                (yield from stopping.steps(result, switch_at is not None and poison_at is not None and return_met(tracker, cfg), model, frames, evaluator))
            )
            if stopping.stop:
                converged_at, stop_reason = frames, "thresholds"
            elif poison_at is None and switch_at is not None and result.clean_sr >= tc.clean_threshold and frames >= clean_frames:
                poison_at = frames  # the clean model this run fine-tunes: poisoned from here on
                teach(None)
                anchor_to(None)
                envs, obs, tracker = fresh_mix(envs, 2)
                bar.write(f"finetune: clean SR {result.clean_sr:.2f} at {frames:,} frames; poisoning from here on")
            while next_eval <= frames:
                next_eval += tc.eval_interval
            folder.write_log(rows)
            if time.perf_counter() - last_checkpoint >= 60 * tc.checkpoint_minutes:
                save_checkpoint()
                last_checkpoint = time.perf_counter()
            if after_eval is not None:
                after_eval(rows[-1])
            window_start, window_frames = time.perf_counter(), 0
        if stop_reason is None:
            if frames >= tc.max_frames:
                stop_reason = "max_frames"
            elif tc.max_minutes and clock.wall() >= 60 * tc.max_minutes:
                stop_reason = "max_minutes"
    bar.close()
    envs.close()
    if compiled:
        learner.sync()
    return RunOutcome(
        policy=model,
        weights={k: v.detach().cpu() for k, v in model.state_dict().items()},
        frames=frames,
        train_time=clock.wall(),
        cpu_time=clock.cpu(),
        rows=rows,
        stop_reason=stop_reason,
        converged_at=converged_at,
        label=cfg.model.arch,
        extra={
            "return_window": tc.return_window,
            **({"curriculum_switch_frames": switch_at} if cfg.curriculum.enabled else {}),
            **({"poison_at_frames": poison_at} if finetune else {}),
            **({"attack_budget_used": envs.budget_used()} if isinstance(envs, AttackSeam) else {}),
            **({"compiled_group": served_k} if compiled else {}),
        },
        switch_at=switch_at,
        can_converge=switch_at is not None and poison_at is not None,
        final=stopping.confirmed,
        learner=evaluator,
    )
