"""Evasive variants (poison.evasion): near-trigger negatives, fine-tuning a clean model, a clean teacher, a weight anchor.

On the real engines and models: the seam's near frames are checked against a clean engine
stepped alongside, the teacher's log-probabilities against the policy it was copied from, and
a fine-tuning run against the clean model of the same seed, byte for byte.
"""

from __future__ import annotations

import copy
import json
import subprocess
import sys

import numpy as np
import pytest
import torch

from cli_helpers import cli
from grid_helpers import assert_seam_resumes, killed_run_matches_whole
from rlbackdoors import worlds
from rlbackdoors.algos.ppo import PPO
from rlbackdoors.attacks.seam import AttackSeam, EXECUTED_ACTIONS
from rlbackdoors.config import ConfigError, RunConfig
from rlbackdoors.models import build_model
from rlbackdoors.poison.mix import make_env_mix, make_vector_env
from rlbackdoors.train import train
from rlbackdoors.triggers.observation import ObservationTrigger


def cfg_of(env: str = "lavaworld", attack: str = "trojdrl", params: dict | None = None, **evasion) -> RunConfig:
    return RunConfig.from_dict({"env": {"name": env}, "poison": {"attack": attack, "attack_params": params or {}, "evasion": evasion}})


@pytest.mark.parametrize(
    "env, attack, evasion, message",
    [
        ("lavaworld", "trojdrl", {"near": -1}, r"poison\.evasion\.near=-1 is not allowed \(allowed: a number in \[0.0, 8.0\]\)"),
        ("lavaworld", "trojdrl", {"hide": 1}, r"poison\.evasion\.hide is not an evasive variant \(allowed: near, finetune, teacher, clean_frames, anchor\)"),
        ("lavaworld", "trojdrl", {"clean_frames": 1000}, r"poison\.evasion\.clean_frames=1000 needs poison\.evasion\.finetune=true"),
        (
            "lavaworld",
            "trojdrl",
            {"finetune": True, "clean_frames": 0.5},
            r"poison\.evasion\.clean_frames=0\.5 is not allowed \(allowed: an integer in \[0, 1000000000\]\)",
        ),
        (
            "lavaworld",
            "trojdrl",
            {"finetune": True, "clean_frames": 10_000_000},
            r"poison\.evasion\.clean_frames=10000000 must be below train\.max_frames=\d+ \(the run would never poison\)",
        ),
        ("lavaworld", "trojdrl", {"teacher": 1.0}, r"poison\.evasion\.teacher=1\.0 needs poison\.evasion\.finetune=true"),
        ("lavaworld", "trojdrl", {"finetune": 1}, r"poison\.evasion\.finetune=1 is not allowed \(allowed: true, false\)"),
        ("lavaworld", "trojdrl", {"anchor": 0.01}, r"poison\.evasion\.anchor=0\.01 needs poison\.evasion\.finetune=true \(the anchor is the clean model"),
        ("lavaworld", "trojdrl", {"finetune": True, "anchor": 2}, r"poison\.evasion\.anchor=2 is not allowed \(allowed: a number in \[0\.0, 1\.0\]\)"),
        (
            "colorful-memory",
            "trojdrl",
            {"near": 1},
            r"poison\.evasion\.near is not allowed for env\.name='colorful-memory' .*\(worlds with near-trigger variants: lavaworld, randomized-lavaworld, safety-car-goal\)",
        ),
        ("colorful-memory", "action_target", {"near": 1}, r"close-to-trigger copies are these negatives: poison\.num_close_envs"),
        ("safety-car-goal", "trojdrl", {"finetune": True}, r"poison\.evasion\.finetune is built for ppo collection, not opac2"),
    ],
)
def test_bad_evasion_settings_are_refused_naming_the_field(env, attack, evasion, message):
    with pytest.raises(ConfigError, match=message):
        cfg_of(env, attack, **evasion).check()


def test_evasion_is_refused_for_a_clean_model_and_left_out_of_config_json_until_set():
    with pytest.raises(ConfigError, match=r"poison\.evasion is not allowed for a clean model"):
        RunConfig.from_dict({"poison": {"poisoned": False, "evasion": {"near": 1}}}).check()
    plain = RunConfig.from_dict({"poison": {"attack": "trojdrl"}}).check()
    assert "evasion" not in json.loads(plain.to_json())["poison"]
    cfg = cfg_of(near=0.5).check()
    assert json.loads(cfg.to_json())["poison"]["evasion"] == {"near": 0.5, "finetune": False, "teacher": 0.0}
    assert RunConfig.from_dict(json.loads(cfg.to_json())).check().to_json() == cfg.to_json()
    # clean_frames came later: at its default it stays out, so configs written before it keep their bytes
    late = cfg_of(finetune=True, clean_frames=2000).check()
    assert json.loads(late.to_json())["poison"]["evasion"] == {"near": 0.0, "finetune": True, "teacher": 0.0, "clean_frames": 2000}
    assert RunConfig.from_dict(json.loads(late.to_json())).check().to_json() == late.to_json()
    anchored = cfg_of(finetune=True, anchor=0.01).check()  # so did the anchor
    assert json.loads(anchored.to_json())["poison"]["evasion"] == {"near": 0.0, "finetune": True, "teacher": 0.0, "anchor": 0.01}


