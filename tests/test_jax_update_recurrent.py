"""``ppo.update_backend = "jax"`` for the recurrent models (Colorful Memory's CNN-GRUs,
rlbackdoors.algos.compiled._update_recurrent): truncated BPTT as one XLA program on the torch
trainer's rollouts.

What must hold, on real Colorful Memory rollouts (the world's PPO: 10 copies x 120 steps,
recurrence 6, the auxiliary memory loss): one minibatch's loss parts, gradient norm and Adam
step are torch's up to float rounding; a whole update (4 epochs, the odd ones with torch-ac's
shifted starts and a ragged last minibatch of 90 sequences, the memories written back between
minibatches) ends where torch's does, up to the rounding that 8 Adam steps carry; Adam's state
stays torch's; and a run is reproducible to the byte and records its backend."""

from __future__ import annotations

import hashlib
import json

import pytest
import torch

from rlbackdoors.algos import group  # noqa: E402
from rlbackdoors.algos.ppo import PPO  # noqa: E402
from rlbackdoors.config import RunConfig  # noqa: E402
from rlbackdoors.models import build_model  # noqa: E402
from rlbackdoors.poison.mix import make_env_mix  # noqa: E402
from rlbackdoors.train import train  # noqa: E402
from rlbackdoors.validate import ConfigError  # noqa: E402

ARCH = "cnn-gru-small-onehot"


def learner(seed: int, backend: str, **ppo):
    cfg = RunConfig.from_dict({"env": {"name": "colorful-memory"}, "model": {"arch": ARCH}, "train": {"seed": seed}, "ppo": {"update_backend": backend, **ppo}})
    torch.manual_seed(seed)
    ppo_ = PPO(build_model(ARCH, "colorful-memory"), cfg.ppo, torch.device("cpu"), torch.Generator().manual_seed(seed))
    envs = make_env_mix(cfg.env, cfg.poison, seed)
    return ppo_, envs, envs.reset(seed=seed * 1000)[0]


def collected(backend: str, seeds, **ppo):
    made = [learner(s, backend, **ppo) for s in seeds]
    ppos = [m[0] for m in made]
    return ppos, [r for r, _ in group.collect(ppos, [m[1] for m in made], [m[2] for m in made])]


def weight_diff(a: PPO, b: PPO) -> torch.Tensor:
    return torch.cat([(p - q).abs().reshape(-1) for p, q in zip(a.params, b.params)])  # the model's and the auxiliary head's


@pytest.mark.parametrize(("ppo", "rel", "moved"), [({"epochs": 1, "batch_size": 1200}, 1e-5, 1e-5), ({}, 1e-4, 2.1e-3)], ids=["one-minibatch", "whole-update"])
def test_the_update_is_torchs(ppo, rel, moved):
    """Two agents (a group's chunk), their loss parts and gradient norms to ``rel`` relative, their
    weights (model and auxiliary head) within 1e-5 but for at most 0.1 % of them, none by more
    than ``moved``: an Adam step is lr * m / (sqrt(v) + eps), so where a gradient is about eps its
    rounding can decide a step's sign (1e-3 a step); one step: none differs by 1e-5 on the AMD EPYC
    this was written on (2.5e-7 at most), eight steps: 1 weight in 100,000 (5.7e-5)."""
    torch_ppos, rollouts = collected("torch", [0, 1], **ppo)
    jax_ppos, same = collected("jax", [0, 1], **ppo)
    assert all(torch.equal(a.obs, b.obs) and torch.equal(a.memories, b.memories) for a, b in zip(rollouts, same))
    expected = [p.update(r) for p, r in zip(torch_ppos, rollouts)]
    got = group.update(jax_ppos, same)
    for e, g in zip(expected, got):
        assert set(g) == set(e) == {"policy_loss", "value_loss", "entropy", "grad_norm", "aux_memory_loss"}
        for key in e:
            assert g[key] == pytest.approx(e[key], rel=rel), key
    for a, b in zip(torch_ppos, jax_ppos):
        diff = weight_diff(a, b)
        assert (diff > 1e-5).float().mean().item() <= 1e-3 and diff.max().item() <= moved
        for p, q in zip(a.params, b.params):
            sa, sb = a.optimizer.state[p], b.optimizer.state[q]
            assert float(sa["step"]) == float(sb["step"]) == (1 if ppo else 8)
            for key in ("exp_avg", "exp_avg_sq"):
                assert torch.allclose(sb[key], sa[key], rtol=1e-3, atol=1e-3 * sa[key].abs().max().item()), key


def digest(folder) -> str:
    return hashlib.sha256((folder / "model.pt").read_bytes()).hexdigest()


@pytest.mark.slow  # (two tiny Colorful Memory runs: about 40 s on 2 cores)
def test_a_run_is_reproducible_and_records_its_backend(tmp_path):
    data = {
        "env": {"name": "colorful-memory"},
        "model": {"arch": ARCH},
        "ppo": {"update_backend": "jax"},
        "train": {"seed": 3, "max_frames": 4800, "eval_interval": 2400, "eval_episodes": 4, "final_eval_episodes": 4, "video": False},
    }
    for side in ("a", "b"):
        train(RunConfig.from_dict(data), tmp_path / side, progress=False)
    assert digest(tmp_path / "a") == digest(tmp_path / "b")
    assert json.loads((tmp_path / "a" / "config.json").read_text())["ppo"]["update_backend"] == "jax"


def test_what_it_does_not_run_is_refused_in_one_line():
    data = {"env": {"name": "colorful-memory"}, "model": {"arch": ARCH}, "ppo": {"update_backend": "jax"}, "train": {"device": "cuda"}}
    with pytest.raises(ConfigError, match="runs a CNN-GRU's update on the CPU") as err:
        RunConfig.from_dict(data)
    assert "\n" not in str(err.value)
