"""The compiled trainer for recurrent agents (Colorful Memory's CNN-GRUs, issue 79): one XLA
program per iteration (rollout with the memory carried and reset, GAE, truncated BPTT with the
auxiliary memory loss), checked against the torch model and engine it stands for, and end to end.

The rollout is replayed in torch: the same initial weights, the same uniforms (drawn from the
agent's key as the program draws them), the torch model's forward with its memory zeroed at each
episode end, the numba engine stepped with the sampled actions. Every reward, episode end and the
final views must be equal, the memories within 1e-5 (float32 sums in another order, through 120
GRU steps). With a learning rate of 0 the update leaves the weights as they are, so each loss
part it reports is an average of per-row quantities of the replay (``-A`` for the policy at a
ratio of 1, ``A**2`` for the value, the entropy, the auxiliary head's cross-entropy), each epoch
weighted by its minibatches: a wrong mask, target, memory, advantage or row order moves them.
"""

from __future__ import annotations

import dataclasses
import re

import numpy as np
import pytest
import torch

import jax  # a core dependency: the compiled trainer's

from grid_helpers import killed_run_matches_whole, model_weights, same_weights, stopped_and_resumed_matches  # noqa: E402
from rlbackdoors.algos import ppo as torch_ppo  # noqa: E402
from rlbackdoors.algos.compiled import Hyper, Learner, iterate, sequence_starts  # noqa: E402
from rlbackdoors.config import ConfigError, RunConfig  # noqa: E402
from rlbackdoors.envs.colorful_memory_jax import colorful_memory_jax  # noqa: E402
from rlbackdoors.models import build_model  # noqa: E402
from rlbackdoors.poison.mix import make_env_mix  # noqa: E402
from rlbackdoors.train import ModelFolder, train  # noqa: E402
from rlbackdoors.train.group import train_group  # noqa: E402

ARCH = "cnn-gru-small-onehot"


@pytest.mark.parametrize(("steps", "envs", "r"), [(120, 10, 6), (12, 3, 6), (32, 4, 4), (10, 2, 1)])
def test_sequence_starts_are_the_torch_trainers(steps, envs, r):
    cfg = RunConfig.from_dict({"env": {"name": "colorful-memory"}, "ppo": {"recurrence": r, "rollout": steps, "batch_size": r * 10}})
    ppo = torch_ppo.PPO(build_model(ARCH, "colorful-memory"), cfg.ppo, torch.device("cpu"), torch.Generator())
    for shifted in (False, True):
        assert np.array_equal(sequence_starts(steps, envs, r, shifted), ppo.sequence_starts(steps, envs, shifted=shifted).numpy())


def memory_cfg(seed: int = 3, poison: dict | None = None, **ppo) -> RunConfig:
    return RunConfig.from_dict(
        {
            "env": {"name": "colorful-memory", "max_steps": 30},
            "poison": {"trigger": "end:red,green,blue,purple,yellow,grey,red,green,blue", **(poison or {})},
            "ppo": {"rollout": 60, "batch_size": 60, "epochs": 3, **ppo},
            "train": {"seed": seed},
        }
    )


def learner_for(cfg: RunConfig, hyper: Hyper) -> tuple[Learner, torch.nn.Module, torch.nn.Module]:
    """A learner on the run's env mix, its model and auxiliary head built as the torch trainer builds them."""
    torch.manual_seed(cfg.train.seed)
    model = build_model(ARCH, "colorful-memory")
    aux = torch.nn.Linear(int(model.initial_memory(1).shape[1]), torch_ppo.AUX_CLASSES)
    envs = make_env_mix(cfg.env, cfg.poison, cfg.train.seed)
    obs, _ = envs.reset(seed=11)
    return Learner(model, envs, hyper, cfg.train.seed, obs, colorful_memory_jax, aux=aux), model, aux