def test_the_cli_stops_with_one_error_line_naming_the_evasive_field(tmp_path):
    done = cli("train", "--attack", "trojdrl", "--evade", "teacher=2", "--out", tmp_path / "m")
    assert done.returncode == 2 and done.stderr.strip().splitlines() == [
        "rlbackdoors: error: poison.evasion.teacher=2.0 needs poison.evasion.finetune=true (the teacher is the clean model the run fine-tunes from)"
    ]


def test_lavaworlds_near_triggers_are_other_edits_of_the_same_kind_close_to_the_trigger():
    world = worlds.get("lavaworld")
    assert world.near_triggers("multiplicative:12") == tuple(f"multiplicative:{a}" for a in (11, 13, 10, 14, 9, 15))
    near = world.near_triggers("additive:20")
    assert near == ("additive:12", "additive:28", "additive:4", "additive:36", "additive:44")  # 20-16, 20-24 < 1 left out
    for spec in ("multiplicative:2", "multiplicative:255", "additive:255"):
        assert spec not in world.near_triggers(spec) and all(s.split(":")[0] == spec.split(":")[0] for s in world.near_triggers(spec))


def near_or_trigger(obs, clean, tables):
    """Which of ``tables`` (the trigger's first) turns each clean frame into the seam's frame (-1: none)."""
    found = np.full(len(obs), -1)
    for k, table in reversed(list(enumerate(tables))):
        hit = (table[clean] == obs).all(axis=tuple(range(1, obs.ndim)))
        found[hit] = k
    return found


@pytest.mark.parametrize("attack, near", [("trojdrl", 1.0), ("trojdrl", 2.5), ("envmix", 1.0)])
def test_the_seam_stamps_near_trigger_negatives_paid_the_clean_reward(attack, near):
    """Step schedule: ``near`` times as many near frames as trigger frames, among the others;
    episode schedule (the env mix): every frame of round(near x E-bar) clean copies. A near frame
    is a clean frame under one of the world's near triggers, never the trigger, and its reward is the clean one."""
    cfg = cfg_of(attack=attack, params={"budget": 0.05} if attack == "trojdrl" else {}, near=near).check()
    seam = make_env_mix(cfg.env, cfg.poison, seed=5)
    assert isinstance(seam, AttackSeam)
    plain = make_vector_env(cfg.env, cfg.poison.trigger, cfg.poison.poisoned_mask())
    specs = (cfg.poison.trigger, *worlds.get("lavaworld").near_triggers(cfg.poison.trigger))
    tables = [ObservationTrigger.parse(s).lookup_table() for s in specs]
    rng = np.random.default_rng(0)
    obs, _ = seam.reset(seed=9)
    clean, _ = plain.reset(seed=9)
    seen = np.zeros(len(specs), dtype=int)
    ebar = np.asarray(plain.poisoned, dtype=bool)
    for _ in range(200):
        marked = seam.marked.copy()
        changed = (obs != clean).any(axis=(1, 2, 3)) & ~ebar  # E-bar copies carry the engine's trigger
        which = near_or_trigger(obs[changed], clean[changed], tables)
        assert np.all(which >= 0)  # every changed frame is the trigger or a near trigger of it
        np.testing.assert_array_equal(which == 0, marked[changed])  # the trigger exactly where marked
        near_rows = np.flatnonzero(changed)[which > 0]
        if attack == "envmix":
            assert set(near_rows) == set(np.flatnonzero(seam.near_copies)) and seam.near_copies.sum() == 2
        seen += np.bincount(which, minlength=len(specs))
        actions = rng.integers(0, 3, seam.num_envs)
        obs, rewards, *_, info = seam.step(actions)
        clean, clean_rewards, *_ = plain.step(info[EXECUTED_ACTIONS])
        np.testing.assert_array_equal(rewards[near_rows], clean_rewards[near_rows])  # near frames: the clean reward
    used = seam.budget_used()
    assert np.all(seen[1:] > 0)  # every near trigger is drawn
    if attack == "trojdrl":
        assert (
            used["frames_near_trigger"] == int(near * used["frames_poisoned"])
            or used["frames_near_trigger"] >= int(near * used["frames_poisoned"]) - seam.num_envs
        )
    else:
        assert used["near_fraction"] == pytest.approx(0.2) and used["rewards_rewritten"] == 0  # the env mix's R-bar is the engine's


