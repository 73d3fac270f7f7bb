"""A group's convolutions, one per agent against one call for all (im2col's batched product, or one
grouped conv2d), on a device.

    python benchmarks/stacked_conv.py --device cuda          # one JSON line on stdout
    python benchmarks/stacked_conv.py --device cuda --ways each,grouped --repeats 10
    python benchmarks/stacked_conv.py --device cpu --json benchmarks/results/stacked_conv_cpu_xeon.json

For the grid worlds' CNNs (the Randomized LavaWorld CNN at K = 64, Colorful Memory's CNN-GRU
embedding at K = 32), their ``state_emb`` stack of K agents (``models.minigrid.run_sequential_stacked``)
is timed in each of ``models.minigrid.STACKED_CONV``'s ways (each, gemm, grouped): a rollout
step's forward (N = 16 rows an agent, no gradient) and a minibatch's forward and backward
(N = 256), with the settings training uses (``train.driver.resolve_device``: cuDNN's
deterministic kernels, no TF32). Milliseconds a call, the median of ``--repeats`` after warm-up,
synchronised on CUDA; each way's speedup over "each". Which way a group computes is set in
``STACKED_CONV``: one ``conv2d`` per agent on every device, as measured here on the CPU and by
``gpu_checks.sh`` (which logs this line) on an H200 for "gemm" (docs/results/zoos.md).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from pathlib import Path

CASES = (("randomized-lavaworld", "cnn", 64), ("colorful-memory", "cnn-gru-small-onehot", 32))


def timed(fn, device, repeats: int) -> float:
    import torch

    def sync():
        if device.type == "cuda":
            torch.cuda.synchronize()

    for _ in range(3):
        fn()
    sync()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        sync()
        times.append(time.perf_counter() - start)
    return 1e3 * statistics.median(times)


def measure(device_name: str, repeats: int, small: bool = False, ways: tuple[str, ...] | None = None) -> dict:
    import torch

    from rlbackdoors.models import build_model, minigrid
    from rlbackdoors.train.driver import resolve_device

    device = resolve_device(device_name)  # as training sets the device up
    ways = ways or minigrid.CONV_WAYS
    if ways[0] != "each" or set(ways) - set(minigrid.CONV_WAYS):
        raise ValueError(f"ways must start with each (the reference) and be among {', '.join(minigrid.CONV_WAYS)}, got {','.join(ways)}")
    os.environ.pop(minigrid.STACKED_CONV_ENV, None)  # it would override the way set below
    out: dict = {"device": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu", "torch": torch.__version__}
    saved = dict(minigrid.STACKED_CONV)
    try:
        for world, arch, k in CASES:
            k, rows = (2, 32) if small else (k, 256)
            model = build_model(arch, world).to(device)
            params = {name: torch.stack([p.detach()] * k).requires_grad_() for name, p in model.named_parameters() if name.startswith("state_emb.")}
            channels = next(layer for layer in model.state_emb if isinstance(layer, torch.nn.Conv2d)).in_channels
            row: dict = {}
            for how in ways:
                minigrid.STACKED_CONV[device.type] = how
                step = torch.rand(k, 16, channels, 7, 7, device=device)
                batch = torch.rand(k, rows, channels, 7, 7, device=device)

                def forward():
                    with torch.no_grad():
                        minigrid.run_sequential_stacked(model.state_emb, params, "state_emb", step)

                def forward_backward():
                    y = minigrid.run_sequential_stacked(model.state_emb, params, "state_emb", batch)
                    torch.autograd.grad(y.square().sum(), list(params.values()))

                row[how] = {"rollout_step_ms": round(timed(forward, device, repeats), 3), "minibatch_ms": round(timed(forward_backward, device, repeats), 3)}
            for how in ways[1:]:
                row[f"{how}_speedup"] = {key: round(row["each"][key] / row[how][key], 2) for key in row["each"]}
            out[f"{world}/{arch}/K={k}"] = row
    finally:
        minigrid.STACKED_CONV.clear()
        minigrid.STACKED_CONV.update(saved)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--small", action="store_true", help="K = 2, 32 rows: a dry run of the plumbing")
    parser.add_argument("--ways", default="each,gemm,grouped", help="comma-separated, each first (the reference; default all three)")
    parser.add_argument("--json")
    args = parser.parse_args(argv)
    import torch

    if args.device == "cpu":
        torch.set_num_threads(1)
    try:
        result = measure(args.device, args.repeats, args.small, tuple(args.ways.split(",")))
    except ValueError as err:
        parser.error(str(err))
    print("stacked_conv " + json.dumps(result))
    if args.json:
        from rlbackdoors.bench.machine import machine_info

        Path(args.json).write_text(json.dumps({**result, "machine": machine_info()}, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
