"""PPO's update for feed-forward agents as one XLA program (``ppo.update_backend = "jax"``).

Why: a CPU group's update is about two thirds of what a small grid world's FC model costs, and of that
only the matrix products are arithmetic; the rest is elementwise passes (ReLU's backward, the
loss, Adam) and a dispatch per op. XLA fuses the passes and runs a whole update, every epoch and
minibatch, as one program (``lax.scan``). An update of 8 FC agents (1,280 frames each, 4 epochs
of 5 minibatches) took 96.5 against 132.6 CPU-ms with torch (x0.73), one core of a 2-core AMD
EPYC (Zen 4) (experiments/jax_update/ab.py).

The same algorithm as :meth:`rlbackdoors.algos.ppo.PPO.update` and
:func:`rlbackdoors.algos.group.update`: each agent's epochs and minibatches in the orders its own
generator draws, torch-ac's loss, one clipping norm over the agent's whole gradient, and Adam with
the agent's own moments, step and learning rate, read from and written back to its
``torch.optim.Adam`` state (a checkpoint resumes under either backend). The rounding is XLA's, so
the bytes are not torch's; and XLA's kernels round differently at different batch widths, so a
group's agents are computed in chunks of exactly :data:`WIDTH` (padded with copies of the chunk's
first): an agent's bytes then depend on its config, not on its group-mates or the group's size
(tested). A lone run computes at width 1: its bytes are the lone path's, as with torch.

JAX computes on one thread where this module starts it (:func:`_jax`): a zoo trains a process
per core, and one process's pool must not wait on the other's core. On CUDA (``train.device``)
the update runs on the GPU: the tensors pass to JAX and back through DLPack without a copy, a
group computes in chunks of :data:`CUDA_WIDTH`, and JAX starts with deterministic GPU kernels
and without taking the GPU's memory up front. A CPU run's arrays are placed on the CPU's XLA
device, never on a GPU JAX would pick by default.
"""

from __future__ import annotations

import functools
import os
import sys
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from rlbackdoors.algos.group import FlatParameters, StackedAdam, parameters_by_name, stacked_parameters
from rlbackdoors.algos.obs import stack

WIDTH = 8  # agents per XLA call in a CPU group (see the module doc)
CUDA_WIDTH = 64  # ... in a CUDA group: the torch group's width there (algos.group.CUDA_WIDTH)
ONE_THREAD = "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"
DETERMINISTIC_GPU = "--xla_gpu_deterministic_ops=true"  # gathers' backward without atomics: the same bytes each run
STATS = ("policy_loss", "value_loss", "entropy", "grad_norm")


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


def _jax(gpu: bool = False):
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
                "ppo.update_backend='jax' on CUDA needs JAX started by rlbackdoors (deterministic GPU kernels); "
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
    why = None
    if getattr(model, "recurrent", False):
        why = "it is recurrent"
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
    if why is None and not hasattr(model, "stacked_input"):
        why = "it has no stacked input"
    if why is not None:
        raise ValueError(
            f"ppo.update_backend='jax' runs feed-forward networks of Linear, ReLU and Tanh layers on one observation array; not {type(model).__name__} ({why})"
        )
    return tuple(parts)


def _pair(v) -> tuple:
    return tuple(v) if isinstance(v, (tuple, list)) else (v, v)


def _plain_conv(layer: nn.Conv2d) -> bool:
    """A convolution :func:`run_layers` computes as torch does: stride 1, no padding or dilation, one group, a bias."""
    return _pair(layer.stride) == (1, 1) and _pair(layer.padding) == (0, 0) and _pair(layer.dilation) == (1, 1) and layer.groups == 1 and layer.bias is not None


def _plain_pool(layer: nn.MaxPool2d) -> bool:
    """A square max-pool window at its own stride, no padding, dilation or ceil mode."""
    k, stride = _pair(layer.kernel_size), _pair(layer.stride if layer.stride is not None else layer.kernel_size)
    return k[0] == k[1] and stride == k and _pair(layer.padding) == (0, 0) and _pair(layer.dilation) == (1, 1) and not layer.ceil_mode


def check(model: Any, device: torch.device) -> None:
    """Refuse (``ValueError``, one line) what this backend cannot update: a model other than
    :func:`structure` runs, a device other than the CPU or CUDA, a missing JAX or one without GPU support."""
    if device.type not in ("cpu", "cuda"):
        raise ValueError(f"ppo.update_backend='jax' runs on the CPU or CUDA, not {device.type!r}")
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError("ppo.update_backend='jax' on CUDA: no CUDA device is available (train.device 'cpu')")
    structure(model)
    jax = _jax(gpu=device.type == "cuda")
    if device.type == "cuda" and not _gpu_devices(jax):
        raise ValueError("ppo.update_backend='jax' with train.device='cuda' needs JAX with CUDA (jax[cuda]); this one has no GPU: use 'torch'")