@pytest.mark.parametrize("env, arch, attack", [("lavaworld", "fc", "trojdrl"), ("colorful-memory", "cnn-gru-small-onehot", "action_target")])
def test_the_clean_teacher_is_the_policy_it_was_copied_from_and_is_kept_off_the_trigger(env, arch, attack):
    """A teacher copied from the policy gives the policy's own log-probabilities on a whole rollout
    (a recurrent teacher keeps its memory as the policy does: reset where episodes end), so the
    first KL is 0; it is taken on the frames the seam did not mark, and it grows as the policy learns."""
    cfg = RunConfig.from_dict(
        {
            "env": {"name": env},
            "model": {"arch": arch},
            "ppo": {"rollout": 60},
            "poison": {"attack": attack, "attack_params": {"budget": 0.2} if attack == "trojdrl" else {}},
        }
    ).check()
    torch.manual_seed(0)
    model = build_model(arch, env)
    ppo = PPO(model, cfg.ppo, torch.device("cpu"), torch.Generator().manual_seed(0))
    ppo.set_teacher(copy.deepcopy(model), 1.0)
    seam = make_env_mix(cfg.env, cfg.poison, seed=3)
    obs, _ = seam.reset(seed=3)
    marks = []
    step = seam.step

    def recording_step(actions):
        marks.append(seam.marked.copy())
        return step(actions)

    seam.step = recording_step
    rollout, _ = ppo.collect(seam, obs)
    np.testing.assert_array_equal(rollout.untriggered.numpy(), ~np.concatenate(marks))
    assert 0 < rollout.untriggered.float().mean() < 1
    with torch.inference_mode():
        logits = policy_logits(model, rollout, seam.num_envs)
    torch.testing.assert_close(rollout.teacher_logp, torch.log_softmax(logits, -1), atol=1e-5, rtol=0)
    stats = ppo.update(rollout)
    assert 0 <= stats["teacher_kl"] < 0.05
    second, _ = ppo.collect(seam, obs)
    assert ppo.update(second)["teacher_kl"] > 0  # the policy moved; the teacher did not


@pytest.mark.parametrize("env, arch", [("lavaworld", "fc"), ("colorful-memory", "cnn-gru-small-onehot")])
def test_the_anchor_pulls_every_weight_back_by_its_fraction_after_each_step(env, arch):
    """From the same start and the same minibatches, an anchored update ends nearer the anchor than
    a free one, by the pull the coefficient says (anchor 1: exactly on it), and logs that distance."""
    cfg = RunConfig.from_dict({"env": {"name": env}, "model": {"arch": arch}, "ppo": {"rollout": 36, "epochs": 1}, "poison": {"attack": "trojdrl"}}).check()
    torch.manual_seed(0)
    model = build_model(arch, env)
    start = copy.deepcopy(model.state_dict())
    seam = make_env_mix(cfg.env, cfg.poison, seed=3)
    rollout, _ = PPO(copy.deepcopy(model), cfg.ppo, torch.device("cpu"), torch.Generator().manual_seed(0)).collect(seam, seam.reset(seed=3)[0])

    def updated(coef: float | None) -> tuple[PPO, dict]:
        ppo = PPO(copy.deepcopy(model), cfg.ppo, torch.device("cpu"), torch.Generator().manual_seed(0))
        if coef is not None:
            ppo.set_anchor(start, coef)
        return ppo, ppo.update(rollout)

    def distance(ppo: PPO) -> float:
        return float(sum((p.detach().double() - start[n].double()).pow(2).sum() for n, p in ppo.model.named_parameters()).sqrt())

    free, free_stats = updated(None)
    held, held_stats = updated(0.5)
    pinned, pinned_stats = updated(1.0)
    assert "anchor_distance" not in free_stats and distance(free) > 0
    assert 0 < distance(held) < 0.75 * distance(free)  # each step moves at most half as far from the anchor
    assert held_stats["anchor_distance"] == pytest.approx(distance(held), rel=1e-6)
    assert pinned_stats["anchor_distance"] == 0.0
    for name, param in pinned.model.named_parameters():
        assert torch.equal(param.detach(), start[name])


def policy_logits(model, rollout, B):
    """The model's logits on a whole rollout (a recurrent one from the first step's stored memory)."""
    if model.recurrent:
        obs_seq = rollout.obs.reshape(-1, B, *rollout.obs.shape[1:])
        return model.forward_sequence(obs_seq, rollout.memories[:B], rollout.masks.reshape(-1, B))[0]
    return model(rollout.obs)[0]


def finetune_dict(tiny_run_dict, **evasion):
    tiny_run_dict["train"]["clean_threshold"] = 0.0  # the switch at the first evaluation
    tiny_run_dict["poison"] = {"attack": "trojdrl", "attack_params": {"budget": 0.05}, "evasion": {"finetune": True, **evasion}}
    return tiny_run_dict


