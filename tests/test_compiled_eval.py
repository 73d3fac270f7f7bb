"""A compiled run's evaluations in its program (``train.eval_backend = "compiled"``,
evaluate/compiled.py) against torch's: the same layouts, uniforms and scoring, so the same
episodes, for LavaWorld (a frame trigger) and Randomized LavaWorld (a layout trigger: the
trigger-seen flags, and an action target counted in sight of it), FC and CNN; group-mates that do
not move a run's numbers; and runs whose logs match the torch evaluation's.

Why "at most one or two episodes in 100 differ" and not "equal": the forward is XLA's float32
arithmetic, not torch's, so an action whose uniform falls within an ulp of a boundary of the
policy's CDF may differ (about 1e-7 of a step's draws; none in these runs here, a few thousand steps
each; 30 to 100 episodes a condition). Every check below would fail on a wrong layout, seed, uniform order, sight or scoring:
those move most episodes.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch


from rlbackdoors.algos.compiled import Hyper, Learner, iterate  # noqa: E402
from rlbackdoors.config import RunConfig  # noqa: E402
from rlbackdoors.evaluate import compiled as xeval  # noqa: E402
from rlbackdoors.evaluate.episodes import Played, _vector_envs, play_episodes  # noqa: E402
from rlbackdoors.models import build_model  # noqa: E402
from rlbackdoors.poison.mix import make_env_mix  # noqa: E402
from rlbackdoors.train import ModelFolder, train  # noqa: E402
from rlbackdoors.train.driver import eval_setup, evaluate_compiled, evaluate_runs  # noqa: E402


def learner(world: str, arch: str, poison: dict, iterations: int, seed: int = 0, policy: str = "sample") -> tuple[Learner, RunConfig]:
    """A compiled learner trained ``iterations`` iterations (partly trained: episodes of every length)."""
    from importlib import import_module

    cfg = RunConfig.from_dict(
        {
            "env": {"name": world},
            "model": {"arch": arch},
            "poison": poison,
            "ppo": {"update_backend": "compiled"},
            "train": {"eval_backend": "compiled", "eval_policy": policy, "seed": seed},
        }
    )
    mix = make_env_mix(cfg.env, cfg.poison, seed)
    if hasattr(mix, "set_switches"):  # an attack's collection seam: the program starts from the engine's own views
        mix.set_switches()
        obs, _ = mix.envs.reset(seed=seed * 1000)
    else:
        obs, _ = mix.reset(seed=seed * 1000)
    torch.manual_seed(seed)
    module, _, name = str(cfg.world.compiled_engine).partition(":")
    one = Learner(build_model(arch, world), mix, Hyper.of(cfg.ppo), seed, obs, getattr(import_module(module), name))
    for _ in range(iterations):
        iterate([one])
    one.sync()
    return one, cfg


def torch_played(one: Learner, cfg: RunConfig, episodes: int) -> dict[str, Played]:
    """torch's episodes of each condition (evaluate.episodes.play_episodes, as evaluate_many plays them)."""
    setup = eval_setup(cfg, episodes)
    hits = None
    out = {}
    for name, trigger, close_k, target in setup.conditions():
        hits = None if target is None else cfg.world.target_hits(target)
        envs = _vector_envs(setup.env, trigger, episodes, close_k)
        try:
            out[name] = play_episodes(one.model, envs, setup.seed, setup.policy, hits, sight=cfg.world.trigger_sight == "frame")
        finally:
            envs.close()
    return out


def differing(a: Played, b: Played) -> int:
    """Episodes that did not play out the same (outcome, length, return, trigger seen, target counts)."""
    same = (a.outcomes == b.outcomes) & (a.steps == b.steps) & (a.returns == b.returns) & (a.saw == b.saw)
    if a.target_steps is not None or b.target_steps is not None:
        assert a.target_steps is not None and b.target_steps is not None and a.sighted_steps is not None and b.sighted_steps is not None
        same &= (a.target_steps == b.target_steps) & (a.sighted_steps == b.sighted_steps)
    return int((~same).sum())


def check_same(one: Learner, cfg: RunConfig, counted: bool = False, episodes: int = 100) -> dict[str, Played]:
    want = torch_played(one, cfg, episodes)
    got = xeval.play([one], [eval_setup(cfg, episodes)])[0]
    assert list(got) == list(want) == ["clean", "poisoned"]
    for name in want:
        assert got[name].returns.dtype == np.float64 and len(got[name].outcomes) == episodes
        assert differing(got[name], want[name]) <= 2, name
    assert (got["poisoned"].target_steps is not None) == counted
    a, b = evaluate_runs([one.model], [cfg], [episodes])[0].to_dict(), evaluate_compiled([one], [cfg], [episodes])[0].to_dict()
    for key, value in a.items():
        assert np.isnan(value) == np.isnan(b[key]) and (np.isnan(value) or abs(value - b[key]) <= 0.02 * max(1.0, abs(value))), key
    return got


@pytest.mark.parametrize("policy, iterations", [("sample", 40), ("greedy", 120)])  # (greedy: trained on until it stops spinning)
def test_lavaworld_fc_plays_torchs_episodes(policy, iterations):
    one, cfg = learner("lavaworld", "fc", {"trigger": "multiplicative:12"}, iterations, policy=policy)
    got = check_same(one, cfg)
    assert len(np.unique(np.concatenate([p.steps for p in got.values()]))) > 5  # (episodes of many lengths: a wrong step would show)


def test_randomized_lavaworld_counts_an_action_target_in_sight_of_the_trigger():
    """A layout trigger: the trigger-seen flags and the target's steps among those in sight of it."""
    one, cfg = learner("randomized-lavaworld", "fc", {"trigger": "cross", "attack": "action_target"}, 20)
    got = check_same(one, cfg, counted=True, episodes=50)
    p = got["poisoned"]
    assert p.sighted_steps is not None and 0 < p.sighted_steps.sum() < p.steps.sum()  # in sight on some steps, not all