def _gpu_devices(jax) -> list:
    try:
        return jax.devices("gpu")
    except RuntimeError:  # no GPU backend in this jaxlib
        return []


def _placed(jax, device: torch.device):
    """Torch tensor -> JAX array on the learners' device: the CPU's XLA device for CPU tensors
    (never a GPU JAX would pick by default on a GPU machine: a CPU run's bytes are the CPU's), and
    the same GPU memory, no copy, for CUDA tensors (DLPack, after torch's queued work is done)."""
    if device.type == "cpu":
        cpu = jax.devices("cpu")[0]
        return lambda t: jax.device_put(t.numpy(), cpu)
    torch.cuda.synchronize(device)
    return lambda t: jax.dlpack.from_dlpack(t.contiguous())


def _back(array, device: torch.device) -> torch.Tensor:
    """JAX array -> torch tensor on the learners' device (a CPU copy: XLA's buffer is read-only)."""
    if device.type == "cpu":
        return torch.from_numpy(np.array(array))
    array.block_until_ready()
    return torch.from_dlpack(array)


def run_layers(part: tuple, p: dict, x):
    """One part of a :func:`structure` (its layers in turn) on ``x``, with the weights ``p`` by
    name: full fp32 products as torch's (TF32 off, train.driver): XLA's default on a GPU rounds
    their inputs to TF32, 1e-3 from torch's losses on an H200 (benchmarks/results/gpu/h200_2026-11-29,
    call2_gpu_tests.log); on a CPU the products are fp32 either way (the same bytes)."""
    jax = _jax()
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


@functools.cache
def _program(layers: tuple, layout: tuple, hyper: tuple):
    """The jitted update for one network structure, parameter layout and loss hyper-parameters."""
    jax = _jax()
    jnp = jax.numpy
    # full fp32 products as torch's (TF32 off, train.driver): XLA's default on a GPU rounds their
    # inputs to TF32, 1e-3 from torch's losses on an H200 (benchmarks/results/gpu/h200_2026-11-29,
    # call2_gpu_tests.log); on a CPU the products are fp32 either way (the same bytes)
    clip, value_coef, entropy_coef, max_grad_norm, eps, beta1, beta2 = hyper
    run = run_layers

    def loss(row, x, actions, old_logp, old_values, adv, returns):
        """One agent's torch-ac PPO loss on its minibatch (rlbackdoors.algos.ppo.ppo_loss)."""
        p = {name: row[start:stop].reshape(shape) for name, start, stop, shape in layout}
        embedding = run(layers[0], p, x)
        logits, values = run(layers[1], p, embedding), run(layers[2], p, embedding)[:, 0]
        log_probs = jax.nn.log_softmax(logits)
        entropy = -(jnp.exp(log_probs) * log_probs).sum(-1).mean()
        ratio = jnp.exp(jnp.take_along_axis(log_probs, actions[:, None], 1)[:, 0] - old_logp)
        policy_loss = -jnp.minimum(ratio * adv, jnp.clip(ratio, 1 - clip, 1 + clip) * adv).mean()
        clipped = old_values + jnp.clip(values - old_values, -clip, clip)
        value_loss = jnp.maximum((values - returns) ** 2, (clipped - returns) ** 2).mean()
        return policy_loss - entropy_coef * entropy + value_coef * value_loss, (policy_loss, value_loss, entropy)

    def agent_step(row, avg, sq, step, lr, *batch):
        """One optimiser step of one agent: gradient, clipping by its norm, Adam (torch's rule)."""
        grad, parts = jax.grad(loss, has_aux=True)(row, *batch)
        norm = jnp.sqrt(jnp.sum(grad * grad))
        grad = grad * jnp.minimum(max_grad_norm / (norm + 1e-6), 1.0)
        step = step + 1
        avg = avg + (1 - beta1) * (grad - avg)
        sq = beta2 * sq + (1 - beta2) * grad * grad
        row = row - (lr / (1 - beta1**step)) * avg / (jnp.sqrt(sq) / jnp.sqrt(1 - beta2**step) + eps)
        return row, avg, sq, step, jnp.stack([*parts, norm])

    agents_step = jax.vmap(agent_step)

    def update(rows, avg, sq, step, lr, inputs, actions, old_logp, old_values, adv, returns, orders):
        """Every minibatch of the update in turn (``orders``: (minibatches, K, N) frame indices)."""

        def minibatch(carry, idx):
            def take(a):
                return jnp.take_along_axis(a, idx.reshape(idx.shape + (1,) * (a.ndim - 2)), 1)

            rows, avg, sq, step = carry
            rows, avg, sq, step, parts = agents_step(rows, avg, sq, step, lr, take(inputs), *(take(a) for a in (actions, old_logp, old_values, adv, returns)))
            return (rows, avg, sq, step), parts

        (rows, avg, sq, step), parts = jax.lax.scan(minibatch, (rows, avg, sq, step), orders)
        return rows, avg, sq, step, parts.mean(0)

    return jax.jit(update)