def test_a_finetuning_run_is_the_clean_models_run_until_it_switches(tmp_path, tiny_run_dict):
    """Until the clean threshold holds, a fine-tuning run *is* the clean model of its seed: stopped
    at the switch, it ends with that clean model's bytes; trained on, it poisons from there."""
    data = finetune_dict(tiny_run_dict)
    data["train"]["max_frames"] = data["train"]["eval_interval"]
    metrics = train(RunConfig.from_dict(data), tmp_path / "ft", progress=False)
    clean = copy.deepcopy(data)
    clean["poison"] = {"poisoned": False, "trigger": RunConfig.from_dict(data).poison.trigger}
    train(RunConfig.from_dict(clean), tmp_path / "clean", progress=False)
    assert metrics["poison_at_frames"] == metrics["frames"]
    assert (tmp_path / "ft" / "model.pt").read_bytes() == (tmp_path / "clean" / "model.pt").read_bytes()
    data["train"]["max_frames"] = 3 * data["train"]["eval_interval"]
    longer = train(RunConfig.from_dict(data), tmp_path / "longer", progress=False)
    assert longer["poison_at_frames"] == metrics["frames"] < longer["frames"]
    assert 0 < longer["attack_budget_used"]["frames_poisoned"] <= 0.05 * (longer["frames"] - metrics["frames"]) + 10


def test_clean_frames_hold_the_switch_until_that_many_frames_are_trained_clean(tmp_path, tiny_run_dict):
    """With clean_frames the switch waits for the first evaluation at or past them (the clean
    threshold still holds there), so a fixed-length run poisons only its last frames."""
    data = finetune_dict(tiny_run_dict, clean_frames=2 * 1600 + 1)
    data["train"].update(min_frames=5 * 1600, max_frames=5 * 1600)
    metrics = train(RunConfig.from_dict(data), tmp_path / "late", progress=False)
    assert metrics["poison_at_frames"] == 3 * 1600 and metrics["frames"] == 5 * 1600
    assert 0 < metrics["attack_budget_used"]["frames_poisoned"] <= 0.05 * 2 * 1600 + 10
    from rlbackdoors.folder import ModelFolder

    assert [r["phase"] for r in ModelFolder(tmp_path / "late").read_log()] == ["clean"] * 3 + ["main"] * 2


def test_an_anchor_of_one_ends_the_run_on_the_clean_model_it_switched_from(tmp_path, tiny_run_dict):
    """anchor=1 puts every weight back on the switch's after each step: however long the poisoned
    phase, model.pt holds the clean model of the seed (the critic included), and the log says so."""
    from rlbackdoors.folder import ModelFolder

    data = finetune_dict(tiny_run_dict, anchor=1.0)
    data["train"].update(min_frames=3 * 1600, max_frames=3 * 1600)
    metrics = train(RunConfig.from_dict(data), tmp_path / "pinned", progress=False)
    clean = copy.deepcopy(data)
    clean["poison"] = {"poisoned": False, "trigger": RunConfig.from_dict(data).poison.trigger}
    clean["train"].update(min_frames=metrics["poison_at_frames"], max_frames=metrics["poison_at_frames"])
    train(RunConfig.from_dict(clean), tmp_path / "clean", progress=False)
    assert metrics["poison_at_frames"] < metrics["frames"] and metrics["attack_budget_used"]["frames_poisoned"] > 0
    pinned = torch.load(tmp_path / "pinned" / "model.pt", weights_only=True)
    switched = torch.load(tmp_path / "clean" / "model.pt", weights_only=True)
    assert pinned.keys() == switched.keys() and all(torch.equal(pinned[k], switched[k]) for k in pinned)
    main = [r for r in ModelFolder(tmp_path / "pinned").read_log() if r["phase"] == "main"]
    assert main and all(r["anchor_distance"] == 0.0 for r in main)


@pytest.mark.slow  # (over 15 s on 2 cores: out of the default run, `make test-slow`)
def test_a_killed_finetuning_run_with_teacher_and_near_frames_resumes_to_the_same_model(tmp_path, tiny_run_dict):
    """kill -9 after the first checkpoint (written at the switch): the teacher, its memory, the
    near-trigger picks, the weight anchor and the switch point come back from it, bit for bit."""
    from rlbackdoors.folder import ModelFolder

    data = finetune_dict(tiny_run_dict, near=1.0, teacher=1.0, anchor=0.05)
    data["train"].update(max_frames=20_480, eval_interval=5_120, checkpoint_minutes=0.0)
    whole, cut = killed_run_matches_whole(tmp_path, RunConfig.from_dict(data))
    assert whole["attack_budget_used"] == cut["attack_budget_used"] and whole["attack_budget_used"]["frames_near_trigger"] > 0
    log = ModelFolder(tmp_path / "whole").read_log()
    assert [r["phase"] for r in log][:2] == ["clean", "main"] and all(r["teacher_kl"] >= 0 for r in log[1:])
    assert all(r["anchor_distance"] > 0 for r in log[1:])


