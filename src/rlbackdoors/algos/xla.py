"""The JAX side both XLA backends share: JAX started on one thread with its compilation cache,
and a torch network read as static data and run as JAX functions.

Why one module: the compiled trainer (:mod:`rlbackdoors.algos.compiled`, ``ppo.update_backend =
"compiled"``, and its update alone under the torch trainer's rollouts, ``"jax"``) and the compiled
evaluations (:mod:`rlbackdoors.evaluate.compiled`) start JAX the same way and read the same
networks; nothing here knows a trainer, so the trainers import it and never each other.

JAX computes on one thread where this module starts it (:func:`start`): a zoo trains a process
per core, and one process's pool must not wait on the other's core. On CUDA, JAX starts with
deterministic GPU kernels and without taking the GPU's memory up front.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Any

import numpy as np
from torch import nn

ONE_THREAD = "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"
DETERMINISTIC_GPU = "--xla_gpu_deterministic_ops=true"  # gathers' backward without atomics: the same bytes each run
STATS = ("policy_loss", "value_loss", "entropy", "grad_norm")  # an update's statistics, in the programs' order


CACHE_ENV = "RLBACKDOORS_JAX_CACHE"  # a folder for the compiled programs, or "off"


def compile_cache_dir() -> Path | None:
    """Where this process keeps JAX's compiled programs between processes (None: nowhere).

    Why: every zoo job, benchmark and test process compiles its programs anew, about 10 s for a
    small grid world's FC iteration (measured: 9.7 s, 1.3 s from the cache, the same weights' bytes), and a
    job of a zoo with several attacks compiles one a program. JAX's cache is trusted code (its docs:
    whoever can write it can run code here), so it lives in a folder of this user's alone
    (``~/.cache/rlbackdoors``, or ``$RLBACKDOORS_JAX_CACHE``), made 0700 and refused (with a
    warning, then compiled as without) where another user owns it or may write it; and it is kept
    per machine (CPU model and flags), so a home shared between machines never hands one
    machine's executable to another's run, whose bytes are keyed by machine."""
    import getpass
    import hashlib
    import platform
    import stat
    import warnings

    chosen = os.environ.get(CACHE_ENV, "")
    if chosen.lower() in ("off", "0", "false", "none"):
        return None
    base = Path(chosen).expanduser() if chosen else Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "rlbackdoors"
    try:
        cpu = Path("/proc/cpuinfo").read_text(errors="replace")
    except OSError:
        cpu = ""
    facts = sorted(
        {line.split(":", 1)[1].strip() for line in cpu.splitlines() if line.split(":", 1)[0].strip() in ("model name", "flags", "cpu family", "model")}
    )
    machine = hashlib.sha256("\n".join([platform.machine(), platform.processor(), *facts]).encode()).hexdigest()[:12]
    path = base / f"jax-{machine}"
    try:
        path.mkdir(parents=True, exist_ok=True, mode=0o700)
        info = path.stat()
    except OSError as err:
        warnings.warn(f"rlbackdoors: no JAX compilation cache ({err}); programs compile in every process", stacklevel=2)
        return None
    if info.st_uid != os.getuid() or info.st_mode & (stat.S_IWGRP | stat.S_IWOTH) or not stat.S_ISDIR(info.st_mode):
        warnings.warn(
            f"rlbackdoors: no JAX compilation cache: {str(path)!r} is not {getpass.getuser()}'s alone (a cache is trusted code); "
            f"programs compile in every process (set {CACHE_ENV} to a private folder, or to off)",
            stacklevel=2,
        )
        return None
    return path


def _use_cache(jax) -> None:
    """JAX's compilation cache in :func:`compile_cache_dir`, unless one is set already (by the user, or before)."""
    if jax.config.jax_compilation_cache_dir is None:
        cache = compile_cache_dir()
        if cache is not None:
            jax.config.update("jax_compilation_cache_dir", str(cache))


