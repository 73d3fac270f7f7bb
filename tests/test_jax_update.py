"""``ppo.update_backend = "jax"`` (rlbackdoors.algos.compiled.update): PPO's update as one XLA program.

What must hold: the same loss and gradient as torch's update on the same minibatch (up to float
rounding), each agent's Adam state in torch's format (a run resumes under either backend), an
agent's bytes independent of its group-mates and the group's size (XLA's chunks of a fixed width),
a run reproducible to the byte, and what the backend does not run refused in one line. Whether
it trains agents as well as torch over many seeds is a measurement
(experiments/group_equivalence, ``--update-backend jax``), not a unit test.
"""

from __future__ import annotations

import copy
import hashlib
import json

import pytest
import torch


from rlbackdoors.algos import compiled, group  # noqa: E402
from rlbackdoors.algos.ppo import PPO  # noqa: E402
from rlbackdoors.config import RunConfig, migrate  # noqa: E402
from rlbackdoors.models import build_model  # noqa: E402
from rlbackdoors.poison.mix import make_env_mix  # noqa: E402
from rlbackdoors.train import train  # noqa: E402
from rlbackdoors.train.group import train_group  # noqa: E402
from rlbackdoors.validate import ConfigError  # noqa: E402
from cli_helpers import cli  # noqa: E402

# a rollout of 32 steps x 10 copies = 320 frames, minibatches of 64
TINY = {
    "ppo": {"rollout": 32, "batch_size": 64},
    "train": {"max_frames": 3200, "eval_interval": 1600, "eval_episodes": 4, "final_eval_episodes": 4, "video": False},
}


def tiny(seed: int, backend: str = "jax") -> RunConfig:
    data = copy.deepcopy(TINY)
    data["train"]["seed"] = seed
    data["env"] = {"name": "lavaworld"}
    data["ppo"]["update_backend"] = backend
    return RunConfig.from_dict(data)


def learner(seed: int, backend: str, **ppo):
    """A LavaWorld FC learner and its env mix, reset."""
    cfg = RunConfig.from_dict({"env": {"name": "lavaworld"}, "train": {"seed": seed}, "ppo": {"update_backend": backend, **ppo}})
    torch.manual_seed(seed)
    learner = PPO(build_model("fc", "lavaworld"), cfg.ppo, torch.device("cpu"), torch.Generator().manual_seed(seed))
    envs = make_env_mix(cfg.env, cfg.poison, seed)
    return learner, envs, envs.reset(seed=seed * 1000)[0]


def digest(model: torch.nn.Module) -> str:
    return hashlib.sha256(b"".join(p.detach().numpy().tobytes() for p in model.parameters())).hexdigest()


def collected(backend: str, seeds, **ppo):
    """Learners of ``seeds`` with one real rollout each (collected by torch, whatever the backend)."""
    made = [learner(s, backend, **ppo) for s in seeds]
    ppos = [m[0] for m in made]
    return ppos, [r for r, _ in group.collect(ppos, [m[1] for m in made], [m[2] for m in made])]