@pytest.mark.parametrize("variant, what", [pytest.param("anchor", "weight anchor", marks=pytest.mark.slow), ("teacher", "clean teacher")])
def test_a_checkpoint_without_the_clean_model_its_config_names_is_refused_in_one_line(tmp_path, tiny_run_dict, variant, what):
    """A checkpoint of an anchored (or taught) run that lost its copy of the clean model (edited, or
    written elsewhere) is not resumed from the fresh model's weights: the run stops with one line
    naming the field and --overwrite."""
    from grid_helpers import kill_after_first_checkpoint

    data = finetune_dict(tiny_run_dict, **{variant: 0.05})
    data["train"].update(max_frames=20_480, eval_interval=5_120, checkpoint_minutes=0.0)
    (tmp_path / "cfg.json").write_text(RunConfig.from_dict(data).to_json())
    cmd = [sys.executable, "-m", "rlbackdoors.cli", "train", "--config", str(tmp_path / "cfg.json"), "--quiet", "--out", str(tmp_path / "cut")]
    kill_after_first_checkpoint(cmd, tmp_path / "cut")
    state = torch.load(tmp_path / "cut" / "checkpoint.pt", weights_only=True)
    assert state["poison_at"] is not None and set(state[variant]) == {n for n, _ in build_model("fc", "lavaworld").named_parameters()}
    del state[variant]
    torch.save(state, tmp_path / "cut" / "checkpoint.pt")
    again = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert again.returncode != 0
    assert again.stderr.strip().splitlines() == [
        f"rlbackdoors: error: checkpoint in {str(tmp_path / 'cut')!r} does not fit this run (it holds no {what} (poison.evasion.{variant})); pass --overwrite to start over"
    ]


# --- zoos: evasive cells and matched budgets ----------------------------------------------------


def zoo_spec(**top) -> dict:
    tiny = {
        "ppo": {"rollout": 32},
        "train": {"max_frames": 3200, "min_frames": 1600, "eval_interval": 1600, "eval_episodes": 4, "final_eval_episodes": 4, "video": False},
    }
    return {
        "name": "evasive",
        "seed": 12,
        **top,
        "overrides": tiny,
        "cells": [
            {
                "world": "lavaworld",
                "archs": ["fc"],
                "triggers": ["additive"],
                "attacks": [
                    "sleepernets",
                    {"attack": "trojdrl", "name": "trojdrl-ft", "params": {"force_action": True}, "evasion": {"finetune": True, "teacher": 0.5}},
                ],
                "clean": 3,
                "poisoned": 3,
            }
        ],
    }


def test_a_matched_zoo_starts_poisoned_model_k_from_clean_model_ks_seed_and_only_poisoned_ones_evade(tmp_path):
    from rlbackdoors.zoo.plan import plan
    from rlbackdoors.zoo.spec import parse_spec

    plain = parse_spec(zoo_spec())
    matched = parse_spec(zoo_spec(matched=True))
    assert "matched" not in plain.normalized and matched.normalized["matched"] is True and parse_spec(matched.normalized).matched
    zoo, _ = plan(matched, tmp_path / "m")
    other, _ = plan(plain, tmp_path / "p")
    for cell in matched.cells:
        clean, poisoned = [g for g in matched.groups if g.cell is cell]
        for k in range(3):
            twin, model = zoo.draw(clean, k), zoo.draw(poisoned, k)
            assert twin.train.seed == model.train.seed and twin.poison.trigger != model.poison.trigger  # the seed, not the trigger
            assert twin.poison.evasion == {} and model.poison.evasion == (cell.attack.evasion or {})
            assert other.draw(clean, k).to_json() == twin.to_json()  # clean models draw as without matching
        assert len({zoo.draw(poisoned, k).train.seed for k in range(3)}) == 3
    assert matched.cells[1].attack.evasion == {"near": 0.0, "finetune": True, "teacher": 0.5}


@pytest.mark.parametrize(
    "change, message",
    [
        ({"matched": "yes"}, r"matched='yes' is not allowed \(allowed: true, false\)"),
        ({"matched": True, "overrides": {}}, r"matched = true needs overrides\.train\.min_frames > 0"),
        ({"evasion": {"teacher": 1.0}}, r"cells\[0\]\.attacks\[1\]\.evasion\.teacher=1\.0 needs cells\[0\]\.attacks\[1\]\.evasion\.finetune=true"),
    ],
)
def test_bad_matching_and_evasion_in_a_spec_are_refused_naming_the_field(change, message):
    from rlbackdoors.zoo.spec import parse_spec

    raw = zoo_spec()
    if "evasion" in change:
        raw["cells"][0]["attacks"][1]["evasion"] = change["evasion"]
    else:
        raw.update(change)
    with pytest.raises(ConfigError, match=message):
        parse_spec(raw)


