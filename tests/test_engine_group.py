"""One engine call for a training group's env copies (issue 55): K engines of one grid world
(LavaWorld, Randomized LavaWorld, Colorful Memory) stepped as one
(:class:`rlbackdoors.envs.batched_base.EngineGroup`) give every slot exactly what its own engine
gives, and a group's rollouts are the same bytes with one call a step as with one per agent."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from rlbackdoors.algos import group
from rlbackdoors.envs.batched_base import EngineGroup, ThreadChoice, thread_choices
from rlbackdoors.envs.colorful_memory_batched import BatchedColorfulMemory
from rlbackdoors.envs.lavaworld_batched import BatchedLavaWorld
from rlbackdoors.envs.randomized_lavaworld_batched import BatchedRandomizedLavaWorld
from rlbackdoors.triggers.pattern import as_pattern_trigger, near_patterns
from test_group import learner, with_teachers


def same(a, b) -> bool:
    """Equal observations (arrays or CPU tensors, or dicts of them)."""
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)
    return np.array_equal(a, b)


def step_beside_twins(engines: list, seed: int, steps: int = 600, switch=None, watch=None, parallel: bool | int = False) -> int:
    """Reset ``engines`` (seeds apart), step them as one group and deep copies of them one engine
    at a time with the same random actions for ``steps`` steps, asserting after every step that
    each slot's observation, reward, ends and info, each engine's terminal views and its answers to
    ``watch(engine)`` are its twin's, and at the end that every per-slot array is. ``switch(step,
    pairs, rng)`` may flip per-episode switches on each (engine, twin) pair. ``parallel``: the group
    steps over numba's threads where they are faster (True: timed, batched_base.ThreadChoice), or
    over that many (the twins never do). Returns the episodes ended."""
    for k, e in enumerate(engines):
        e.reset(seed=seed + k)
    twins = copy.deepcopy(engines)
    together = EngineGroup.of(engines, parallel=parallel)
    assert together is not None and together.parallel == parallel
    rng = np.random.default_rng(seed)
    ended = 0
    for t in range(steps):
        if switch is not None:
            switch(t, list(zip(engines, twins)), rng)
        actions = [rng.integers(0, 3, e.num_envs) for e in engines]
        obs, reward, terminated, truncated, info = together.step(np.concatenate(actions))
        first = 0
        for k, twin in enumerate(twins):
            view = together.result(k, obs, reward, terminated, truncated, info)[0]
            o, r, te, tr, inf = twin.step(actions[k])
            rows = slice(first, first + twin.num_envs)
            first = rows.stop
            assert same(o, view) and np.array_equal(r, reward[rows]), t
            assert np.array_equal(te, terminated[rows]) and np.array_equal(tr, truncated[rows])
            assert inf.keys() == info.keys() and all(np.array_equal(inf[key], info[key][rows]) for key in inf)
            assert same(twin.final_obs, engines[k].final_obs)
            assert watch is None or all(np.array_equal(a, b) for a, b in zip(watch(twin), watch(engines[k])))
        ended += int((terminated | truncated).sum())
    for engine, twin in zip(engines, twins):  # the engines stay whole: their own state is the group's
        assert same(engine.observe(), twin.observe())
        assert all(np.array_equal(getattr(engine, name), getattr(twin, name)) for name in engine._slot_arrays())
    return ended


# (timed: 25 s on 2 cores, each way of the parallel kernel compiled and timed; the choice has its
# own tests below, the kernel "two numba threads": make test-slow)
@pytest.mark.parametrize("parallel", [False, pytest.param(True, marks=pytest.mark.slow), 2], ids=["one thread", "timed", "two numba threads"])
def test_one_call_steps_every_slot_as_its_own_engine_would(parallel):
    """Three LavaWorld engines (three triggers, clean and poisoned slots), 600 random steps
    (hundreds of autoresets): every slot as in its own engine (:func:`step_beside_twins`)."""
    engines = [BatchedLavaWorld(5, trigger=t, poisoned=[i % 2 == 0 for i in range(5)]) for t in ("multiplicative:12", "additive:60", "additive:135")]
    assert step_beside_twins(engines, 100, parallel=parallel) > 100


# (numba threads: 13-18 s, the world's parallel kernel compiled, never cached; the same kernel
# template as LavaWorld's, whose threads stay in the default run: make test-slow)
@pytest.mark.parametrize("parallel", [False, pytest.param(True, marks=pytest.mark.slow)], ids=["one thread", "numba threads"])
def test_one_call_steps_randomized_lavaworld_slots_as_their_own_engines_would(parallel):
    """A layout-trigger world: a clean engine, one with the cross (some slots paying R-bar), one
    with an arrow and near-trigger patterns: each slot draws its layouts from its own engine's
    placement tables. The per-episode switches (``trigger_next``, ``near_next``) are flipped on
    the engines as attacks do; dict observations and the trigger flags of info are compared too."""
    engines = [
        BatchedRandomizedLavaWorld(4),
        BatchedRandomizedLavaWorld(4, trigger=as_pattern_trigger("cross"), poisoned=[True, False, True, False]),
        BatchedRandomizedLavaWorld(4, trigger="arrow:east", poisoned=[False] * 4, near_patterns=near_patterns(as_pattern_trigger("arrow:east"))[:3]),
    ]
    patterned = []

    def switch(t, pairs, rng):
        patterned.append(int(engines[1]._pcount.astype(bool).sum()))
        if t % 7 == 0:  # read at the next (auto)reset, on the engine as on its twin
            flips = rng.random(4) < 0.5
            for e in (*pairs[1], *pairs[2]):
                e.trigger_next(e.poisoned | flips)
            for e in pairs[2]:
                e.near_next(~flips)

    assert step_beside_twins(engines, 50, switch=switch, parallel=parallel) > 50 and sum(patterned) > 0


@pytest.mark.parametrize("parallel", [False, pytest.param(True, marks=pytest.mark.slow)], ids=["one thread", "numba threads"])  # (as above)
def test_one_call_steps_colorful_memory_slots_as_their_own_engines_would(parallel):
    """Wall-colour triggers of 3 and 9 squares and a clean engine (none): each slot paints and
    tracks its own engine's squares (the group's record of shown squares is padded to the most;
    each engine's is a view of its rows), with ``trigger_next`` flips; which squares each episode
    has shown and the memory targets are compared too."""
    engines = [
        BatchedColorfulMemory(4),
        BatchedColorfulMemory(4, trigger="room:purple,yellow,red", close_to_trigger=[False, True, False, False], poisoned=[True, False, False, False]),
        BatchedColorfulMemory(4, trigger="end:red,green,blue,purple,yellow,grey,red,green,blue", poisoned=[False, True, False, True]),
    ]
    shown = []

    def switch(t, pairs, rng):
        shown.append(int(engines[2]._seen.sum()))
        if t % 5 == 0:
            flips = rng.random(4) < 0.5
            for e in (*pairs[1], *pairs[2]):
                e.trigger_next(e.poisoned | (flips & ~e.close_to_trigger))

    def watch(engine):
        return engine.trigger_in_sight(), engine.memory_targets(), engine._seen

    assert step_beside_twins(engines, 70, switch=switch, watch=watch, parallel=parallel) > 20 and sum(shown) > 0


def test_engines_that_cannot_share_a_call_are_stepped_one_by_one():
    plain = BatchedLavaWorld(3)
    plain.reset(seed=0)
    other_size = BatchedLavaWorld(3, size=11)
    other_size.reset(seed=1)
    assert EngineGroup.of([plain, other_size]) is None  # other settings
    assert EngineGroup.of([plain, BatchedLavaWorld(3)]) is None  # one not reset yet
    fewer = BatchedRandomizedLavaWorld(3, num_lava=6)
    fewer.reset(seed=2)
    more = BatchedRandomizedLavaWorld(3)
    more.reset(seed=3)
    assert EngineGroup.of([more, fewer]) is None  # the world refuses: other lava counts
    assert not np.shares_memory(more._grid, fewer._grid)  # each engine has arrays of its own again


ATTACKS = {
    "env mix": [None, {"trigger": "multiplicative:12"}, {"trigger": "additive:135"}],
    # a layout-trigger world (dict observations): the env mix, an episode-scheduled attack and the
    # near-trigger evasive variant beside a clean run
    "randomized lavaworld": [
        None,
        {"trigger": "cross"},
        {"trigger": "cross", "attack": "trojdrl", "attack_params": {"budget": 0.2}},
        {"trigger": "arrow:east", "attack": "action_target"},
        {"trigger": "cross", "evasion": {"near": 1.0}},
    ],
    # a recurrent world with the auxiliary memory targets, read from the engines between calls
    "colorful memory": [
        None,
        {"trigger": "end:red,green,blue,purple,yellow,grey,red,green,blue"},
        {"trigger": "room:purple,yellow,red", "attack": "trojdrl", "attack_params": {"budget": 0.2}},
    ],
    # fine-tuning under clean teachers: the seams' marks (which frames carry the trigger) read between calls
    "teachers": [{"attack": "trojdrl", "attack_params": {"budget": 0.3}}, {"trigger": "additive:90", "attack": "badrl", "attack_params": {"budget": 0.2}}],
    # through the attacks' seams: a forced target, a critic's picks, a compensated reward, and a
    # 1 % budget, whose seam has nothing to do in most steps (one call: the group skips them)
    "seams": [
        {"trigger": "additive:60", "attack": "trojdrl", "attack_params": {"budget": 0.2, "force_action": True}},
        {"trigger": "additive:135", "attack": "trojdrl", "attack_params": {"budget": 0.01, "force_action": True}},
        {"trigger": "multiplicative:14", "attack": "badrl", "attack_params": {"budget": 0.2}},
        {"trigger": "additive:90", "attack": "sleepernets", "attack_params": {"budget": 0.2}},
        None,
    ],
}


@pytest.mark.parametrize("kind", list(ATTACKS))
def test_a_groups_rollouts_are_the_same_bytes_with_one_engine_call(kind):
    """Learners collect twice from the same state, once with one engine call a step and once with
    a call per agent: identical rollouts and next observations. The env mix's bare engines, and
    the literature's attacks, whose seams prepare the actions before the call and finish after it
    (forced actions, rewritten and compensated rewards, stamped frames), in the three grid worlds;
    a recurrent learner's memories and auxiliary memory targets, and clean teachers' log-probabilities
    and untriggered masks, read from the engines and seams between calls."""
    world = {"randomized lavaworld": "randomized-lavaworld", "colorful memory": "colorful-memory"}.get(kind, "lavaworld")
    one = [learner(world, None if world == "colorful-memory" else "fc", k, spec) for k, spec in enumerate(ATTACKS[kind])]
    if kind == "teachers":
        one = with_teachers(one, [0.5, 1.0])
    for ppo, envs, _ in one:
        if hasattr(envs, "bind_critic"):  # BadRL and SleeperNets ask the learner's critic
            envs.bind_critic(lambda o, model=ppo.model: model(torch.from_numpy(o))[1].detach().float().numpy())
    each = copy.deepcopy(one)
    assert EngineGroup.of([getattr(e, "envs", e) for _, e, _ in one]) is not None
    for _ in range(2):
        a = group.collect([p for p, _, _ in one], [e for _, e, _ in one], [o for _, _, o in one])
        b = group.collect([p for p, _, _ in each], [e for _, e, _ in each], [o for _, _, o in each], one_call=False)
        for k, ((ra, oa), (rb, ob)) in enumerate(zip(a, b)):
            assert same(ra.obs, rb.obs), k
            for name in ("actions", "logprobs", "values", "advantages", "returns"):
                assert torch.equal(getattr(ra, name), getattr(rb, name)), (k, name)
            for name in ("rewards", "dones", "outcomes", "steps"):
                assert np.array_equal(getattr(ra, name), getattr(rb, name)), (k, name)
            for name in ("memories", "masks", "memory_targets", "teacher_logp", "untriggered"):  # where the run has them
                assert (getattr(ra, name, None) is None) == (getattr(rb, name, None) is None), (k, name)
                assert getattr(ra, name, None) is None or torch.equal(getattr(ra, name), getattr(rb, name)), (k, name)
            assert same(oa, ob)
            one[k], each[k] = (one[k][0], one[k][1], oa), (each[k][0], each[k][1], ob)
    assert any(r.dones.any() for r, _ in a)  # episodes ended (autoresets inside the call)
    if kind == "seams":
        assert any(r.rewards.min() < 0 for r, _ in a)  # rewritten rewards (the target's -c) reached the rollouts
    if kind == "colorful memory":
        assert all(r.memory_targets is not None and r.memories is not None for r, _ in a)
    if kind == "teachers":
        assert all(r.teacher_logp is not None for r, _ in a) and any(not r.untriggered.all() for r, _ in a)  # marked frames reached the rollouts


def test_a_parallel_group_steps_the_way_it_timed_fastest_and_times_again():
    """``EngineGroup.of(..., parallel=True)`` (a GPU group's engines) steps its slots serially or
    over numba's threads as :class:`ThreadChoice` timed them on this host: every way 3 times in
    turn, then the fastest median of each way's last 3 calls, the others timed again every
    ``reprobe`` calls, so a way that became slow (the host got busy) is left. Synthetic timings
    here (the choice's arithmetic); the kernels' bytes are the same every way (above)."""
    choice = ThreadChoice(trials=3, reprobe=10, most=8)
    assert choice.ways == [0, 2, 4, 8]
    cost = {0: 1.0, 2: 0.5, 4: 0.3, 8: 2.0}
    seen = []
    for call in range(40):
        if call == 25:
            cost[4] = 5.0  # four threads slowed down (another process on their cores)
        way = choice.next()
        seen.append(way)
        choice.record(way, cost[way])
    assert seen[:12] == [0, 2, 4, 8] * 3 and seen[12:20] == [4] * 8  # timed in turn, then the fastest
    assert seen[20:23] == [0, 2, 8]  # at call 20 the others timed once more; four still the fastest
    assert seen[23:26] == [4] * 3 and seen[-1] == 2  # its last three calls' median rose past two threads'
    assert choice.describe() == {"chosen": 2, "median_ms": {0: 1000.0, 2: 500.0, 4: 5000.0, 8: 2000.0}}


def test_the_engine_threads_can_be_fixed_and_a_bad_count_is_refused_in_one_line(monkeypatch):
    """``RLBACKDOORS_ENGINE_THREADS`` fixes the way (0: the serial kernel), nothing timed; a
    count the host lacks, or not a count, is refused naming the variable and the allowed range."""
    monkeypatch.setenv("RLBACKDOORS_ENGINE_THREADS", "0")
    fixed = ThreadChoice(most=4)
    assert fixed.ways == [0] and fixed.next() == 0 and fixed.chosen == 0
    for bad in ("5", "two", "-1"):
        monkeypatch.setenv("RLBACKDOORS_ENGINE_THREADS", bad)
        with pytest.raises(ValueError) as err:
            ThreadChoice(most=4)
        assert str(err.value) == f"RLBACKDOORS_ENGINE_THREADS={bad!r}: expected 0 (one serial call) to 4 (numba's threads on this host)"


def test_a_timed_group_records_its_choice_for_the_process():
    """A parallel group's engines time their ways on first use, once a process per world and slot
    count (a training group builds a new EngineGroup each rollout), and the choice is listed."""
    engines = [BatchedLavaWorld(5, trigger=t, poisoned=[i % 2 == 0 for i in range(5)]) for t in ("multiplicative:12", "additive:60", "additive:135")]
    for k, e in enumerate(engines):
        e.reset(seed=k)
    together = EngineGroup.of(engines, parallel=True)
    assert together is not None
    rng = np.random.default_rng(0)
    for _ in range(40):
        together.step(rng.integers(0, 3, together.total))
    made = thread_choices()["BatchedLavaWorld/15"]
    assert made["chosen"] in made["median_ms"] and set(made["median_ms"]) == set(ThreadChoice().ways)