def start(gpu: bool = False):
    """The ``jax`` module, started with one compute thread; ``ValueError`` (one line) where it is
    missing, or (``gpu``) where it was started in this process without deterministic GPU kernels.
    With ``gpu`` it starts with them and without taking the GPU's memory up front (torch's
    allocator shares the device).

    JAX sizes its CPU thread pool by the starting thread's CPU affinity, and XLA_FLAGS alone do not
    stop it (measured: 1.35 CPU-s per second of a minibatch loop, the spare core's share spent
    waiting). So the backend starts with the calling thread allowed one core, and then the threads
    it made, and the caller, get their affinity back: one compute thread, free to move (1.05)."""
    if "jax" in sys.modules:
        if gpu and DETERMINISTIC_GPU not in os.environ.get("XLA_FLAGS", ""):
            raise ValueError(
                "JAX on CUDA (ppo.update_backend 'jax' or 'compiled') needs JAX started by rlbackdoors (deterministic GPU kernels); "
                "this process imported jax before: train in a fresh process"
            )
        import jax

        _use_cache(jax)
        return jax
    if "intra_op_parallelism_threads" not in os.environ.get("XLA_FLAGS", ""):
        os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} {ONE_THREAD}".strip()
    if gpu:
        os.environ["XLA_FLAGS"] = f"{os.environ['XLA_FLAGS']} {DETERMINISTIC_GPU}"
        os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
    pin = hasattr(os, "sched_setaffinity") and os.path.isdir("/proc/self/task")
    if pin:
        allowed = os.sched_getaffinity(0)
        before = set(os.listdir("/proc/self/task"))
        os.sched_setaffinity(0, {min(allowed)})
    try:
        import jax

        _use_cache(jax)
        jax.device_put(np.zeros(1, np.float32), jax.devices("cpu")[0]).block_until_ready()  # the CPU backend and its pool, started now
    except ImportError:
        raise ValueError(
            "ppo.update_backend='jax' and 'compiled' need JAX, a core dependency that is missing here: pip install 'jax>=0.10' (or reinstall rlbackdoors), or set ppo.update_backend='torch'"
        ) from None
    finally:
        if pin:
            for task in set(os.listdir("/proc/self/task")) - before:
                try:
                    os.sched_setaffinity(int(task), allowed)
                except OSError:  # a thread that has ended since
                    pass
            os.sched_setaffinity(0, allowed)
    return jax


def structure(model: Any, convolutions: bool = False) -> tuple:
    """The network as static data: per part (``state_emb``, ``actor``, ``critic``) its layers, each
    ``("linear", weight name, bias name)``, ``("relu",)`` or ``("tanh",)``, and with
    ``convolutions`` (the compiled trainer's) also ``("conv", weight name, bias name)`` (stride 1,
    no padding), ``("maxpool", k)`` (a k x k window at stride k) and ``("flatten",)`` (channels
    first, as torch's, of a channels-last input; rows stay rows); ``ValueError`` for a model
    this backend does not run (recurrent, convolutions, a Flatten of dict observations)."""
    why = "it is recurrent" if getattr(model, "recurrent", False) else None
    parts, more = _parts(model, convolutions)
    why = why or more
    if why is None and not hasattr(model, "stacked_input"):
        why = "it has no stacked input"
    if why is not None:
        raise ValueError(
            f"ppo.update_backend='jax' runs feed-forward networks of Linear, ReLU and Tanh layers on one observation array; not {type(model).__name__} ({why})"
        )
    return parts


def _parts(model: Any, convolutions: bool) -> tuple[tuple, str | None]:
    """:func:`structure`'s parts, and why the model's stacks are not all read (None: they are)."""
    why = None
    parts = []
    for part in ("state_emb", "actor", "critic"):
        seq = getattr(model, part, None)
        if not isinstance(seq, nn.Sequential):
            why = why or f"it has no {part} stack"
            break
        layers: list[tuple] = []
        for i, layer in enumerate(seq):
            if isinstance(layer, nn.Linear):
                layers.append(("linear", f"{part}.{i}.weight", f"{part}.{i}.bias"))
            elif isinstance(layer, (nn.ReLU, nn.Tanh)):
                layers.append((type(layer).__name__.lower(),))
            elif convolutions and isinstance(layer, nn.Conv2d) and _plain_conv(layer):
                layers.append(("conv", f"{part}.{i}.weight", f"{part}.{i}.bias"))
            elif convolutions and isinstance(layer, nn.MaxPool2d) and _plain_pool(layer):
                layers.append(("maxpool", _pair(layer.kernel_size)[0]))
            elif convolutions and isinstance(layer, nn.Flatten) and (layer.start_dim, layer.end_dim) == (1, -1):
                layers.append(("flatten",))
            else:
                why = why or f"its {part} has a {type(layer).__name__}"
        parts.append(tuple(layers))
    return tuple(parts), why