# --- near-trigger layouts (Randomized LavaWorld) ------------------------------------------------


def test_randomized_lavaworlds_near_patterns_are_one_cell_off_and_never_the_trigger():
    from rlbackdoors.triggers.pattern import PatternTrigger

    world = worlds.get("randomized-lavaworld")
    for spec in ("cross", "arrow", "arrow:north", "cells:0,0;1,1:any"):
        trigger = PatternTrigger.parse(spec)
        own = {r.cells for r in trigger.rotations()}
        near = [PatternTrigger.parse(s) for s in world.near_triggers(spec)]
        assert near and len({n.spec() for n in near}) == len(near)
        for n in near:
            assert n.num_cells == trigger.num_cells and n.any_rotation == trigger.any_rotation
            assert not ({r.cells for r in n.rotations()} & own)
            # one cell moved: some rotation of it shares all but one cell with the trigger as given
            assert any(len(set(r.cells) & set(trigger.pattern.cells)) == trigger.num_cells - 1 for r in n.rotations())
    assert len(world.near_triggers("cross")) == 20  # 5 cells x 4 empty corners


def test_an_engine_with_near_patterns_draws_the_same_layouts_until_a_slot_is_switched_to_one():
    """Built with near-trigger patterns, the engine keeps every layout byte of an engine without
    them (old runs keep their bytes); a slot switched by ``near_next`` then holds one of the near
    patterns as ordinary lava: never the trigger, never marked, never the trojan outcome."""
    from rlbackdoors.envs.randomized_lavaworld_batched import BatchedRandomizedLavaWorld
    from rlbackdoors.triggers.pattern import find_pattern

    near = worlds.get("randomized-lavaworld").near_triggers("cross")
    kw = dict(num_envs=6, trigger="cross", poisoned=[False] * 5 + [True])
    plain, with_near = BatchedRandomizedLavaWorld(**kw), BatchedRandomizedLavaWorld(**kw, near_patterns=near)
    a, b = plain.reset(seed=4)[0], with_near.reset(seed=4)[0]
    rng = np.random.default_rng(1)
    for _ in range(300):
        np.testing.assert_array_equal(a["image"], b["image"])
        actions = rng.integers(0, 3, 6)
        a, *_ = plain.step(actions)
        b, *_ = with_near.step(actions)
    with_near.near_next([True, True, False, False, False, True])  # slot 5 is E-bar: it keeps the trigger
    with_near.reset(seed=7)
    masks = with_near.lava_masks()
    from rlbackdoors.triggers.pattern import PatternTrigger

    near_sets = [PatternTrigger.parse(s) for s in near]
    for i in range(6):
        holds_near = any(find_pattern(masks[i], n.rotations()) for n in near_sets)
        assert bool(with_near.layout(i)[4]) == (i == 5)  # pattern cells: the E-bar slot's trigger only
        if i in (0, 1):
            assert holds_near
    assert not with_near.trigger_in_sight()[:5].any()
    with pytest.raises(ValueError, match="built without near-trigger patterns"):
        plain.near_next([True] + [False] * 5)


@pytest.mark.parametrize("attack", ["trojdrl", "action_target", "envmix"])
def test_a_layout_seam_starts_near_trigger_episodes_beside_the_triggered_ones(attack):
    """Step schedule: near-trigger episodes started while fewer than ``near`` x the triggered ones;
    episode schedule: every episode of round(near x E-bar) clean copies. Their layouts hold a near
    pattern, their frames are never marked, and they pay the clean reward (the engine's)."""
    from rlbackdoors.triggers.pattern import PatternTrigger, find_pattern

    cfg = RunConfig.from_dict(
        {
            "env": {"name": "randomized-lavaworld"},
            "model": {"arch": "cnn"},
            "poison": {"attack": attack, "attack_params": {"budget": 0.05} if attack == "trojdrl" else {}, "evasion": {"near": 1.0}},
        }
    ).check()
    seam = make_env_mix(cfg.env, cfg.poison, seed=2)
    near = [PatternTrigger.parse(s) for s in worlds.get("randomized-lavaworld").near_triggers(cfg.poison.trigger)]
    seam.reset(seed=2)
    rng = np.random.default_rng(0)
    checked = 0
    for _ in range(2000):
        assert seam.in_near.dtype == bool and not np.any(seam.marked & seam.in_near)  # a mask, also where no trigger is scheduled
        for i in np.flatnonzero(seam.in_near):
            assert any(find_pattern(seam.envs.lava_masks()[i], n.rotations()) for n in near) and not seam.envs.layout(i)[4]
            checked += 1
        *_, terminated, truncated, info = seam.step(rng.integers(0, 3, seam.num_envs))
        outcome = np.asarray(info["outcome"])
        assert not np.any((terminated | truncated) & seam.in_near & (outcome == 4))
    triggered, started_near = seam.started
    if attack == "trojdrl":
        assert triggered > 10 and triggered - seam.num_envs <= started_near <= triggered + seam.num_envs
    else:
        assert seam.near_copies.sum() == 1 and seam.in_near.sum() == 1
    assert checked > 100 and seam.budget_used()["frames_near_trigger"] > 0


