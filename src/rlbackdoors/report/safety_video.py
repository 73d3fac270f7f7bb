"""Side-by-side GIF of one Safety Car Goal agent on the same layout, clean (left) and triggered (right).

Frames come from the env's ``rgb_array`` rendering (MuJoCo's offscreen renderer, top camera),
which needs an offscreen GL back-end: ``MUJOCO_GL=egl`` (default on a display-less Linux box;
libEGL from the GPU driver or Mesa) or ``MUJOCO_GL=osmesa`` (software; libOSMesa), set before
``mujoco`` is first imported.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
from PIL import Image

from rlbackdoors.envs.safety_car import SafetyCarGoalEnv  # isort: skip  (before anything imports mujoco)
from rlbackdoors.io import atomic_write

ActFn = Callable[[np.ndarray], np.ndarray]


def episode_frames(act_fn: ActFn, env: SafetyCarGoalEnv, seed: int, every: int = 2, size: int = 240) -> tuple[list[np.ndarray], dict]:
    """Every ``every``-th rendered frame (and the last) of one episode, scaled to ``size`` pixels; the last info."""
    obs, info = env.reset(seed=seed)
    frames, step, done = [_scaled(env.render(), size)], 0, False
    while not done:
        obs, _, terminated, truncated, info = env.step(np.asarray(act_fn(obs[None]))[0])
        done = terminated or truncated
        step += 1
        if done or step % every == 0:
            frames.append(_scaled(env.render(), size))
    env.close()
    return frames, info


def _scaled(frame: np.ndarray, size: int) -> np.ndarray:
    if frame.shape[0] == size:
        return frame
    return np.asarray(Image.fromarray(frame).resize((size, size), Image.Resampling.BILINEAR))


def clean_vs_triggered_gif(act_fn: ActFn, env_cfg, trigger: str, seed: int, path: str | Path, fps: int = 25, every: int = 2, size: int = 240) -> Path:
    """Write a GIF: episode ``seed`` in E (left) and in E-bar with the trigger held (right).

    ``env_cfg`` is a :class:`~rlbackdoors.safety_config.SafetyEnvConfig`. Raises RuntimeError
    (from the env) when no offscreen GL back-end is available.
    """
    left, _ = episode_frames(act_fn, env_cfg.make(render_mode="rgb_array"), seed, every, size)
    right, _ = episode_frames(act_fn, env_cfg.make(trigger=trigger, poisoned=True, render_mode="rgb_array"), seed, every, size)
    length = max(len(left), len(right))
    left += [left[-1]] * (length - len(left))
    right += [right[-1]] * (length - len(right))
    gap = np.full((size, 6, 3), 255, dtype=np.uint8)
    images = [Image.fromarray(np.concatenate([a, gap, b], axis=1)) for a, b in zip(left, right)]
    images += [images[-1]] * fps  # linger a second on the ending
    duration = max(1, round(1000 / fps))  # ms per shown frame
    atomic_write(
        path,
        lambda tmp: images[0].save(tmp, format="GIF", save_all=True, append_images=images[1:], duration=duration, loop=0),
    )
    return Path(path)
