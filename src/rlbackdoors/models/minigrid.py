"""Actor-critic models for the MiniGrid-based envs, with the TrojAI round's state-dict layout.

Both models take the raw uint8 7x7x3 observation (no scaling, as torch-ac and the
TrojAI round did), turn it channels-first with ``transpose(1, 3).transpose(2, 3)``,
embed it in ``state_emb``, and read ``actor`` logits and a ``critic`` value off the
embedding. Keeping the attribute names and layer indices of the TrojAI models means a
state dict trained there loads here unchanged (and vice versa).
"""

from __future__ import annotations

import functools
import os
from typing import TYPE_CHECKING

import torch
import torch.nn.functional as F
from torch import nn

VIEW = 7
CHANNELS = 3


def init_linear_unit_rows(module: nn.Module) -> None:
    """rl-starter-files init: Linear weights N(0, 1), each output row scaled to unit norm; bias 0."""
    if isinstance(module, nn.Linear):
        with torch.no_grad():
            module.weight.normal_(0.0, 1.0)
            module.weight.div_(module.weight.pow(2).sum(1, keepdim=True).sqrt())
            if module.bias is not None:
                module.bias.zero_()


def channels_first(obs: torch.Tensor) -> torch.Tensor:
    """(B, x, y, c) uint8 -> (B, c, x, y) float, exactly as the TrojAI/torch-ac models do it."""
    return obs.float().transpose(1, 3).transpose(2, 3)


_FUNCTIONAL = {
    nn.Linear: lambda m, x: F.linear(x, m.weight, m.bias),
    nn.ReLU: lambda m, x: torch.relu(x),
    nn.Tanh: lambda m, x: torch.tanh(x),
    nn.Conv2d: lambda m, x: F.conv2d(x, m.weight, m.bias, m.stride, m.padding, m.dilation, m.groups),
    nn.MaxPool2d: lambda m, x: F.max_pool2d(x, m.kernel_size, m.stride, m.padding, m.dilation, m.ceil_mode),
}


def run_sequential(seq: nn.Sequential, x: torch.Tensor) -> torch.Tensor:
    """``seq(x)`` with the same ops but without ``Module.__call__`` per layer.

    Why: the PPO rollout calls the model once per env step on ~10 rows, where the per-module
    hook machinery costs more than the arithmetic (measured ~8 us per layer on our CPUs).
    The layers stay modules so the state-dict keys stay TrojAI's.
    """
    for layer in seq:
        fn = _FUNCTIONAL.get(type(layer))
        x = fn(layer, x) if fn is not None else layer(x)
    return x


# How a group computes its agents' convolutions, by device type (default "each"): "each", one
# ``conv2d`` per agent; "gemm", all agents' as one batched matrix product over their unfolded
# patches (:func:`_conv_stacked_gemm`); "grouped", all agents' as one ``conv2d`` with a group of
# channels per agent (:func:`_conv_stacked_grouped`: one cuDNN call where "each" makes K). "each"
# everywhere until a GPU measures better: a convolution per agent and layer is a launch each (K x 3
# a forward for the grid CNNs), yet on an H200 the unfolded product was slower still, x0.32 a
# rollout step and x0.08 a minibatch's forward and backward (Randomized LavaWorld CNN, K = 64: 16.8
# against 5.4 ms, 265 against 22 ms; Colorful Memory's CNN-GRU, K = 32, alike;
# benchmarks/stacked_conv.py in benchmarks/results/gpu/h200_2026-11-29); "grouped" is not yet
# timed there (gpu_checks.sh times all three). The environment variable sets it for a process and
# the jobs it starts (bench zoo's CONV side field sets it): a comma-separated list of DEVICE:WAY.
# Unlike the engine's choice it changes an agent's bytes, so a group run records it in metrics.json
# (:func:`conv_record`, train.driver) and its checkpoint, and does not resume under another (train.ppo_run).
STACKED_CONV_ENV = "RLBACKDOORS_STACKED_CONV"
STACKED_CONV: dict[str, str] = {}
CONV_WAYS = ("each", "gemm", "grouped")