def recurrent_structure(model: Any) -> tuple:
    """A CNN-GRU actor-critic (the ``cnn-gru-*`` architectures' ``CNNGRUModel``) as static
    data: its parts as :func:`structure` reads them (the embedding's convolutions, the heads), its
    GRU stack ``(blocks, layers, hidden)`` (each block an ``nn.GRU``, torch's gate order r, z, n)
    and whether it reads one-hot planes of the observation's bytes (``-onehot``); ``ValueError``
    (one line) for any other recurrent model."""
    why = None if getattr(model, "recurrent", False) else "it is not recurrent"
    parts, more = _parts(model, convolutions=True)
    why = why or more
    grus: Any = getattr(model, "gru", None)
    if why is None and not (isinstance(grus, nn.ModuleList) and len(grus) and all(isinstance(g, nn.GRU) for g in grus)):
        why = "it has no stack of nn.GRU blocks"
    if why is None:
        first = grus[0]
        plain = all(g.bias and not g.batch_first and not g.bidirectional and g.dropout == 0 and g.proj_size == 0 for g in grus)
        same = all((g.num_layers, g.hidden_size) == (first.num_layers, first.hidden_size) for g in grus)
        if not (plain and same and getattr(model, "memory_size", None) == len(grus) * first.num_layers * first.hidden_size):
            why = "its GRU blocks are not plain ones of one size, their states the memory"
    if why is not None:
        raise ValueError(f"the compiled trainer runs CNN-GRU actor-critics (cnn-gru-*); not {type(model).__name__} ({why})")
    onehot = tuple(model.onehot_planes) if getattr(model, "onehot", False) else None  # each byte's plane count
    return parts, (len(grus), grus[0].num_layers, grus[0].hidden_size), onehot


def recurrent_forward(net: tuple, p: dict, obs, memory):
    """:func:`recurrent_structure`'s network on raw views ``obs`` (B, 7, 7, 3) uint8 and memories
    (B, M): logits (B, A), values (B,) and the memories after the step, as the torch model's
    ``forward`` computes them."""
    return recurrent_heads(net, p, *recurrent_step(net, p, recurrent_embed(net, obs, p), memory))


def recurrent_embed(net: tuple, obs, p: dict):
    """The embedding (B, 64) of raw views: their bytes as the CNN reads them (one-hot planes, or the
    codes as floats), channels last, through the convolutions, flattened channels first as torch's."""
    jax = start()
    jnp = jax.numpy
    (emb, _, _), _, onehot = net
    if onehot is None:
        x = obs.astype(jnp.float32)
    else:
        x = jnp.concatenate([(obs[..., i, None] == jnp.arange(n, dtype=obs.dtype)) for i, n in enumerate(onehot)], -1).astype(jnp.float32)
    e = run_layers(emb, p, x)
    return jnp.transpose(e, (0, 3, 1, 2)).reshape(e.shape[0], -1) if e.ndim == 4 else e


def recurrent_step(net: tuple, p: dict, x, memory):
    """One time step of the GRU blocks (nn.GRU's equations, torch's weight names and gate order):
    x (B, in), memory (B, blocks layers H) in the model's layout (block, then layer) -> the last
    layer's output (B, H) and the new memory."""
    jax = start()
    jnp = jax.numpy
    _, (blocks, layers, hidden), _ = net
    states = memory.reshape(memory.shape[0], blocks, layers, hidden)
    new = []
    for b in range(blocks):
        for i in range(layers):
            h = states[:, b, i]
            key = f"gru.{b}."
            gi = jnp.matmul(x, p[f"{key}weight_ih_l{i}"].T, precision="highest") + p[f"{key}bias_ih_l{i}"]
            gh = jnp.matmul(h, p[f"{key}weight_hh_l{i}"].T, precision="highest") + p[f"{key}bias_hh_l{i}"]
            i_r, i_z, i_n = jnp.split(gi, 3, -1)
            h_r, h_z, h_n = jnp.split(gh, 3, -1)
            r, z = jax.nn.sigmoid(i_r + h_r), jax.nn.sigmoid(i_z + h_z)
            x = (1 - z) * jnp.tanh(i_n + r * h_n) + z * h
            new.append(x)
    return x, jnp.stack(new, 1).reshape(memory.shape)


