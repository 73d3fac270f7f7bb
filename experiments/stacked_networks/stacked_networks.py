"""How much can training K agents in one process save? Measure before building (issue 18).

    python experiments/stacked_networks/stacked_networks.py [--k 8 16] [--json experiments/stacked_networks/stacked_networks.json]

For the LavaWorld FC and CNN, on one torch thread, it times the two pieces of PPO that a group
trainer would batch, each for one agent and for K agents with stacked weights:

* the rollout's forward pass on the 10 env copies (one per env step): one model K times, against
  one stacked forward of K x 10 rows, written with batched matmuls (``baddbmm``) and grouped
  convolutions, and against ``torch.func.vmap`` over ``functional_call``;
* the update's forward + backward on one minibatch of 256: one model K times, against the stacked
  network on K x 256 rows (``vmap`` too).

Then it measures the single-agent path's split between collection and update (``PPO.collect`` /
``PPO.update`` on the paper's setup) and combines the two into the ceiling of a group trainer's
frames/s gain over one process per model: ``1 / (collect_share / collect_gain + update_share /
update_gain)``, before evaluation, process start-up and writing folders (which a group can only
make cheaper per model, not cheaper per frame). The machine and its load are recorded.
"""

from __future__ import annotations

import argparse
import json
import os
import time

import torch
import torch.nn.functional as F
from torch.func import functional_call, vmap

from rlbackdoors.algos.ppo import PPO
from rlbackdoors.bench.machine import machine_info
from rlbackdoors.config import RunConfig
from rlbackdoors.models import build_model
from rlbackdoors.poison.mix import make_env_mix


def timed(fn, seconds: float = 1.0) -> float:
    """Median-free, simple: mean seconds per call over about ``seconds`` of calls."""
    for _ in range(3):
        fn()
    n, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        fn()
        n += 1
    return (time.perf_counter() - start) / n


def stacked_forward(model: torch.nn.Module, params: dict[str, torch.Tensor], obs: torch.Tensor):
    """The LavaWorld FC / CNN forward for K agents at once: obs (K, N, 7, 7, 3) -> logits (K, N, A), values (K, N).

    Linear layers as one ``baddbmm``; conv layers as one grouped ``conv2d`` (agents as groups);
    the same layer order and activations as the model's Sequentials."""
    k, n = obs.shape[:2]
    x = obs.float().reshape(k * n, 7, 7, 3).transpose(1, 3).transpose(2, 3)  # (K*N, C, 7, 7), as channels_first

    def run(prefix: str, seq: torch.nn.Sequential, x: torch.Tensor, conv: bool) -> torch.Tensor:
        for i, layer in enumerate(seq):
            if isinstance(layer, torch.nn.Linear):
                w, b = params[f"{prefix}.{i}.weight"], params[f"{prefix}.{i}.bias"]
                x = torch.baddbmm(b[:, None, :], x, w.transpose(1, 2))
            elif isinstance(layer, torch.nn.Conv2d):  # x: (N, K*C, H, W)
                w, b = params[f"{prefix}.{i}.weight"], params[f"{prefix}.{i}.bias"]
                x = F.conv2d(x, w.reshape(-1, *w.shape[2:]), b.reshape(-1), groups=k)
            elif isinstance(layer, torch.nn.MaxPool2d):
                x = F.max_pool2d(x, layer.kernel_size, layer.stride)
            elif isinstance(layer, torch.nn.ReLU):
                x = torch.relu(x)
            elif isinstance(layer, torch.nn.Tanh):
                x = torch.tanh(x)
            else:
                raise TypeError(f"no stacked form of {type(layer).__name__}")
        return x

    if any(isinstance(layer, torch.nn.Conv2d) for layer in model.state_emb):
        x = x.reshape(k, n, *x.shape[1:]).transpose(0, 1).reshape(n, -1, 7, 7)  # agents into channel groups
        x = run("state_emb", model.state_emb, x, True)
        x = x.reshape(n, k, -1).transpose(0, 1)  # (K, N, features)
    else:
        x = run("state_emb", model.state_emb, x.reshape(k, n, -1), False)
    return run("actor", model.actor, x, False), run("critic", model.critic, x, False)[..., 0]