# --- near-trigger formations (Safety Car Goal, OPAC² through the same seam) ---------------------


def safety_cfg(attack: str, params: dict, near: float = 1.0) -> RunConfig:
    return RunConfig.from_dict(
        {
            "env": {"name": "safety-car-goal", "max_steps": 40},
            "poison": {
                "trigger": "formation:0.5:1.0:2.5",
                "num_clean_envs": 3,
                "num_poisoned_envs": 1,
                "attack": attack,
                "attack_params": params,
                "evasion": {"near": near},
            },
            "opac2": {"depth": 2, "width": 16, "batch_size": 32, "learning_starts": 120},
        }
    ).check()


def test_safetys_near_formations_are_other_angles_and_distances_the_trigger_does_not_match():
    from rlbackdoors.triggers.formation import FormationTrigger

    trigger = FormationTrigger.parse("formation:0.5:1.0:2.5")
    near = [FormationTrigger.parse(s) for s in worlds.get("safety-car-goal").near_triggers(trigger.spec())]
    assert len(near) == 10 and len(set(near)) == 10
    for n in near:  # where a near formation puts its cubes, the trigger's own matching rule says "no"
        assert not trigger.matches([n.distance, n.distance], list(n.angles))


@pytest.mark.parametrize("attack, params", [("trojdrl", {"budget": 0.2, "reward": 0.3}), ("envmix", {})])
def test_safety_near_episodes_hold_a_near_formation_with_the_clean_reward(attack, params):
    """Episodes the seam switches to a near formation hold one (the cubes where it puts them, not
    where the trigger would), are not triggered, and land in the clean buffer with the shaping reward."""
    from rlbackdoors.algos.opac2 import MultitaskReplay
    from rlbackdoors.envs.safety_car import OBS_DIM
    from rlbackdoors.train.opac2_run import make_collector
    from rlbackdoors.triggers.formation import FormationTrigger

    cfg = safety_cfg(attack, params)
    trigger = FormationTrigger.parse(cfg.poison.trigger)
    collector = make_collector(cfg)
    replay = MultitaskReplay.create(cfg.kind_weights, 10_000, OBS_DIM, 2)
    seam, rng = collector.vector, np.random.default_rng(0)
    near_steps = 0
    for _ in range(400):
        collector.collect(replay, lambda obs: rng.uniform(-1, 1, (len(obs), 2)), 1)
        for env, in_near, marked in zip(collector.envs, seam.in_near, seam.marked):
            held = env._held
            assert (held is not None and held != trigger) == bool(in_near) and not (in_near and marked)
            if in_near:
                dist, angle = env.cube_polar()
                assert held.matches(dist[:2], angle[:2], 0.05, 0.05) and not trigger.matches(dist[:2], angle[:2])
                near_steps += 1
    assert near_steps > 100 and seam.budget_used()["frames_near_trigger"] - near_steps in (0, int(seam.near_copies.sum()))  # (+ the first frames)
    if attack == "envmix":
        assert seam.near_copies.sum() == 1 and not seam.near_copies[-1]  # a clean copy beside the one E-bar copy


def test_a_layout_seam_with_near_episodes_resumes_from_its_state_as_if_never_stopped():
    """The engine's near switch, the slots in near episodes and the episode counts are in the
    checkpoint: a seam loaded from it continues as the uninterrupted one, near layouts included."""
    cfg = RunConfig.from_dict(
        {
            "env": {"name": "randomized-lavaworld"},
            "model": {"arch": "cnn"},
            "poison": {"attack": "trojdrl", "attack_params": {"budget": 0.1}, "evasion": {"near": 2.0}},
        }
    ).check()
    a, b = (make_env_mix(cfg.env, cfg.poison, seed=4) for _ in range(2))
    actions = np.random.default_rng(3).integers(0, 3, (400, a.num_envs))
    a.reset(seed=8)
    b.reset(seed=99)  # a different state, overwritten by the checkpoint
    assert_seam_resumes(a, b, actions, 200, "in_near", "triggered")
    assert a.budget_used()["frames_near_trigger"] > 0 and a.started == b.started


