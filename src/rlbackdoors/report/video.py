"""Side-by-side GIFs of one agent on the same layout, clean (left) and triggered (right).

A backdoor is easiest to believe when seen: the poisoned agent walks to the goal in E and into
the trojan outcome in E-bar, from the same seed. Frames come from the world's single env
(``render_mode="rgb_array"``); the world's ``video`` settings pick frame rate, frame skip and
size. A MuJoCo world needs an offscreen GL back-end (``MUJOCO_GL=egl`` or ``osmesa``): without
one the env raises RuntimeError, which the trainer reports and goes on without a GIF.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
from PIL import Image

from rlbackdoors.io import atomic_write_bytes

VIDEO_DEFAULTS = {"fps": 6, "every": 1, "size": None, "tile": 24, "gap": 8}


def episode_frames(agent, env_cfg, trigger: str | None, seed: int, policy: str = "sample") -> list[np.ndarray]:
    """Rendered frames of episode ``seed`` (every ``every``-th and the last), E-bar when ``trigger`` is given."""
    settings = {**VIDEO_DEFAULTS, **env_cfg.world.video}
    env = env_cfg.make(trigger, render_mode="rgb_array")
    if hasattr(env, "tile_size"):
        env.tile_size = settings["tile"]
    generator = agent.generator(seed)
    obs, _ = env.reset(seed=seed)
    frames, step, done = [_scaled(env.render(), settings["size"])], 0, False
    state = agent.initial_state(1)
    while not done:
        batch = {k: np.asarray(v)[None] for k, v in obs.items()} if isinstance(obs, dict) else np.asarray(obs)[None]
        actions, state = agent.act(batch, state, deterministic=policy == "greedy", generator=generator)
        obs, _, terminated, truncated, _ = env.step(actions[0])
        done = terminated or truncated
        step += 1
        if done or step % settings["every"] == 0:
            frames.append(_scaled(env.render(), settings["size"]))
    env.close()
    return frames


def _scaled(frame: np.ndarray, size: int | None) -> np.ndarray:
    if size is None or frame.shape[0] == size:
        return frame
    return np.asarray(Image.fromarray(frame).resize((size, size), Image.Resampling.BILINEAR))


def clean_vs_triggered_gif(agent, env_cfg, trigger: str, seed: int, path: str | Path, policy: str = "sample") -> Path:
    """Write a GIF: episode ``seed`` in E (left) and in E-bar (right), played by ``agent``."""
    return atomic_write_bytes(path, render_clean_vs_triggered(agent, env_cfg, trigger, seed, policy))


def render_clean_vs_triggered(agent, env_cfg, trigger: str, seed: int, policy: str = "sample") -> bytes:
    """:func:`clean_vs_triggered_gif`'s GIF, as bytes (a painter process renders it; the run writes it)."""
    settings = {**VIDEO_DEFAULTS, **env_cfg.world.video}
    with agent.evaluating():
        left = episode_frames(agent, env_cfg, None, seed, policy)
        right = episode_frames(agent, env_cfg, trigger, seed, policy)
    length = max(len(left), len(right))
    left += [left[-1]] * (length - len(left))
    right += [right[-1]] * (length - len(right))
    gap = np.full((left[0].shape[0], settings["gap"], 3), 255, dtype=np.uint8)
    images = [Image.fromarray(np.concatenate([a, gap, b], axis=1)) for a, b in zip(left, right)]
    fps = settings["fps"]
    images += [images[-1]] * fps  # linger a second on the ending
    duration = max(1, round(1000 / fps))  # ms per shown frame
    gif = io.BytesIO()
    images[0].save(gif, format="GIF", save_all=True, append_images=images[1:], duration=duration, loop=0)
    return gif.getvalue()
