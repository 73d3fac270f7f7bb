"""Does a LavaWorld FC state dict score the same on Farama's own MiniGrid env as on ours?

Plays ``--episodes`` episodes of ``MiniGrid-LavaCrossingS9N1-v0`` built by ``gymnasium.make``
(250-step limit, as LavaWorld), with a plain loop that knows nothing of rlbackdoors' envs,
and compares the success rate with ``rlbackdoors evaluate --weights`` on LavaWorld's default
configuration (a two-proportion z-test). Usage:

    python experiments/minigrid_weights_check/minigrid_weights_check.py runs/demo/poisoned-fc/model.pt --arch fc
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys

import gymnasium as gym
import minigrid  # noqa: F401  (registers MiniGrid ids)
import torch

from rlbackdoors.models import build_model, load_weights


def farama_success_rate(weights: str, arch: str, episodes: int, seed: int) -> float:
    model = load_weights(build_model(arch), weights).eval()
    env = gym.make("MiniGrid-LavaCrossingS9N1-v0", max_steps=250)
    generator = torch.Generator().manual_seed(seed)
    wins = 0
    for i in range(episodes):
        obs, _ = env.reset(seed=seed + i)
        done = False
        while not done:
            with torch.no_grad():
                logits, _ = model(torch.from_numpy(obs["image"][None]))
            action = int(torch.multinomial(torch.softmax(logits, -1), 1, generator=generator))
            obs, reward, terminated, truncated, _ = env.step(action)
            done = terminated or truncated
        wins += int(reward > 0)
    return wins / episodes


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("weights")
    parser.add_argument("--arch", default="fc")
    parser.add_argument("--episodes", type=int, default=500)
    parser.add_argument("--seed", type=int, default=7_000_000)
    args = parser.parse_args()
    torch.set_num_threads(1)
    farama = farama_success_rate(args.weights, args.arch, args.episodes, args.seed)
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "rlbackdoors.cli",
            "evaluate",
            "--weights",
            args.weights,
            "--arch",
            args.arch,
            "--env",
            "lavaworld",
            "--episodes",
            str(args.episodes),
            "--json",
        ],
        check=True,
        capture_output=True,
        text=True,
    ).stdout
    ours = json.loads(out)["clean_sr"]
    n = args.episodes
    pooled = (farama + ours) / 2
    z = (farama - ours) / math.sqrt(max(pooled * (1 - pooled) * 2 / n, 1e-12))
    print(json.dumps({"episodes": n, "farama_minigrid_sr": farama, "rlbackdoors_sr": ours, "z": round(z, 2)}, indent=2))
    return 0 if abs(z) < 3 else 1


if __name__ == "__main__":
    sys.exit(main())