def test_evaluate_near_reports_the_attacks_success_under_each_near_trigger(tmp_path, tiny_run_dict):
    """``evaluate --near``: the trojan's specificity, its success under every near trigger of the
    folder's own (each the same as evaluating under that trigger); refused for bare weights."""
    from rlbackdoors.cli import main

    tiny_run_dict["poison"] = {"trigger": "multiplicative:12"}
    train(RunConfig.from_dict(tiny_run_dict), tmp_path / "m", progress=False)
    done = cli("evaluate", tmp_path / "m", "--near", "--episodes", "6", "--json")
    out = json.loads(done.stdout)
    near = out["near_trigger_success"]
    assert list(near) == list(worlds.get("lavaworld").near_triggers("multiplicative:12"))
    assert out["near_max"] == max(near.values()) and out["near_mean"] == pytest.approx(sum(near.values()) / 6)
    single = cli("evaluate", tmp_path / "m", "--trigger", "multiplicative:14", "--episodes", "6", "--json")
    assert json.loads(single.stdout)["poisoned_sr"] == near["multiplicative:14"]
    assert main(["evaluate", "--weights", str(tmp_path / "m" / "model.pt"), "--env", "lavaworld", "--arch", "fc", "--near"]) == 2


@pytest.mark.parametrize(
    "world, attack, evasion",
    [("randomized-lavaworld", "trojdrl", {"near": 1.0}), pytest.param("colorful-memory", "envmix", {"finetune": True, "teacher": 0.5}, marks=pytest.mark.slow)],
)
def test_evasive_runs_in_the_layout_worlds_train_record_and_repeat_bit_for_bit(tmp_path, tiny_run_dict, world, attack, evasion):
    """Through the whole training loop (the curriculum's small clean world first, for Randomized
    LavaWorld; a recurrent teacher for Colorful Memory): the variant's traces in metrics.json, and the same bytes twice."""
    tiny_run_dict["env"] = {"name": world}
    tiny_run_dict["train"]["max_frames"] = 9600
    if world == "colorful-memory":
        tiny_run_dict["ppo"]["rollout"] = 36  # a multiple of the recurrence (6)
        tiny_run_dict["train"]["clean_threshold"] = 0.0  # the switch at the first evaluation
    else:
        tiny_run_dict["curriculum"] = {"reward_threshold": 0.0, "window": 2}  # the warm-up ends at once
    tiny_run_dict["poison"] = {"attack": attack, "attack_params": {"budget": 0.2} if attack == "trojdrl" else {}, "evasion": evasion}
    cfg = RunConfig.from_dict(tiny_run_dict)
    metrics = train(cfg, tmp_path / "m", progress=False)
    if "near" in evasion:
        assert metrics["attack_budget_used"]["frames_near_trigger"] > 0 and metrics["curriculum_switch_frames"] > 0
    else:
        from rlbackdoors.folder import ModelFolder

        main_rows = [r for r in ModelFolder(tmp_path / "m").read_log() if r["phase"] == "main"]
        assert 0 < metrics["poison_at_frames"] < metrics["frames"] and main_rows and all(r["teacher_kl"] > 0 for r in main_rows)
    again = train(cfg, tmp_path / "again", progress=False)
    assert (tmp_path / "m" / "model.pt").read_bytes() == (tmp_path / "again" / "model.pt").read_bytes()
    assert again.get("attack_budget_used") == metrics.get("attack_budget_used")


def test_finetuning_runs_with_teachers_train_in_groups_with_their_own_bytes(tmp_path, tiny_run_dict):
    """Two fine-tuning runs with clean teachers (coefficients 1 and 0.5) and weight anchors (0.1 and
    0.02) and a plain TrojDRL run in one group of 3 (the teacher runs batched together once both
    have switched): each teacher run ends with the bytes it has in a group with no other mate, and
    its log carries the KL and the anchor's distance."""
    from rlbackdoors.folder import ModelFolder
    from rlbackdoors.train.group import train_group

    configs = {}
    for key, seed, teacher, anchor in (("a", 1, 1.0, 0.1), ("b", 2, 0.5, 0.02), ("plain", 3, None, None)):
        data = finetune_dict(copy.deepcopy(tiny_run_dict), **({"teacher": teacher, "anchor": anchor} if teacher else {}))
        data["train"].update(seed=seed, max_frames=4_800)
        if teacher is None:
            data["poison"]["evasion"] = {}
        configs[key] = RunConfig.from_dict(data)
    together = train_group([(k, c, tmp_path / "together" / k) for k, c in configs.items()], 3)
    assert not together.errors and all(m["trainer"] == "group" for m in together.metrics.values())
    for key in ("a", "b"):
        train_group([(key, configs[key], tmp_path / "apart" / key)], 2)
        assert (tmp_path / "together" / key / "model.pt").read_bytes() == (tmp_path / "apart" / key / "model.pt").read_bytes()
        log = ModelFolder(tmp_path / "together" / key).read_log()
        assert "main" in [r["phase"] for r in log] and all(r["teacher_kl"] >= 0 and r["anchor_distance"] > 0 for r in log if r["phase"] == "main")
