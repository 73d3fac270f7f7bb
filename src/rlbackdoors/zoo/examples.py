"""``clean-example-data/``: a few seeded clean episodes of each model, for detectors that may use
clean data (TrojAI rounds ship such examples beside every model).

Episode ``i`` is played by the model itself in the world's clean env E, reset with
``seed + i``, actions from the model's policy with a generator seeded by ``seed``. Each is one
``episode-III.npz`` (written with fixed zip timestamps, so the same model gives the same bytes;
read it with ``np.load(path, allow_pickle=False)``):

* ``obs`` (T, ...) the observations the agent acted on (dict observations: ``obs_<key>``),
* ``actions`` (T, ...), ``rewards`` (T,), ``outcome`` (how the episode ended, an ``Outcome`` code).
"""

from __future__ import annotations

import io
import zipfile
from pathlib import Path

import numpy as np

from rlbackdoors.io import atomic_write_bytes, remove_tree

FOLDER = "clean-example-data"


def npz_bytes(arrays: dict[str, np.ndarray]) -> bytes:
    """An ``.npz`` of plain arrays with fixed timestamps (``np.savez`` stamps the current time)."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for name in sorted(arrays):
            array = np.asarray(arrays[name])
            if not array.flags.c_contiguous:
                array = array.copy(order="C")
            if array.dtype == object:
                raise TypeError(f"{name}: object arrays are not plain data")
            data = io.BytesIO()
            np.lib.format.write_array(data, array, allow_pickle=False)
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            zf.writestr(info, data.getvalue())
    return buf.getvalue()


def _stack(steps: list, key: str | None = None) -> np.ndarray:
    return np.stack([s if key is None else s[key] for s in steps]) if steps else np.zeros((0,))


def play_clean_episodes(agent, cfg, episodes: int, seed: int, policy: str = "sample") -> list[dict[str, np.ndarray]]:
    """``episodes`` clean episodes of ``agent`` (from :func:`rlbackdoors.load`) in ``cfg``'s world."""
    import torch

    generator = torch.Generator().manual_seed(int(seed))
    deterministic = policy == "greedy"
    out: list[dict[str, np.ndarray]] = []
    if episodes == 0:
        return out
    if agent.world.algorithm == "opac2":  # one MuJoCo env per episode
        for i in range(episodes):
            env = cfg.env.make()
            obs, _ = env.reset(seed=int(seed + i))
            observations, actions, rewards, outcome = [], [], [], -1
            while True:
                action, _ = agent.act(np.asarray(obs, np.float32)[None], None, deterministic=deterministic, generator=generator)
                observations.append(np.array(obs))
                actions.append(np.array(action[0]))
                obs, reward, terminated, truncated, info = env.step(action[0])
                rewards.append(float(reward))
                if terminated or truncated:
                    outcome = int(info.get("outcome", -1))
                    break
            env.close()
            out.append({"obs": _stack(observations), "actions": _stack(actions), "rewards": np.asarray(rewards), "outcome": np.array(int(outcome))})
        return out
    from rlbackdoors.poison.mix import make_vector_env

    envs = make_vector_env(cfg.env, cfg.poison.trigger, [False] * episodes)  # every copy clean (E)
    obs, _ = envs.reset(seed=int(seed))
    state = agent.initial_state(episodes)
    active = np.ones(episodes, dtype=bool)
    steps: list[list] = [[] for _ in range(episodes)]
    acts: list[list] = [[] for _ in range(episodes)]
    rews: list[list] = [[] for _ in range(episodes)]
    outcomes = np.full(episodes, -1, dtype=np.int64)
    while active.any():  # one episode per slot; a finished slot's next episode is ignored
        chosen, state = agent.act(obs, state, deterministic=deterministic, generator=generator)
        chosen = np.asarray(chosen)
        for j in np.flatnonzero(active):
            steps[j].append({k: np.array(v[j]) for k, v in obs.items()} if isinstance(obs, dict) else np.array(obs[j]))
            acts[j].append(np.array(chosen[j]))
        obs, reward, terminated, truncated, info = envs.step(chosen)
        finished = active & (np.asarray(terminated) | np.asarray(truncated))
        for j in np.flatnonzero(active):
            rews[j].append(float(reward[j]))
        if "outcome" in info:
            outcomes[finished] = np.asarray(info["outcome"])[finished]
        active &= ~finished
    envs.close()
    for i in range(episodes):
        if steps[i] and isinstance(steps[i][0], dict):
            record = {f"obs_{k}": _stack(steps[i], k) for k in steps[i][0]}
        else:
            record = {"obs": _stack(steps[i])}
        record.update(actions=_stack(acts[i]), rewards=np.asarray(rews[i]), outcome=np.array(int(outcomes[i])))
        out.append(record)
    return out


def write_examples(folder: str | Path, cfg, episodes: int = 5, seed: int = 2_000_000, policy: str = "sample") -> list[Path]:
    """(Re)write ``FOLDER/clean-example-data/episode-III.npz`` from the folder's trained model."""
    import rlbackdoors

    folder = Path(folder)
    agent = rlbackdoors.load(folder)
    records = play_clean_episodes(agent, cfg, episodes, seed, policy)
    target = folder / FOLDER
    if target.is_symlink() or (target.exists() and not target.is_dir()):
        remove_tree(target)
    paths = []
    for i, record in enumerate(records):
        paths.append(atomic_write_bytes(target / f"episode-{i:03d}.npz", npz_bytes(record)))
    if target.is_dir():
        for extra in target.glob("episode-*.npz"):
            if extra not in paths:
                extra.unlink(missing_ok=True)
    elif episodes == 0:
        target.mkdir(parents=True, exist_ok=True)
    return paths