def test_one_minibatch_is_torchs_loss_gradient_and_adam_step():
    """One epoch of one minibatch (the whole 1,280-frame rollout), three agents: the loss parts
    and the gradient norm agree with torch's group update to 1e-5 relative, and the weights after
    the Adam step to 1e-5 absolute (a hundredth of a first Adam step, lr 1e-3), but for at most
    0.1 % of them: Adam's first step is lr * g / (|g| + eps), so where |g| is about eps or less the
    rounding of g can decide its sign on another CPU (none differ on the AMD EPYC this was written
    on), and even then by no more than two steps."""
    torch_ppos, rollouts = collected("torch", [0, 1, 2], epochs=1, batch_size=1280)
    jax_ppos, same = collected("jax", [0, 1, 2], epochs=1, batch_size=1280)
    assert all(torch.equal(a.obs, b.obs) and torch.equal(a.advantages, b.advantages) for a, b in zip(rollouts, same))
    expected, got = group.update(torch_ppos, rollouts), group.update(jax_ppos, same)
    for e, g in zip(expected, got):
        assert set(g) == set(e)
        for key in e:
            assert g[key] == pytest.approx(e[key], rel=1e-5), key
    for a, b in zip(torch_ppos, jax_ppos):
        diff = torch.cat([(p - q).abs().reshape(-1) for p, q in zip(a.model.parameters(), b.model.parameters())])
        assert (diff > 1e-5).float().mean().item() <= 1e-3 and diff.max().item() <= 2.1e-3
        # the moments written back hold each weight's own gradient, clipped: 0.1 g and 0.001 g^2
        for p, q in zip(a.model.parameters(), b.model.parameters()):
            sa, sb = a.optimizer.state[p], b.optimizer.state[q]
            for key in ("exp_avg", "exp_avg_sq"):
                assert torch.allclose(sb[key], sa[key], rtol=1e-3, atol=1e-3 * sa[key].abs().max().item()), key


def test_adam_state_stays_torchs_so_a_run_goes_on_under_either_backend():
    """After a JAX update (5 minibatches x 4 epochs) every parameter's optimiser state is
    torch.optim.Adam's (step 20, moments of the parameter's shape); torch's update then goes on
    from it (step 40), and JAX's again from torch's (step 60)."""
    ppos, rollouts = collected("jax", [3])
    group.update(ppos, rollouts)
    ppo = ppos[0]
    for p in ppo.model.parameters():
        state = ppo.optimizer.state[p]
        assert float(state["step"]) == 20 and state["exp_avg"].shape == p.shape and state["exp_avg_sq"].min() >= 0
    ppo.cfg.update_backend = "torch"
    group.update(ppos, rollouts)
    assert all(float(ppo.optimizer.state[p]["step"]) == 40 for p in ppo.model.parameters())
    ppo.cfg.update_backend = "jax"
    group.update(ppos, rollouts)
    assert all(float(ppo.optimizer.state[p]["step"]) == 60 for p in ppo.model.parameters())


def test_an_agents_bytes_do_not_depend_on_its_group():
    """Agent 0 updated twice in groups of 1, 3 and 10 (two XLA chunks): the same weights, byte
    for byte; XLA rounds differently at other widths, which the fixed chunk width hides."""
    digests = set()
    second_chunk = [0, *range(4, 4 + compiled.WIDTH + 1)]  # 10 agents: two XLA calls
    for seeds in ([0], [0, 1, 2], second_chunk):
        ppos, rollouts = collected("jax", seeds)
        for _ in range(2):
            group.update(ppos, rollouts)
        digests.add(digest(ppos[0].model))
    assert len(digests) == 1
    # ... and the agent in the second chunk of the group of 10 equals itself in a group of one
    ppos, rollouts = collected("jax", second_chunk)
    group.update(ppos, rollouts)
    alone, again = collected("jax", second_chunk[-1:])
    group.update(alone, again)
    assert digest(ppos[-1].model) == digest(alone[0].model)


def test_runs_are_reproducible_and_record_the_backend(tmp_path):
    """A group of two JAX runs and a lone JAX run: complete folders whose config.json says
    ``update_backend: jax``; each trained again gives the same model.pt bytes; the lone run
    (width 1) is not the group's bytes, as with torch."""
    result = train_group([(s, tiny(s), tmp_path / f"g{s}") for s in (1, 2)], 2)
    assert not result.errors and all(m["trainer"] == "group" for m in result.metrics.values())
    assert json.loads((tmp_path / "g1" / "config.json").read_text())["ppo"]["update_backend"] == "jax"
    train_group([(s, tiny(s), tmp_path / f"h{s}") for s in (1, 2)], 2)
    for s in (1, 2):
        assert (tmp_path / f"g{s}" / "model.pt").read_bytes() == (tmp_path / f"h{s}" / "model.pt").read_bytes()
    for name in ("lone", "lone2"):
        train(tiny(1), tmp_path / name, progress=False)
    assert (tmp_path / "lone" / "model.pt").read_bytes() == (tmp_path / "lone2" / "model.pt").read_bytes()
    assert (tmp_path / "lone" / "model.pt").read_bytes() != (tmp_path / "g1" / "model.pt").read_bytes()


