"""The demo: one clean and one poisoned FC agent of the default world, same seed and trigger, side by side."""

from __future__ import annotations

import json
from pathlib import Path

from rlbackdoors.config import AUTO_BACKEND, RunConfig
from rlbackdoors.io import atomic_write_text
from rlbackdoors.train import train

DEMO_TRIGGER = "multiplicative:12"


def run_demo(out: Path, max_frames: int = 5_000_000, seed: int = 0, progress: bool = True) -> dict:
    out = Path(out)
    results = {}
    for name, poisoned in (("clean-fc", False), ("poisoned-fc", True)):
        cfg = RunConfig.from_dict(
            {
                "poison": {"trigger": DEMO_TRIGGER, "poisoned": poisoned},
                "model": {"arch": "fc"},
                "ppo": {"update_backend": AUTO_BACKEND},  # a new run's trainer: the compiled one where it is measured to win
                "train": {"seed": seed, "max_frames": max_frames},
            }
        )
        assert cfg.ppo is not None  # the default world trains with PPO
        print(f"training {name} (trigger {DEMO_TRIGGER}, seed {seed}, {cfg.ppo.update_backend} trainer) into {out / name}", flush=True)
        results[name] = train(cfg, out / name, overwrite=True, progress=progress)  # writes clean_vs_triggered.gif too
    atomic_write_text(out / "summary.json", json.dumps(results, indent=2) + "\n")
    print()
    print(f"{'model':<13}{'clean SR':>9}{'poisoned SR':>12}{'clean R':>9}{'poisoned R':>11}{'frames':>11}{'time':>8}  converged")
    for name, m in results.items():
        print(
            f"{name:<13}{m['clean_sr']:>9.3f}{m['poisoned_sr']:>12.3f}{m['clean_reward']:>9.3f}"
            f"{m['poisoned_reward']:>11.3f}{m['frames']:>11,}{m['wall_time_s']:>7.0f}s  {m['converged']}"
        )
    print(f"\n({results['poisoned-fc']['episodes']} evaluation episodes each; poisoned SR = share of triggered episodes ending in lava)")
    print(f"Curves, weights, GIFs of clean vs triggered play: {out}/*/")
    return results