def conv_way(device_type: str) -> str:
    """How a group computes its convolutions on ``device_type`` (:data:`STACKED_CONV_ENV`, else
    :data:`STACKED_CONV`, else "each"). Raises ValueError naming the allowed values."""
    text = os.environ.get(STACKED_CONV_ENV)
    if not text:
        return STACKED_CONV.get(device_type, "each")
    return _parsed_ways(text).get(device_type, STACKED_CONV.get(device_type, "each"))


@functools.lru_cache(maxsize=8)
def _parsed_ways(text: str) -> dict[str, str]:
    """:data:`STACKED_CONV_ENV`'s value as device -> way, parsed once per value (it is read at
    every convolution of a group's forward)."""
    ways = {}
    for item in text.split(","):
        device, _, way = item.strip().partition(":")
        if device not in ("cpu", "cuda") or way not in CONV_WAYS:
            raise ValueError(
                f"{STACKED_CONV_ENV}={text!r} is not allowed (allowed: a comma-separated list of DEVICE:WAY, DEVICE cpu or cuda, WAY one of {', '.join(CONV_WAYS)})"
            )
        ways[device] = way
    return ways


def conv_record(model: nn.Module, device_type: str) -> str | None:
    """What a run records of its group's convolutions (with its device and group: what reproduces
    its bytes): the way (:func:`conv_way`) where ``model`` has convolutions and it is not the
    default "each"; else None, and older runs' records stay as they were."""
    if not any(isinstance(m, nn.Conv2d) for m in model.modules()):
        return None
    way = conv_way(device_type)
    return None if way == "each" else way