def recurrent_heads(net: tuple, p: dict, x, memory):
    """The actor's logits and the critic's values of the GRU outputs ``x``, with the memory passed on."""
    (_, actor, critic), _, _ = net
    return run_layers(actor, p, x), run_layers(critic, p, x)[:, 0], memory


def _pair(v) -> tuple:
    return tuple(v) if isinstance(v, (tuple, list)) else (v, v)


def _plain_conv(layer: nn.Conv2d) -> bool:
    """A convolution :func:`run_layers` computes as torch does: stride 1, no padding or dilation, one group, a bias."""
    return _pair(layer.stride) == (1, 1) and _pair(layer.padding) == (0, 0) and _pair(layer.dilation) == (1, 1) and layer.groups == 1 and layer.bias is not None


def _plain_pool(layer: nn.MaxPool2d) -> bool:
    """A square max-pool window at its own stride, no padding, dilation or ceil mode."""
    k, stride = _pair(layer.kernel_size), _pair(layer.stride if layer.stride is not None else layer.kernel_size)
    return k[0] == k[1] and stride == k and _pair(layer.padding) == (0, 0) and _pair(layer.dilation) == (1, 1) and not layer.ceil_mode


def gpu_devices(jax) -> list:
    try:
        return jax.devices("gpu")
    except RuntimeError:  # no GPU backend in this jaxlib
        return []


def run_layers(part: tuple, p: dict, x):
    """One part of a :func:`structure` (its layers in turn) on ``x``, with the weights ``p`` by
    name: full fp32 products as torch's (TF32 off, train.driver): XLA's default on a GPU rounds
    their inputs to TF32, 1e-3 from torch's losses on an H200 (benchmarks/results/gpu/h200_2026-11-29,
    call2_gpu_tests.log); on a CPU the products are fp32 either way (the same bytes)."""
    jax = start()
    jnp = jax.numpy
    for layer in part:
        if layer[0] == "linear":
            x = jnp.matmul(x, p[layer[1]].T, precision=jax.lax.Precision.HIGHEST) + p[layer[2]]
        elif layer[0] == "conv":
            x = _conv(jnp, x, p[layer[1]]) + p[layer[2]]
        elif layer[0] == "maxpool":  # k x k windows at stride k, a remainder dropped (VALID)
            k = layer[1]
            b, h, w, c = x.shape
            x = x[:, : h - h % k, : w - w % k].reshape(b, h // k, k, w // k, k, c).max((2, 4))
        elif layer[0] == "flatten":  # torch's order: channels first
            x = x if x.ndim == 2 else jnp.transpose(x, (0, 3, 1, 2)).reshape(x.shape[0], -1)
        elif layer[0] == "relu":
            x = jax.nn.relu(x)
        else:
            x = jnp.tanh(x)
    return x


def _conv(jnp, x, weight):
    """A stride-1 VALID convolution of channels-last ``x`` (B, H, W, C) by torch's ``weight``
    (O, C, kH, kW), as one matrix product of the windows (im2col): under ``vmap`` over agents it
    is a batched product, where XLA's CPU runs a batched convolution as a grouped one, measured
    x0.2 of the torch group on a grid world's CNN."""
    o, c, kh, kw = weight.shape
    b, h, w, _ = x.shape
    hh, ww = h - kh + 1, w - kw + 1
    windows = jnp.concatenate([x[:, i : i + hh, j : j + ww, :] for i in range(kh) for j in range(kw)], axis=-1)  # (B, H', W', kH kW C)
    matrix = jnp.transpose(weight, (2, 3, 1, 0)).reshape(kh * kw * c, o)  # rows in the windows' (i, j, channel) order
    out = jnp.matmul(windows.reshape(b * hh * ww, kh * kw * c), matrix, precision="highest")
    return out.reshape(b, hh, ww, o)