def pieces(arch: str, k: int) -> dict:
    torch.manual_seed(0)
    models = [build_model(arch, "lavaworld") for _ in range(k)]
    one = models[0]
    names = [name for name, _ in one.named_parameters()]
    stacked = {name: torch.stack([dict(m.named_parameters())[name].detach() for m in models]) for name in names}
    logits, values = stacked_forward(one, stacked, torch.randint(0, 11, (k, 10, 7, 7, 3), dtype=torch.uint8))
    check_obs = torch.randint(0, 11, (10, 7, 7, 3), dtype=torch.uint8)
    ref_logits, _ = models[1](check_obs)
    got, _ = stacked_forward(one, stacked, check_obs[None].expand(k, -1, -1, -1, -1).contiguous())
    assert torch.allclose(got[1], ref_logits, atol=1e-4), "stacked forward disagrees with the model"
    meta = build_model(arch, "lavaworld").to("meta")
    vmapped = vmap(lambda p, o: functional_call(meta, p, (o,)))
    out = {}
    obs10 = torch.randint(0, 11, (k, 10, 7, 7, 3), dtype=torch.uint8)
    with torch.inference_mode():
        out["rollout_forward_loop_s"] = timed(lambda: [m(obs10[i]) for i, m in enumerate(models)])
        out["rollout_forward_stacked_s"] = timed(lambda: stacked_forward(one, stacked, obs10))
        out["rollout_forward_vmap_s"] = timed(lambda: vmapped(stacked, obs10))
    obs256 = torch.randint(0, 11, (k, 256, 7, 7, 3), dtype=torch.uint8)

    def loop():
        for i, m in enumerate(models):
            logits, values = m(obs256[i])
            (logits.square().mean() + values.square().mean()).backward()

    grad_params = {name: p.clone().requires_grad_() for name, p in stacked.items()}

    def group():
        logits, values = stacked_forward(one, grad_params, obs256)
        (logits.square().mean() + values.square().mean()).backward()

    def group_vmap():
        logits, values = vmapped(grad_params, obs256)
        (logits.square().mean() + values.square().mean()).backward()

    out["update_minibatch_loop_s"] = timed(loop)
    out["update_minibatch_stacked_s"] = timed(group)
    out["update_minibatch_vmap_s"] = timed(group_vmap)
    out["rollout_forward_gain"] = out["rollout_forward_loop_s"] / out["rollout_forward_stacked_s"]
    out["update_minibatch_gain"] = out["update_minibatch_loop_s"] / out["update_minibatch_stacked_s"]
    del logits, values
    return out


def single_split(arch: str, rollouts: int = 6) -> dict:
    """The single-agent path's seconds per rollout in PPO.collect and PPO.update (paper setup)."""
    cfg = RunConfig.from_dict({"model": {"arch": arch}})
    torch.manual_seed(0)
    model = build_model(arch, "lavaworld")
    ppo = PPO(model, cfg.ppo, torch.device("cpu"), torch.Generator().manual_seed(0))
    envs = make_env_mix(cfg.env, cfg.poison)
    obs, _ = envs.reset(seed=0)
    rollout, obs = ppo.collect(envs, obs)
    ppo.update(rollout)
    collect = update = 0.0
    for _ in range(rollouts):
        start = time.perf_counter()
        rollout, obs = ppo.collect(envs, obs)
        mid = time.perf_counter()
        ppo.update(rollout)
        collect, update = collect + mid - start, update + time.perf_counter() - mid
    total = collect + update
    return {"frames_per_s": rollouts * rollout.num_frames / total, "collect_share": collect / total, "update_share": update / total}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--k", type=int, nargs="+", default=[8, 16])
    parser.add_argument("--json", default=None)
    args = parser.parse_args()
    torch.set_num_threads(1)
    result: dict = {"machine": machine_info(), "loadavg_before": os.getloadavg(), "archs": {}}
    for arch in ("fc", "cnn"):
        split = single_split(arch)
        entry: dict = {"single": split, "groups": {}}
        for k in args.k:
            p = pieces(arch, k)
            ceiling = 1.0 / (split["collect_share"] / p["rollout_forward_gain"] + split["update_share"] / p["update_minibatch_gain"])
            entry["groups"][str(k)] = {**{key: round(v, 6) for key, v in p.items()}, "frames_per_s_gain_ceiling": round(ceiling, 2)}
            print(
                f"{arch} K={k}: rollout forward x{p['rollout_forward_gain']:.2f} (vmap: x{p['rollout_forward_loop_s'] / p['rollout_forward_vmap_s']:.2f}), "
                f"update minibatch x{p['update_minibatch_gain']:.2f} (vmap: x{p['update_minibatch_loop_s'] / p['update_minibatch_vmap_s']:.2f}); "
                f"single path {split['frames_per_s']:,.0f} frames/s, {100 * split['collect_share']:.0f}% collecting -> group ceiling x{ceiling:.2f}"
            )
        result["archs"][arch] = entry
    result["loadavg_after"] = os.getloadavg()
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(result, fh, indent=2)
            fh.write("\n")


if __name__ == "__main__":
    main()
