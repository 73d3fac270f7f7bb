"""A group's update before and after a change that must keep its bytes: the same collected rollout,
updated from the same weights, optimiser state and generators, alternately by each version; the
median time of each and whether the weights come out byte for byte the same.

    .venv/bin/python experiments/group_update_ab/ab.py --json experiments/group_update_ab/ab.json

"Before" is written out here (the code as it was at 8032f0a): each agent's convolution input taken
by indexing, Adam's last three ops allocating a temporary each; and for Colorful Memory's CNN-GRU,
each BPTT step's embeddings and each GRU state taken by indexing, and the one-hot planes made by
``one_hot`` (int64 planes scattered, then converted).
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
from rlbackdoors.models import colorful_memory as cm
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


def split_before(self, memory):
    states = memory.view(*memory.shape[:2], cm.GRU_BLOCKS, cm.GRU_LAYERS, self.hidden)
    return [[states[:, :, b, i] for i in range(cm.GRU_LAYERS)] for b in range(cm.GRU_BLOCKS)]


def sequence_before(self, params, obs, memory, masks):
    K, r, n = masks.shape
    x = self.embed_stacked(params, obs.reshape(K, r * n, *obs.shape[3:])).view(K, r, n, -1)
    states = self._split_stacked(memory)
    outputs, memories = [], []
    for i in range(r):
        keep = masks[:, i, :, None]
        out, states = self._recur_stacked(params, x[:, i], [[h * keep for h in block] for block in states])
        outputs.append(out)
        memories.append(self._join_stacked(states))
    return *self.heads_stacked(params, torch.stack(outputs, 1).reshape(K, r * n, -1)), torch.stack(memories, 1)


def one_hot_before(obs):
    codes = obs.long()
    planes = [F.one_hot(codes[..., i], n) for i, n in enumerate(cm.ONEHOT_PLANES)]
    return torch.cat(planes, -1).permute(0, 3, 1, 2).float()


# (owner, attribute, before): what each version sets
PATCHES = [
    (group.StackedAdam, "apply", adam_before),
    (minigrid, "_conv_stacked", conv_before),
    (cm.CNNGRUModel, "_split_stacked", split_before),
    (cm.CNNGRUModel, "forward_sequence_stacked", sequence_before),
    (cm, "one_hot_planes", one_hot_before),
]
VERSIONS = {"before": [before for _, _, before in PATCHES], "after": [getattr(owner, name) for owner, name, _ in PATCHES]}


def use(version: str) -> None:
    for (owner, name, _), value in zip(PATCHES, VERSIONS[version]):
        setattr(owner, name, value)


def nets(ppo: PPO) -> torch.nn.Module:
    """The learner's networks: the model, and the auxiliary memory head where it has one."""
    return torch.nn.ModuleList([ppo.model, *([ppo.aux] if ppo.aux is not None else [])])


def measure(world: str, arch: str | None, agents: int, repeats: int) -> dict:
    ppos, envs, obs = [], [], []
    for seed in range(agents):
        cfg = RunConfig.from_dict(
            {"env": {"name": world}, **({"model": {"arch": arch}} if arch else {}), "train": {"seed": seed}, "poison": {"poisoned": seed % 2 == 1}}
        )
        assert cfg.model.arch is not None and cfg.ppo is not None
        arch = cfg.model.arch
        torch.manual_seed(seed)
        ppos.append(PPO(build_model(arch, world), cfg.ppo, torch.device("cpu"), torch.Generator().manual_seed(seed)))
        mix = make_env_mix(cfg.env, cfg.poison, seed)
        envs.append(mix)
        obs.append(mix.reset(seed=seed * 1000)[0])
    rollouts = [r for r, _ in group.collect(ppos, envs, obs)]
    saved = [(copy.deepcopy(nets(p).state_dict()), copy.deepcopy(p.optimizer.state_dict()), p.generator.get_state()) for p in ppos]
    seconds: dict[str, list[float]] = {name: [] for name in VERSIONS}
    digests: dict[str, set[str]] = {name: set() for name in VERSIONS}
    for _ in range(repeats):
        for name in VERSIONS:
            use(name)
            for ppo, (model, optimizer, generator) in zip(ppos, saved):
                nets(ppo).load_state_dict(model)
                ppo.optimizer.load_state_dict(optimizer)
                ppo.generator.set_state(generator)
            start = time.perf_counter()
            group.update(ppos, rollouts)
            seconds[name].append(time.perf_counter() - start)
            digests[name].add(hashlib.sha256(b"".join(p.detach().numpy().tobytes() for ppo in ppos for p in nets(ppo).parameters())).hexdigest())
    use("after")
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
    worlds = (
        ("lavaworld", "fc", args.agents, 15),
        ("randomized-lavaworld", "cnn", args.agents, 5),
        ("lavaworld", "cnn", args.agents, 5),
        ("colorful-memory", None, 4, 5),
    )
    rows = [measure(w, a, k, r) for w, a, k, r in worlds]
    result = {
        "machine": {"cpu_count": os.cpu_count(), "torch": torch.__version__, "loadavg_before": load, "loadavg_after": list(os.getloadavg())},
        "rows": rows,
    }
    text = json.dumps(result, indent=2) + "\n"
    print(text, end="")
    if args.json:
        from rlbackdoors.io import atomic_write_text

        atomic_write_text(args.json, text)


if __name__ == "__main__":
    main()