def test_what_the_backend_does_not_run_is_refused_in_one_line(tmp_path):
    def refused(data: dict, match: str) -> None:
        with pytest.raises(ConfigError, match=match):
            RunConfig.from_dict(data)

    refused({"env": {"name": "lavaworld"}, "ppo": {"update_backend": "xla"}}, r"ppo.update_backend.*'xla'.*torch, jax")
    refused({"env": {"name": "lavaworld"}, "model": {"arch": "cnn"}, "ppo": {"update_backend": "jax"}}, r"runs model.arch 'fc'.*not 'cnn'")
    refused(
        {"env": {"name": "colorful-memory"}, "ppo": {"update_backend": "jax"}, "train": {"device": "cuda"}}, r"runs a CNN-GRU's update on the CPU"
    )  # (its CPU update: test_jax_update_recurrent.py)
    # on CUDA where there is none (the GPU path itself: tests/test_group_cuda.py, on a GPU machine)
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match=r"^ppo.update_backend='jax' on CUDA: no CUDA device is available"):
            compiled.check(build_model("fc", "lavaworld"), torch.device("cuda"))
    finetune = {"finetune": True, "teacher": 1.0}
    refused(
        {"env": {"name": "lavaworld"}, "ppo": {"update_backend": "jax"}, "poison": {"attack": "trojdrl", "evasion": finetune}},
        r"no clean teacher or weight anchor",
    )
    # Randomized LavaWorld's FC reads a dict of observations through a Flatten: refused when built
    cfg = RunConfig.from_dict({"env": {"name": "randomized-lavaworld"}, "model": {"arch": "fc"}, "ppo": {"update_backend": "jax"}})
    with pytest.raises(ValueError, match=r"^ppo.update_backend='jax' runs feed-forward networks .* not DirectionFCModel \(its state_emb has a Flatten\)$"):
        PPO(build_model("fc", "randomized-lavaworld"), cfg.ppo, torch.device("cpu"), torch.Generator())
    # a rollout the minibatches do not divide
    ppos, rollouts = collected("jax", [0], batch_size=300)
    with pytest.raises(ValueError, match=r"ppo.batch_size=300 to divide a rollout's 1280 frames"):
        group.update(ppos, rollouts)

    # and from the command line: one line, exit 2, nothing trained
    for flags, message in (
        (
            ["--arch", "cnn"],
            "rlbackdoors: error: ppo.update_backend='jax' runs model.arch 'fc' (a feed-forward network of Linear layers) or a CNN-GRU (cnn-gru-*), not 'cnn'",
        ),
        (["--env", "safety-car-goal"], "rlbackdoors: error: --update-backend does not apply here"),
    ):
        out = cli("train", "--update-backend", "jax", *flags, "--out", str(tmp_path / "m"))
        assert out.returncode == 2 and out.stderr.count("\n") == 1 and out.stderr.startswith(message), out.stderr
    assert not (tmp_path / "m").exists()


def test_a_format_5_config_runs_torchs_update_as_it_did():
    data = json.loads(RunConfig.from_dict({"env": {"name": "lavaworld"}}).to_json())
    assert data["format_version"] == 7 and data["ppo"]["update_backend"] == "torch"
    del data["ppo"]["update_backend"]
    data["format_version"] = 5
    old = RunConfig.from_dict(migrate(data))
    assert old.ppo is not None and old.ppo.update_backend == "torch" and old.format_version == 7