def update(ppos: list, rollouts: list, width: int | None = None) -> list[dict[str, float]]:
    """PPO's update for ``ppos`` (one architecture and PPO config, checked by the caller) on their
    rollouts, ``width`` agents per XLA call (a group: :data:`WIDTH` on the CPU, :data:`CUDA_WIDTH`
    on CUDA; a lone run: 1); one stats dict per agent, as :func:`rlbackdoors.algos.group.update`
    returns them."""
    lead = ppos[0]
    device = lead.device
    if width is None:
        width = CUDA_WIDTH if device.type == "cuda" else WIDTH
    jax = _jax(gpu=device.type == "cuda")
    cfg, model = lead.cfg, lead.model
    n = rollouts[0].num_frames
    if any(r.num_frames != n for r in rollouts):
        raise ValueError("a training group needs rollouts of the same length")
    if n % cfg.batch_size:
        raise ValueError(f"ppo.update_backend='jax' needs ppo.batch_size={cfg.batch_size} to divide a rollout's {n} frames (ppo.rollout x env copies)")
    layers = structure(model)
    hyper = (cfg.clip, cfg.value_coef, cfg.entropy_coef, cfg.max_grad_norm, lead.optimizer.param_groups[0]["eps"], *lead.optimizer.param_groups[0]["betas"])
    out: list[dict[str, float]] = []
    for start in range(0, len(ppos), width):
        chunk, chunk_rollouts = ppos[start : start + width], rollouts[start : start + width]
        real = len(chunk)
        chunk, chunk_rollouts = chunk + chunk[:1] * (width - real), chunk_rollouts + chunk_rollouts[:1] * (width - real)
        weights = FlatParameters(stacked_parameters(chunk))
        adam = StackedAdam([(ppo.optimizer, parameters_by_name(ppo)) for ppo in chunk], weights)
        layout = tuple((name, columns.start, columns.stop, tuple(shape[1:])) for name, (columns, shape) in weights.layout.items())
        with torch.no_grad():
            inputs = model.stacked_input(stack([r.obs for r in chunk_rollouts]))
        if not isinstance(inputs, torch.Tensor):
            raise ValueError(f"ppo.update_backend='jax' runs models on one observation array, not {type(model).__name__}'s")
        # each real agent's minibatch orders, every epoch's drawn in turn from its own generator
        # (as torch's update draws them); a pad copy takes its chunk's first agent's
        perms = [torch.stack([torch.randperm(n, generator=ppo.generator) for _ in range(cfg.epochs)]) for ppo in chunk[:real]]
        orders = torch.stack(perms + perms[:1] * (width - real), 1)  # (epochs, K, n)
        orders = orders.reshape(cfg.epochs, width, n // cfg.batch_size, cfg.batch_size).transpose(1, 2).reshape(-1, width, cfg.batch_size)
        columns = [torch.stack([getattr(r, f) for r in chunk_rollouts]) for f in ("actions", "logprobs", "values", "advantages", "returns")]
        program = _program(layers, layout, tuple(float(h) for h in hyper))
        put = _placed(jax, device)
        rows, avg, sq, step, parts = program(
            put(weights.flat),
            put(adam.exp_avg),
            put(adam.exp_avg_sq),
            put(adam.step.float()),
            put(adam.lr),
            put(inputs),
            *(put(c) for c in columns),
            put(orders.int().to(device)),
        )
        with torch.no_grad():
            weights.flat.copy_(_back(rows, device))
            adam.exp_avg.copy_(_back(avg, device))
            adam.exp_avg_sq.copy_(_back(sq, device))
            adam.step.copy_(_back(step, device).double())
        adam.write_back(real)
        means = np.asarray(parts, dtype=np.float64)  # (K, 4)
        out += [{key: float(means[k, i]) for i, key in enumerate(STATS)} for k in range(real)]
    return out
