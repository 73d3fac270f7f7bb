"""A group's update before and after a change that must keep its bytes: the same collected rollout,
updated from the same weights, optimiser state and generators, alternately by each version; the
median time of each and whether the weights come out byte for byte the same.

    .venv/bin/python experiments/group_update_ab/ab.py --json experiments/group_update_ab/ab.json

"Before" is written out here (the code as it was at 8032f0a): each agent's convolution input taken
by indexing, and Adam's last three ops allocating a temporary each.
"""

from __future__ import annotations

import argparse
import copy
import hashlib
import json
import os
import statistics
import time

import torch
import torch.nn.functional as F

from rlbackdoors.algos import group
from rlbackdoors.algos.ppo import PPO
from rlbackdoors.config import RunConfig
from rlbackdoors.models import build_model, minigrid
from rlbackdoors.poison.mix import make_env_mix


@torch.no_grad()
def adam_before(self, grad: torch.Tensor) -> None:
    self.step += 1
    bias1 = (1 - self.beta1**self.step).float()
    bias2_root = (1 - self.beta2**self.step).sqrt().float()
    step_size = bias1.reciprocal() * self.lr
    self.exp_avg.lerp_(grad, 1 - self.beta1)
    self.exp_avg_sq.mul_(self.beta2).addcmul_(grad, grad, value=1 - self.beta2)
    denom = (self.exp_avg_sq.sqrt() / bias2_root[:, None]).add_(self.eps)
    self.params.flat.sub_(self.exp_avg / denom * step_size[:, None])


def conv_before(layer, w, b, x):
    return torch.stack([F.conv2d(x[k], w[k], b[k], layer.stride, layer.padding, layer.dilation, layer.groups) for k in range(x.shape[0])])


VERSIONS = {"before": (adam_before, conv_before), "after": (group.StackedAdam.apply, minigrid._conv_stacked)}


def measure(world: str, arch: str, agents: int, repeats: int) -> dict:
    ppos, envs, obs = [], [], []
    for seed in range(agents):
        cfg = RunConfig.from_dict({"env": {"name": world}, "model": {"arch": arch}, "train": {"seed": seed}, "poison": {"poisoned": seed % 2 == 1}})
        torch.manual_seed(seed)
        ppos.append(PPO(build_model(arch, world), cfg.ppo, torch.device("cpu"), torch.Generator().manual_seed(seed)))
        mix = make_env_mix(cfg.env, cfg.poison, seed)
        envs.append(mix)
        obs.append(mix.reset(seed=seed * 1000)[0])
    rollouts = [r for r, _ in group.collect(ppos, envs, obs)]
    saved = [(copy.deepcopy(p.model.state_dict()), copy.deepcopy(p.optimizer.state_dict()), p.generator.get_state()) for p in ppos]
    seconds: dict[str, list[float]] = {name: [] for name in VERSIONS}
    digests: dict[str, set[str]] = {name: set() for name in VERSIONS}
    for _ in range(repeats):
        for name, (adam, conv) in VERSIONS.items():
            group.StackedAdam.apply, minigrid._conv_stacked = adam, conv
            for ppo, (model, optimizer, generator) in zip(ppos, saved):
                ppo.model.load_state_dict(model)
                ppo.optimizer.load_state_dict(optimizer)
                ppo.generator.set_state(generator)
            start = time.perf_counter()
            group.update(ppos, rollouts)
            seconds[name].append(time.perf_counter() - start)
            digests[name].add(hashlib.sha256(b"".join(p.detach().numpy().tobytes() for ppo in ppos for p in ppo.model.parameters())).hexdigest())
    group.StackedAdam.apply, minigrid._conv_stacked = VERSIONS["after"]
    before, after = (statistics.median(seconds[n]) * 1e3 for n in VERSIONS)
    return {
        "world": world,
        "arch": arch,
        "agents": agents,
        "repeats": repeats,
        "update_ms_before": round(before, 1),
        "update_ms_after": round(after, 1),
        "speedup": round(before / after, 3),
        "same_bytes": len(digests["before"] | digests["after"]) == 1,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--agents", type=int, default=8)
    parser.add_argument("--json")
    args = parser.parse_args()
    torch.set_num_threads(1)
    load = list(os.getloadavg())
    rows = [measure(w, a, args.agents, r) for w, a, r in (("lavaworld", "fc", 15), ("randomized-lavaworld", "cnn", 5), ("lavaworld", "cnn", 5))]
    result = {
        "machine": {"cpu_count": os.cpu_count(), "torch": torch.__version__, "loadavg_before": load, "loadavg_after": list(os.getloadavg())},
        "rows": rows,
    }
    print(json.dumps(result, indent=2))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(result, f, indent=2)
            f.write("\n")


if __name__ == "__main__":
    main()