def test_randomized_lavaworld_cnn_plays_torchs_episodes():
    one, cfg = learner("randomized-lavaworld", "cnn", {"trigger": "cross"}, 6)
    check_same(one, cfg, episodes=30)


def test_group_mates_do_not_move_a_runs_evaluation():
    """At one capacity, a run's episodes are the same alone (padded) and beside another run."""
    a, cfg_a = learner("lavaworld", "fc", {"trigger": "multiplicative:12"}, 10, seed=1)
    b, cfg_b = learner("lavaworld", "fc", {"trigger": "multiplicative:12", "poisoned": False}, 10, seed=2)
    setups = [eval_setup(cfg_a, 20), eval_setup(cfg_b, 20)]
    alone = xeval.play([a], setups[:1], capacity=2)[0]
    together = xeval.play([b, a], setups[::-1], capacity=2)
    for name in alone:
        assert differing(alone[name], together[1][name]) == 0
    assert differing(alone["clean"], together[0]["clean"]) > 0  # another agent plays other episodes
    with pytest.raises(ValueError, match="do not fit a compiled group of 1"):
        xeval.play([a, b], setups, capacity=1)


def test_the_uniforms_are_a_generators_per_step_draws():
    g = torch.Generator().manual_seed(1_000_000)
    steps = np.stack([torch.rand(7, generator=g).numpy() for _ in range(5)])
    np.testing.assert_array_equal(xeval.uniforms(1_000_000, 5, 7), steps)


def test_a_run_with_compiled_evaluations_logs_what_torchs_would(tmp_path):
    """The same run with each evaluation backend: the same weights (the evaluations only decide
    when to stop, and these runs go to max_frames) and the same logged evaluations."""
    base = {
        "env": {"name": "lavaworld"},
        "poison": {"trigger": "multiplicative:12"},
        "ppo": {"rollout": 32, "batch_size": 64, "update_backend": "compiled"},
        "train": {"seed": 1, "max_frames": 1920, "eval_interval": 640, "eval_episodes": 16, "final_eval_episodes": 16, "video": False},
    }
    logs = {}
    for backend in ("torch", "compiled"):
        data = json.loads(json.dumps(base))
        data["train"]["eval_backend"] = backend
        metrics = train(RunConfig.from_dict(data), tmp_path / backend, progress=False)
        assert metrics["frames"] == 1920
        logs[backend] = ModelFolder(tmp_path / backend).read_log()
    assert ModelFolder(tmp_path / "compiled").read_config().train.eval_backend == "compiled"
    assert [r["frames"] for r in logs["compiled"]] == [640, 1280, 1920]
    for a, b in zip(logs["torch"], logs["compiled"]):
        for key in ("clean_sr", "poisoned_sr", "clean_reward", "poisoned_reward", "clean_mean_steps", "poisoned_mean_steps"):
            assert abs(float(a[key]) - float(b[key])) <= 0.07, key  # (one episode of 16 at most: 1/16)
    wa, wb = (torch.load(tmp_path / b / "model.pt", weights_only=True) for b in ("torch", "compiled"))
    assert all(torch.equal(wa[k], wb[k]) for k in wa)


def test_a_compiled_runs_confirmation_and_final_evaluation_are_played_in_the_program_too(tmp_path, monkeypatch):
    """train.eval_backend = "compiled": a stop's confirming evaluation (which is the final one)
    and a run's final evaluation at max_frames are the program's too, and score what torch's do:
    the same weights, the same final numbers in metrics.json (to one episode of 16, a float32 flip)."""
    from rlbackdoors.evaluate import compiled as compiled_eval

    base = {
        "env": {"name": "lavaworld"},
        "poison": {"trigger": "multiplicative:12"},
        "ppo": {"rollout": 32, "batch_size": 64, "update_backend": "compiled"},
        "train": {"seed": 2, "max_frames": 1920, "eval_interval": 640, "eval_episodes": 8, "final_eval_episodes": 16, "video": False},
    }
    stops = {"clean_threshold": 0.0, "poisoned_threshold": 0.0, "patience": 1}  # the first evaluation stops, once confirmed
    played, counts = compiled_eval.play, []
    monkeypatch.setattr(compiled_eval, "play", lambda learners, setups, *a: counts.extend(s.episodes for s in setups) or played(learners, setups, *a))
    for name, extra, frames in (("end", {}, 1920), ("stop", stops, 640)):
        metrics = {}
        for backend in ("torch", "compiled"):
            data = json.loads(json.dumps(base))
            data["train"].update(eval_backend=backend, **extra)
            counts.clear()
            metrics[backend] = train(RunConfig.from_dict(data), tmp_path / f"{name}-{backend}", progress=False)
            # torch's evaluations never reach the program; compiled, every one does: the periodic ones' 8 and the final one's 16 episodes
            assert sorted(set(counts)) == ([] if backend == "torch" else [8, 16]), (name, backend)
        t, c = metrics["torch"], metrics["compiled"]
        assert t["frames"] == c["frames"] == frames and t["converged"] == c["converged"] and t["stop_reason"] == c["stop_reason"]
        for key in ("clean_sr", "poisoned_sr", "clean_reward", "poisoned_reward"):
            assert abs(t[key] - c[key]) <= 1 / 16 + 1e-9, (name, key)
        wa, wb = (torch.load(tmp_path / f"{name}-{b}" / "model.pt", weights_only=True) for b in ("torch", "compiled"))
        assert all(torch.equal(wa[k], wb[k]) for k in wa)
    assert c["stop_reason"] == "thresholds" and c["converged"]