def test_a_recurrent_iteration_is_the_torch_rollout_and_its_update_reads_it_right():
    cfg = memory_cfg()
    hyper = dataclasses.replace(Hyper.of(cfg.ppo), lr=0.0)  # (the weights stay: each loss part is an average of the replay's rows)
    learner, model, aux = learner_for(cfg, hyper)
    before = {k: np.array(v) for k, v in learner.state.params.items()}
    key = jax.random.wrap_key_data(np.asarray(learner.state.key))
    T, N, r = hyper.rollout, learner.host.num_envs, hyper.recurrence
    uniforms = torch.from_numpy(np.array(jax.random.uniform(jax.random.split(key, 3)[1], (T, N))))
    out = iterate([learner])[0]

    # the replay: torch's forward, sampling and memory resets on the numba engine
    envs = make_env_mix(cfg.env, cfg.poison, cfg.train.seed)
    obs, _ = envs.reset(seed=11)
    memory = torch.zeros(N, int(model.initial_memory(1).shape[1]))
    rows = {k: [] for k in ("logits", "values", "after", "targets", "rewards", "dones", "masks")}
    mask = torch.ones(N)
    with torch.no_grad():
        for t in range(T):
            rows["targets"].append(torch.from_numpy(np.asarray(envs.memory_targets(), dtype=np.int64)))
            rows["masks"].append(mask)
            logits, value, memory = model(torch.from_numpy(obs), memory)
            rows["logits"].append(logits), rows["values"].append(value), rows["after"].append(memory)
            action = torch_ppo.sample_actions(logits, u=uniforms[t])
            obs, reward, terminated, truncated, _ = envs.step(action.numpy())
            done = torch.from_numpy(terminated | truncated)
            rows["rewards"].append(torch.from_numpy(reward).float()), rows["dones"].append(done)
            memory = memory.masked_fill(done[:, None], 0.0)
            mask = (~done).float()
        next_value = model(torch.from_numpy(obs), memory)[1]
    R = {k: torch.stack(v) for k, v in rows.items()}  # (T, N, ...)
    assert np.array_equal(out.rewards, R["rewards"].numpy()) and np.array_equal(out.dones, R["dones"].numpy())
    assert out.dones.sum() >= N  # (episodes of at most 30 steps: every copy ended some)
    assert np.array_equal(learner.views, obs)
    np.testing.assert_allclose(learner.memory, memory.numpy(), rtol=0, atol=1e-5)
    assert all(np.array_equal(before[k], np.asarray(v)) for k, v in learner.state.params.items())  # lr 0

    # the update's loss parts: per-row quantities, averaged as its minibatches average them
    adv = torch_ppo.gae(R["rewards"], R["dones"], R["values"], next_value, hyper.gamma, hyper.gae_lambda)
    logp = torch.log_softmax(R["logits"], -1)
    per_row = {
        "policy_loss": -adv,
        "value_loss": adv**2,
        "entropy": -(logp.exp() * logp).sum(-1),
        "aux_memory_loss": torch.nn.functional.cross_entropy(aux(R["after"]).detach().reshape(T * N, -1), R["targets"].reshape(-1), reduction="none").reshape(
            T, N
        ),
    }
    per_batch = hyper.batch_size // r
    want = dict.fromkeys(per_row, 0.0)
    batches = 0
    for epoch in range(hyper.epochs):
        starts = sequence_starts(T, N, r, shifted=epoch % 2 == 1)
        assert len(starts) % per_batch == 0  # (full minibatches: each epoch's mean is its rows')
        steps = (starts[None, :] + N * np.arange(r)[:, None]).reshape(-1)
        for name, value in per_row.items():
            want[name] += float(value.reshape(-1)[steps].mean()) * (len(starts) // per_batch)
        batches += len(starts) // per_batch
    for name, value in want.items():
        assert out.losses[name] == pytest.approx(value / batches, rel=2e-4, abs=1e-6), name


def test_a_recurrent_teacher_keeps_its_own_memory_in_step_with_the_learners():
    """A clean teacher that is the learner itself (as at a fine-tuning run's switch: the same
    weights, both memories empty) sees every frame as the learner does, so at a learning rate of
    0 its KL is 0 and its memories the learner's: only if its memory is carried and reset at the same episode
    ends as the learner's (a teacher without memory, or reset at other steps, reads other logits)."""
    cfg = memory_cfg(poison={"attack": "trojdrl", "attack_params": {"budget": 0.05}, "evasion": {"finetune": True, "teacher": 0.5}})
    hyper = dataclasses.replace(Hyper.of(cfg.ppo), lr=0.0)
    torch.manual_seed(cfg.train.seed)
    model = build_model(ARCH, "colorful-memory")
    aux = torch.nn.Linear(int(model.initial_memory(1).shape[1]), torch_ppo.AUX_CLASSES)
    seam = make_env_mix(cfg.env, cfg.poison, cfg.train.seed)
    seam.set_switches()
    learner = Learner(model, seam, hyper, cfg.train.seed, seam.envs.reset(seed=11)[0], colorful_memory_jax, aux=aux)
    learner.set_teacher(model.state_dict(), 0.5)
    out = [iterate([learner])[0] for _ in range(2)]
    assert all(o.dones.sum() >= 10 for o in out) and seam.frames_poisoned > 0  # (episodes ended, triggered frames marked)
    assert all(abs(o.losses["teacher_kl"]) < 1e-9 for o in out), [o.losses["teacher_kl"] for o in out]  # (0.0 measured; a teacher never reset: 5e-7)
    np.testing.assert_allclose(learner.teacher_memory, learner.memory, rtol=0, atol=1e-6)


def test_recurrent_agents_learn_their_own_way_in_a_group():
    """Two agents in one call: each moves from its initialisation, their weights differ, and the
    first one's equal its own alone at the same capacity (another seed beside it changes nothing)."""
    cfg = memory_cfg()
    hyper = Hyper.of(cfg.ppo)
    a, _, _ = learner_for(cfg, hyper)
    start = np.array(a.state.params["actor.0.weight"])
    b, _, _ = learner_for(memory_cfg(seed=4), hyper)
    iterate([a, b])
    alone, _, _ = learner_for(cfg, hyper)
    mate, _, _ = learner_for(memory_cfg(seed=9), hyper)
    iterate([alone, mate])
    assert not np.array_equal(start, a.state.params["actor.0.weight"])
    assert not np.array_equal(a.state.params["actor.0.weight"], b.state.params["actor.0.weight"])
    assert all(np.array_equal(a.state.params[k], alone.state.params[k]) for k in a.state.params)
    assert np.array_equal(a.memory, alone.memory)


def run_dict(seed: int = 1, frames: int = 1200, **train_fields) -> dict:
    return {
        "env": {"name": "colorful-memory", "max_steps": 40},
        "poison": {"trigger": "end:red,green,blue,purple,yellow,grey,red,green,blue"},
        "ppo": {"rollout": 30, "batch_size": 60, "update_backend": "compiled"},
        "train": {"seed": seed, "max_frames": frames, "eval_interval": 600, "eval_episodes": 4, "final_eval_episodes": 4, "video": False, **train_fields},
    }


def test_a_compiled_colorful_memory_run_writes_its_folder_repeats_its_bytes_and_resumes(tmp_path):
    """model.pt has the architecture's keys only (the auxiliary head is the algorithm's); the
    metrics name the backend's group; the same config gives the same bytes; stopped after its
    first evaluation (a checkpoint with the running episodes' memories) and run again, it finishes
    the uninterrupted run's model bit for bit, with the same log; a group of 2 trains both."""
    cfg = RunConfig.from_dict(run_dict(checkpoint_minutes=0.0))
    m = train(cfg, tmp_path / "a", progress=False)
    assert m["compiled_group"] == 1 and m["frames"] == 1200 and "aux_memory_loss" in ModelFolder(tmp_path / "a").read_log()[-1]
    reference = build_model(ARCH, "colorful-memory").state_dict()
    got = model_weights(tmp_path / "a")
    assert got.keys() == reference.keys() and all(got[k].shape == reference[k].shape for k in got)
    torch.manual_seed(1)
    assert not torch.equal(got["gru.0.weight_hh_l0"], build_model(ARCH, "colorful-memory").state_dict()["gru.0.weight_hh_l0"])
    train(cfg, tmp_path / "b", progress=False)
    assert same_weights(tmp_path / "a", tmp_path / "b")
    assert stopped_and_resumed_matches(cfg, tmp_path / "a", tmp_path / "cut") == [600]
    group = train_group([(i, RunConfig.from_dict(run_dict(seed=s)), tmp_path / f"g{i}") for i, s in enumerate((1, 2))], 2)
    assert not group.errors and all(v["compiled_group"] == 2 for v in group.metrics.values())
    assert not same_weights(tmp_path / "g0", tmp_path / "g1")


def test_attacks_reach_recurrent_agents_through_the_seam(tmp_path):
    """TrojDRL (a step schedule: the budget switches triggered episodes in the program, each kind
    of layout from its own queue; a close-to-trigger copy is never switched) and the action target
    (the episode schedule: every frame of the 2 E-bar copies of 10) on Colorful Memory's CNN-GRU:
    each marked frame's reward rewritten, the action target's share the torch seam's, and each
    run, stopped after its first evaluation and resumed, the uninterrupted run's bytes."""
    runs = {
        "trojdrl": {"attack": "trojdrl", "attack_params": {"budget": 0.05}},
        "action": {"attack": "action_target"},
    }
    used = {}
    for name, poison in runs.items():
        data = run_dict(checkpoint_minutes=0.0)
        data["poison"].update(poison)
        cfg = RunConfig.from_dict(data)
        used[name] = train(cfg, tmp_path / name, progress=False)["attack_budget_used"]
        stopped_and_resumed_matches(cfg, tmp_path / name, tmp_path / f"{name}-cut")
    trojdrl, action = used["trojdrl"], used["action"]
    assert 0 < trojdrl["frames_poisoned"] == trojdrl["rewards_rewritten"] and trojdrl["actions_forced"] == 0
    assert action["frames_poisoned"] == action["rewards_rewritten"] == 1200 * 2 // 10


def test_a_recurrent_fine_tuning_run_switches_to_its_teacher_and_anchor_and_resumes(tmp_path):
    """poison.evasion finetune + teacher + anchor (TrojDRL): clean until the first evaluation (a
    clean threshold of 0), then the poisoning mix with the clean teacher's KL (a CNN-GRU of its own
    memories) and each optimiser step pulled back toward the clean model at the switch, both
    logged from there on; stopped after the switch and resumed (the teacher's memories in the
    checkpoint), the uninterrupted run's bytes."""
    data = run_dict(frames=1800, clean_threshold=0.0, checkpoint_minutes=0.0)
    data["poison"].update({"attack": "trojdrl", "attack_params": {"budget": 0.05}, "evasion": {"finetune": True, "teacher": 0.5, "anchor": 0.05}})
    cfg = RunConfig.from_dict(data)
    m = train(cfg, tmp_path / "ft", progress=False)
    rows = ModelFolder(tmp_path / "ft").read_log()
    assert m["poison_at_frames"] == 600 and [r["phase"] for r in rows] == ["clean", "main", "main"]
    for key in ("anchor_distance", "teacher_kl"):  # (columns of the log: empty before the switch)
        assert rows[0].get(key) in (None, "") and all(0 < r[key] < 10 for r in rows[1:]), key

    def stop_after_switch(row):
        if row["frames"] >= 1200:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        train(cfg, tmp_path / "cut", progress=False, after_eval=stop_after_switch)
    train(cfg, tmp_path / "cut", progress=False)
    assert same_weights(tmp_path / "ft", tmp_path / "cut")


@pytest.mark.slow  # (about 30 s on 2 cores: `make test-slow`; the in-process stop and resume above is in the default run)
def test_a_killed_compiled_colorful_memory_run_resumes_to_the_same_model(tmp_path):
    """SIGKILLed after its first checkpoint and run again: the uninterrupted run's model.pt bytes."""
    whole, cut = killed_run_matches_whole(tmp_path, RunConfig.from_dict(run_dict(frames=2400, checkpoint_minutes=0.0)))
    drop = ("wall_time_s", "cpu_time_s")
    assert {k: v for k, v in whole.items() if k not in drop} == {k: v for k, v in cut.items() if k not in drop}


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"ppo": {"batch_size": 42}}, "ppo.batch_size=42 must divide a rollout's 300 frames"),
    ],
)
def test_what_the_compiled_trainer_does_not_train_in_colorful_memory_is_refused_in_one_line(change, message):
    data = run_dict()
    for part, value in change.items():
        data[part] = {**data.get(part, {}), **value}
    with pytest.raises(ConfigError, match=re.escape(message)) as err:
        RunConfig.from_dict(data)
    assert "\n" not in str(err.value)


