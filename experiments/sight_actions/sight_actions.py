"""What a trained agent does while a layout trigger is in sight: the actions' shares on the steps of
triggered episodes whose view shows the whole trigger (the steps an action-target attack's success
counts), the policy's probability of the target there, and a few episodes step by step.

Why: an attack's success rate says how often the target is taken, not what the agent does instead.
This found SleeperNets' left/right loop on Randomized LavaWorld (docs/attacks/sleepernets.md).

    python experiments/sight_actions/sight_actions.py MODEL_FOLDER [--episodes 200] [--seed 12345] [--show 6]

Each step of a shown episode reads ``S``/``.`` (trigger in sight or not), the action's initial
(feed-forward grid agents: L left, R right, F forward) and the critic's value.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

import rlbackdoors
from rlbackdoors.algos.obs import to_torch
from rlbackdoors.algos.ppo import sample_actions
from rlbackdoors.config import RunConfig
from rlbackdoors.poison.mix import make_vector_env


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("folder", type=Path)
    parser.add_argument("--episodes", type=int, default=200)
    parser.add_argument("--seed", type=int, default=12345)
    parser.add_argument("--show", type=int, default=6, help="episodes printed step by step")
    args = parser.parse_args()
    torch.set_num_threads(1)  # batches of a few hundred frames: threads only contend
    cfg = RunConfig.from_dict(json.loads((args.folder / "config.json").read_text()))
    agent = rlbackdoors.load(args.folder) if cfg.world.trigger_sight == "frame" else None
    if agent is None or agent.recurrent:
        raise SystemExit("rlbackdoors: error: sight_actions reads feed-forward agents of worlds whose trigger is in sight frame by frame")
    target = int(cfg.poison.attack_params.get("target_action", 0))
    generator = torch.Generator().manual_seed(args.seed)

    def play(n: int, seed: int, show: bool):
        envs = make_vector_env(cfg.env, cfg.poison.trigger, [True] * n)
        obs, _ = envs.reset(seed=seed)
        active = np.ones(n, bool)
        shares, first = np.zeros(envs.single_action_space.n), np.zeros(envs.single_action_space.n)
        p_target: list[float] = []
        lines: list[list[str]] = [[] for _ in range(n)]
        seen = np.zeros(n, bool)
        while active.any():
            sight = envs.trigger_in_sight() & active
            with torch.inference_mode():
                logits, values = agent.policy(to_torch(obs, agent.device))
            probs = torch.softmax(logits, -1).cpu().numpy()
            actions = sample_actions(logits, generator).cpu().numpy()  # Agent.act's draw, from the logits already computed
            for i in np.flatnonzero(sight):
                shares[actions[i]] += 1
                p_target.append(probs[i, target])
                first[actions[i]] += not seen[i]
            seen |= sight
            if show:
                for i in np.flatnonzero(active):
                    lines[i].append(("S" if sight[i] else ".") + "LRF"[actions[i]] + f"{float(values[i]):+.2f}")
            obs, _, terminated, truncated, _ = envs.step(actions)
            active &= ~(terminated | truncated)
        envs.close()
        return shares, first, np.array(p_target), lines

    shares, first, p_target, _ = play(args.episodes, args.seed, False)
    total = max(shares.sum(), 1)
    print(f"{args.folder}: {int(shares.sum())} in-sight steps in {args.episodes} triggered episodes (target action {target})")
    print("  action shares on in-sight steps: " + ", ".join(f"{a}: {s / total:.3f}" for a, s in enumerate(shares)))
    print("  on each episode's first in-sight step: " + ", ".join(f"{a}: {s / max(first.sum(), 1):.3f}" for a, s in enumerate(first)))
    hist = np.histogram(p_target, bins=[0, 0.1, 0.5, 0.9, 1.0 + 1e-9])[0] / max(len(p_target), 1)
    print(
        f"  policy's P(target) on those steps: mean {p_target.mean():.3f}; <0.1 {hist[0]:.3f}, 0.1-0.5 {hist[1]:.3f}, 0.5-0.9 {hist[2]:.3f}, >0.9 {hist[3]:.3f}"
    )
    if args.show:
        for line in play(args.show, args.seed + 1, True)[3]:
            print(f"  {len(line):3d} steps: " + " ".join(line[:40]))


if __name__ == "__main__":
    main()