def _conv_stacked(layer: nn.Conv2d, w: torch.Tensor, b: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """K agents' convolutions, x (K, N, C, H, W), w (K, O, C, kh, kw), as :func:`conv_way` says
    for ``x``'s device.

    By default one ``conv2d`` per agent. On a CPU that beats one grouped convolution
    (experiments/stacked_networks/stacked_networks.json), and an agent's sums cannot depend on its
    group-mates. The agents' slices come from ``unbind``, whose backward is one stack: indexing
    ``x[k]`` backpropagates K zero-filled (K, ...) tensors summed (the same bytes; a CNN group's
    update x1.06-1.11, experiments/group_update_ab)."""
    way = conv_way(x.device.type)
    if way == "gemm" and layer.groups == 1 and not isinstance(layer.padding, str):
        return _conv_stacked_gemm(layer, w, b, x)
    if way == "grouped":
        return _conv_stacked_grouped(layer, w, b, x)
    return torch.stack(
        [F.conv2d(xk, wk, bk, layer.stride, layer.padding, layer.dilation, layer.groups) for xk, wk, bk in zip(x.unbind(0), w.unbind(0), b.unbind(0))]
    )


def _conv_stacked_grouped(layer: nn.Conv2d, w: torch.Tensor, b: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """:func:`_conv_stacked` as one ``conv2d`` for all K agents: their channels side by side
    (N, K * C, H, W) and each agent's kernel a group of its own (``groups = K * layer.groups``), so
    no agent reads another's channels. One call and one backward whatever K; the library picks
    its kernel by the shape, so, as with the batched products, an agent's sums are its own but
    rounded as its group's width says (fixed on CUDA: ``algos.group.group_width``)."""
    K, N = x.shape[:2]
    out_c = w.shape[1]
    y = F.conv2d(
        x.transpose(0, 1).reshape(N, K * x.shape[2], *x.shape[3:]),
        w.reshape(K * out_c, *w.shape[2:]),
        b.reshape(K * out_c),
        layer.stride,
        layer.padding,
        layer.dilation,
        K * layer.groups,
    )
    return y.reshape(N, K, out_c, *y.shape[2:]).transpose(0, 1)


def _conv_stacked_gemm(layer: nn.Conv2d, w: torch.Tensor, b: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """:func:`_conv_stacked` as a few operations for all K agents, whatever K: the inputs' patches
    unfolded (``F.unfold``, im2col), then one ``baddbmm`` of each agent's patches by its own
    kernel. Each agent's sums are its own (a batched product sums per batch), so, as with the
    linear layers, its numbers do not depend on its group-mates where K is fixed (a CUDA group
    computes at a fixed width, ``algos.group.group_width``); they are not ``conv2d``'s bytes."""
    K, N, C, H, W = x.shape
    out_c, _, kh, kw = w.shape[1:]
    padding = layer.padding
    assert not isinstance(padding, str)  # (_conv_stacked sends a string padding one conv2d per agent)
    (sh, sw), (ph, pw), (dh, dw) = layer.stride, padding, layer.dilation
    out_h, out_w = (H + 2 * ph - dh * (kh - 1) - 1) // sh + 1, (W + 2 * pw - dw * (kw - 1) - 1) // sw + 1
    patches = F.unfold(x.reshape(K * N, C, H, W), (kh, kw), dilation=layer.dilation, padding=padding, stride=layer.stride)
    patches = patches.reshape(K, N, C * kh * kw, out_h * out_w).transpose(2, 3).reshape(K, N * out_h * out_w, C * kh * kw)
    y = torch.baddbmm(b.unsqueeze(1), patches, w.reshape(K, out_c, C * kh * kw).transpose(1, 2))  # (K, N * L, O)
    return y.reshape(K, N, out_h, out_w, out_c).permute(0, 1, 4, 2, 3)


def linear_stacked(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
    """K agents' ``F.linear``: x (K, N, in), weight (K, out, in), bias (K, out) -> (K, N, out)."""
    return torch.baddbmm(bias.unsqueeze(1), x, weight.transpose(1, 2))


def run_sequential_stacked(seq: nn.Sequential, params: dict[str, torch.Tensor], prefix: str, x: torch.Tensor) -> torch.Tensor:
    """``seq`` for K agents at once: ``params[f"{prefix}.{i}.weight"]`` etc. are the K agents'
    weights stacked on a leading dimension, ``x`` is (K, N, ...) with N rows per agent.

    Why: a group of agents trained in one process (:mod:`rlbackdoors.algos.group`) runs one
    batched matmul per layer (``baddbmm``) instead of K small ones, which is what keeps an
    accelerator busy and removes K-1 dispatches per layer on a CPU.
    """
    K, N = x.shape[:2]
    for i, layer in enumerate(seq):
        key = f"{prefix}.{i}."
        if isinstance(layer, nn.Linear):
            x = linear_stacked(x, params[key + "weight"], params[key + "bias"])
        elif isinstance(layer, nn.ReLU):
            x = torch.relu(x)
        elif isinstance(layer, nn.Tanh):
            x = torch.tanh(x)
        elif isinstance(layer, nn.Flatten):
            x = x.reshape(K, N, -1)
        elif isinstance(layer, nn.Conv2d):
            x = _conv_stacked(layer, params[key + "weight"], params[key + "bias"], x)
        elif isinstance(layer, nn.MaxPool2d):
            y = F.max_pool2d(x.reshape(K * N, *x.shape[2:]), layer.kernel_size, layer.stride, layer.padding, layer.dilation, layer.ceil_mode)
            x = y.reshape(K, N, *y.shape[1:])
        else:
            raise TypeError(f"stacked forward: no batched form of {type(layer).__name__}")
    return x


class ActorCritic(nn.Module):
    """Shared skeleton: ``state_emb`` -> (``actor`` logits, ``critic`` value)."""

    recurrent = False
    appends_direction = False  # the heads read the agent's direction after the image embedding
    state_emb: nn.Sequential
    actor: nn.Sequential
    critic: nn.Sequential

    if TYPE_CHECKING:  # recurrent models only (``recurrent = True``); nothing is defined at run time

        def initial_memory(self, batch: int, device=...) -> torch.Tensor: ...

    def embed_input(self, obs: torch.Tensor) -> torch.Tensor:
        """The raw (B, 7, 7, 3) observation as ``state_emb`` takes it."""
        return channels_first(obs)

    def embed(self, obs: torch.Tensor) -> torch.Tensor:
        return run_sequential(self.state_emb, self.embed_input(obs)).reshape(obs.shape[0], -1)

    def forward(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        x = self.embed(obs)
        return run_sequential(self.actor, x), run_sequential(self.critic, x).squeeze(1)

    def forward_stacked(self, params: dict[str, torch.Tensor], obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``forward`` of K agents of this architecture at once: ``params`` their parameters stacked
        (name -> (K, ...)), ``obs`` (K, N, ...); returns logits (K, N, A) and values (K, N)."""
        return self.forward_stacked_input(params, self.stacked_input(obs))

    def stacked_input(self, obs: torch.Tensor) -> torch.Tensor:
        """K agents' raw observations (K, N, ...) as :meth:`forward_stacked_input` takes them (float,
        as ``state_emb`` reads them). Why apart: a group's update converts a whole rollout once,
        not each of its minibatches again in every epoch."""
        K, N = obs.shape[:2]
        x = self.embed_input(obs.reshape(K * N, *obs.shape[2:]))
        return x.reshape(K, N, *x.shape[1:])

    def forward_stacked_input(self, params: dict[str, torch.Tensor], x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """:meth:`forward_stacked` from :meth:`stacked_input`'s tensor."""
        K, N = x.shape[:2]
        return self.heads_stacked(params, run_sequential_stacked(self.state_emb, params, "state_emb", x).reshape(K, N, -1))

    def heads_stacked(self, params: dict[str, torch.Tensor], x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Actor logits (K, N, A) and critic values (K, N) of K agents' embeddings x (K, N, E)."""
        return run_sequential_stacked(self.actor, params, "actor", x), run_sequential_stacked(self.critic, params, "critic", x).squeeze(2)

    def forward_sequence(self, obs, memory: torch.Tensor, masks: torch.Tensor):
        """Recurrent models: ``forward(obs[i], memory * masks[i])`` for ``i < r`` steps, outputs
        concatenated (module doc of :mod:`rlbackdoors.models.colorful_memory`). This plain loop
        is the reference; recurrent models override it with a faster equivalent."""
        logits, values, memories = [], [], []
        for i in range(masks.shape[0]):
            step = {k: v[i] for k, v in obs.items()} if isinstance(obs, dict) else obs[i]
            out, value, memory = self(step, memory * masks[i][:, None])
            logits.append(out)
            values.append(value)
            memories.append(memory)
        return torch.cat(logits), torch.cat(values), torch.stack(memories)


class FCModel(ActorCritic):
    """LavaWorld FC: flatten 147 -> 100 -> 64 (ReLU); actor 64 -> 32 -> n; critic 64 -> 32 -> 1."""

    def __init__(self, num_actions: int = 3, embedding=(100, 64), head: int = 32):
        super().__init__()
        dims = [VIEW * VIEW * CHANNELS, *embedding]
        layers: list[nn.Module] = []
        for d_in, d_out in zip(dims[:-1], dims[1:]):
            layers += [nn.Linear(d_in, d_out), nn.ReLU()]
        self.state_emb = nn.Sequential(*layers)
        self.actor = nn.Sequential(nn.Linear(dims[-1], head), nn.ReLU(), nn.Linear(head, num_actions))
        self.critic = nn.Sequential(nn.Linear(dims[-1], head), nn.ReLU(), nn.Linear(head, 1))
        self.apply(init_linear_unit_rows)

    def embed_input(self, obs: torch.Tensor) -> torch.Tensor:
        # Same values as channels_first(obs).reshape(B, -1), but permuting uint8 bytes is cheaper.
        return obs.permute(0, 3, 1, 2).reshape(obs.shape[0], -1).float()

    def embed(self, obs: torch.Tensor) -> torch.Tensor:
        return run_sequential(self.state_emb, self.embed_input(obs))


class CNNModel(ActorCritic):
    """rl-starter-files CNN: conv 2x2 16, max-pool 2x2, conv 2x2 32, conv 2x2 64 -> 64; heads 64 -> 64 tanh -> out."""

    def __init__(self, num_actions: int = 3, channels=(16, 32, 64), head: int = 64):
        super().__init__()
        c1, c2, c3 = channels
        self.state_emb = nn.Sequential(
            nn.Conv2d(CHANNELS, c1, (2, 2)),
            nn.ReLU(),
            nn.MaxPool2d((2, 2)),
            nn.Conv2d(c1, c2, (2, 2)),
            nn.ReLU(),
            nn.Conv2d(c2, c3, (2, 2)),
            nn.ReLU(),
        )
        embedding = ((VIEW - 1) // 2 - 2) ** 2 * c3
        self.actor = nn.Sequential(nn.Linear(embedding, head), nn.Tanh(), nn.Linear(head, num_actions))
        self.critic = nn.Sequential(nn.Linear(embedding, head), nn.Tanh(), nn.Linear(head, 1))
        self.apply(init_linear_unit_rows)