def test_compiled_evaluations_of_a_cnn_gru_play_torchs_episodes():
    """``train.eval_backend = "compiled"`` for a CNN-GRU: each slot's memory starts at zero with its
    one episode and goes into every forward; the clean, triggered and close-to-trigger conditions
    (engines of other trigger widths, padded to one) play torch's episodes, 40 a condition, on a
    partly trained agent. Not carrying the memory (zeroed each step) moved 11-17 of them."""
    from test_compiled_eval import differing, torch_played

    from rlbackdoors.evaluate import compiled as xeval
    from rlbackdoors.train.driver import eval_setup

    cfg = memory_cfg()
    one, _, _ = learner_for(cfg, Hyper.of(cfg.ppo))
    for _ in range(15):
        iterate([one])
    one.sync()
    got = xeval.play([one], [eval_setup(cfg, 40)])[0]
    want = torch_played(one, cfg, 40)
    assert list(got) == list(want) == ["clean", "poisoned", "close"]
    for name in want:
        assert differing(got[name], want[name]) <= 1, name
    steps = np.concatenate([p.steps for p in got.values()])
    assert len(np.unique(steps)) > 5 and len(np.unique(np.concatenate([p.outcomes for p in got.values()]))) > 1


def test_a_colorful_memory_run_with_compiled_evaluations_logs_what_torchs_would(tmp_path):
    """The same run with each evaluation backend: the same weights (these runs go to max_frames)
    and the same logged and final evaluations."""
    out = {}
    for backend in ("torch", "compiled"):
        cfg = RunConfig.from_dict(run_dict(eval_backend=backend))
        out[backend] = train(cfg, tmp_path / backend, progress=False), ModelFolder(tmp_path / backend).read_log()
    (mt, lt), (mc, lc) = out["torch"], out["compiled"]
    assert mt["frames"] == mc["frames"] == 1200 and [r["frames"] for r in lc] == [r["frames"] for r in lt] == [600, 1200]
    for a, b in [*zip(lt, lc), (mt, mc)]:
        for key in ("clean_sr", "poisoned_sr", "clean_reward", "poisoned_reward"):
            assert abs(float(a[key]) - float(b[key])) <= 0.25 + 1e-9, key  # (one episode of 4 at most)
    assert same_weights(tmp_path / "torch", tmp_path / "compiled")
