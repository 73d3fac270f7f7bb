"""Side-by-side GIFs of one agent on the same layout, clean (left) and triggered (right).

A backdoor is easiest to believe when seen: the poisoned agent walks to the goal in E
and straight into the lava in E-bar, from the same seed. (In LavaWorld the layout is the
very same, the trigger only edits observations; in Randomized LavaWorld the triggered layout
also holds the inserted lava pattern; in Colorful Memory the far walls wear the trigger's colours.)
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from PIL import Image

from rlbackdoors.algos.obs import to_torch
from rlbackdoors.algos.ppo import sample_actions
from rlbackdoors.config import EnvConfig
from rlbackdoors.io import atomic_write
from rlbackdoors.models import ActorCritic


@torch.inference_mode()
def episode_frames(model: ActorCritic, env: EnvConfig, trigger: str | None, seed: int, tile: int = 24) -> list[np.ndarray]:
    """Rendered frames of one episode on the MiniGrid reference env (MiniGrid's renderer)."""
    from rlbackdoors.poison.mix import reference_world

    world = reference_world(env, trigger, render_mode="rgb_array")
    world.tile_size = tile
    generator = torch.Generator().manual_seed(seed)
    obs, _ = world.reset(seed=seed)
    frames = [world.render()]
    memory = model.initial_memory(1) if model.recurrent else None
    done = False
    while not done:
        batch = {k: np.asarray(v)[None] for k, v in obs.items()} if isinstance(obs, dict) else obs[None]
        if memory is not None:
            logits, _, memory = model(to_torch(batch), memory)
        else:
            logits, _ = model(to_torch(batch))
        obs, _, terminated, truncated, _ = world.step(int(sample_actions(logits, generator)[0]))
        frames.append(world.render())
        done = terminated or truncated
    world.close()
    return frames


def clean_vs_triggered_gif(model: ActorCritic, env: EnvConfig, trigger: str, seed: int, path: str | Path, fps: int = 6) -> Path:
    """Write a GIF: the same layout played in E (left) and in E-bar (right)."""
    left = episode_frames(model, env, None, seed)
    right = episode_frames(model, env, trigger, seed)
    length = max(len(left), len(right))
    left += [left[-1]] * (length - len(left))
    right += [right[-1]] * (length - len(right))
    gap = np.full((left[0].shape[0], 8, 3), 255, dtype=np.uint8)
    images = [Image.fromarray(np.concatenate([a, gap, b], axis=1)) for a, b in zip(left, right)]
    images += [images[-1]] * fps  # linger on the ending
    atomic_write(
        path,
        lambda tmp: images[0].save(tmp, format="GIF", save_all=True, append_images=images[1:], duration=int(1000 / fps), loop=0),
    )
    return Path(path)
