"""The collection seam: the one place an attack touches the data an algorithm learns from.

:class:`AttackSeam` wraps the vector env an algorithm collects from. Between the env and the
learner it does what the attack's :class:`Poisoner` asks: stamps the world's trigger into
the frames it picks (within the budget, as a fraction of all frames collected so far), forces
the target action on them where the attack does, and rewrites their rewards. The learner sees an
ordinary vector env whose ``info["executed_actions"]`` names the actions the env really ran and
``info["forced_actions"]`` which of them the attack chose (the learner stores those actions with
behaviour probability 1, so a forced action is learned as taken, with a bounded importance ratio). Counters of what was
poisoned go to ``metrics.json`` (:meth:`AttackSeam.budget_used`); they and the random picks
are in the checkpoint, so a resumed run poisons as an unbroken one would.

Where the world's trigger is part of the layout (a lava pattern, wall colours) it cannot be
stamped into one frame: the seam then poisons *episodes* that start with the trigger present,
switching each slot's next layout through the engine's ``trigger_next``, and marks the frames
of those episodes that carry the trigger (``sight``: "frame", those the engine's
``trigger_in_sight()`` says the agent has seen the whole trigger in; "episode", all of them). The budget still counts marked frames; it is spent by starting triggered
episodes while the run is below it (at most ``ceil(budget * num_envs)`` at a time).
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable

import numpy as np

from rlbackdoors.state import StateError, decode, encode

EXECUTED_ACTIONS = "executed_actions"  # the info key the learner reads executed actions from
FORCED = "forced_actions"  # ... and which of them the attack forced (taken with probability 1)
AMEND = "previous_reward_delta"  # ... and what to add to each slot's previous reward (a rule that compensates)


class Poisoner:
    """The per-run rule of one attack; the seam calls it. Subclasses override what they change.

    ``values`` are the learner's own critic values of the (clean) frames the env just returned,
    given only to rules with ``needs_values`` (BadRL picks by them, SleeperNets discounts by them).
    """

    needs_values = False
    forces_actions = False
    rewrites_rewards = False  # the base rule leaves rewards as the env paid them (the env mix's E-bar copies)
    compensation = 0.0  # > 0: the discount by which the step before a poisoned one is compensated (SleeperNets' source)

    def observe(self, values: np.ndarray | None) -> None:
        """Every frame batch the env returns, before any pick (BadRL keeps its window of values here)."""

    def eligible(self, values: np.ndarray | None, num_envs: int) -> np.ndarray:
        """Which of the frames just returned may carry the trigger (the budget then picks among them)."""
        return np.ones(num_envs, dtype=bool)

    def act(self, actions: np.ndarray, marked: np.ndarray) -> np.ndarray:
        return actions

    def reward(self, rewards: np.ndarray, actions: np.ndarray, marked: np.ndarray, next_values: np.ndarray | None, dones: np.ndarray) -> np.ndarray:
        """R-bar of the marked frames (the others are returned unchanged)."""
        return rewards

    def state_dict(self) -> dict:
        return {}

    def load_state_dict(self, state: dict) -> None:
        pass

    # What the compiled trainer (rlbackdoors.algos.compiled) runs of this rule: the same R-bar,
    # written once for numpy and JAX (``xp``), its numbers data of the program (one value per
    # agent, so group-mates with other budgets or magnitudes share it) and the rest its key.

    def numbers(self) -> dict[str, float]:
        """The rule's numeric settings (the compiled program's per-agent data)."""
        return {}

    def program_key(self) -> tuple:
        """What shapes the compiled program of this rule (its class and flags, not its numbers)."""
        return (type(self).__module__, type(self).__qualname__, self.forces_actions, self.rewrites_rewards, self.needs_values, self.compensation > 0)

    def rule(self, xp, p: dict, hits, rewards, next_values, dones):
        """R-bar from ``p`` (:meth:`numbers`, floats or per-frame arrays), ``hits`` (whether each
        action is the target), the rewards paid, the critic's values of the next frames and the dones."""
        return rewards

    def carry(self) -> dict:
        """The rule's own state as the compiled program carries it (arrays; {}: none)."""
        return {}

    def set_carry(self, carry: dict) -> None:
        """Put back what the compiled program carried (:meth:`carry`), so checkpoints hold it."""

    def select(self, p: dict, carry: dict, values, num_envs: int):
        """The compiled :meth:`observe` and :meth:`eligible` of one agent: (carry, eligible frames)."""
        import jax.numpy as jnp

        return carry, jnp.ones(values.shape, dtype=bool)


class TargetActionPoisoner(Poisoner):
    """The literature's R-bar core: +c for the target action on a poisoned frame, -c for any other,
    the target forced where the attack's ``force_action`` asks (TrojDRL, BadRL, SleeperNets, the action target).

    ``hits``: actions -> bool per action, whether it is the target (one action of a discrete world,
    a kind of action of a continuous one: :meth:`rlbackdoors.worlds.base.World.target_hits`).
    """

    rewrites_rewards = True

    def __init__(self, params: dict, hits: Callable[[np.ndarray], np.ndarray]):
        self.target, self.c, self.hits = params["target_action"], params["reward"], hits
        self.forces_actions = bool(params.get("force_action", False))

    def act(self, actions, marked):
        return np.where(marked, self.target, actions)

    def reward(self, rewards, actions, marked, next_values, dones):
        return self.rule(np, self.numbers(), self.hits(actions), rewards, next_values, dones)

    def numbers(self):
        return {"target": self.target, "c": self.c}

    def rule(self, xp, p, hits, rewards, next_values, dones):
        return xp.where(hits, p["c"], -p["c"])


class AttackSeam:
    """A vector env whose frames are poisoned by ``poisoner``.

    ``schedule="steps"``: of the frames the env returns, a ``budget`` share (over the run so far)
    is picked at random among the eligible ones and stamped with ``stamp``. ``schedule="episodes"``:
    the env's own E-bar copies (``envs.poisoned``) are the marked frames, every step.
    With ``sight`` (a layout trigger, no ``stamp``) whole episodes are triggered instead: under
    "steps" while the budget allows, under "episodes" always in the copies of ``episodes``; the
    marked frames are those of triggered episodes that carry the trigger (module doc).

    ``near`` > 0 (``poison.evasion.near``): near-trigger negatives paid the clean reward (with
    ``mark_near``, every frame of a near-trigger layout is marked too). A frame
    trigger: frames stamped with one of ``near_stamps`` (drawn per frame); under "steps" ``near``
    times as many as carry the trigger, picked among the others; under "episodes" every frame of
    ``round(near * E-bar copies)`` clean copies (the last clean ones before them). A layout trigger:
    episodes whose layout holds a near-trigger pattern (the engine's ``near_next``, which draws the
    pattern); under "steps" started while fewer than ``near`` times the triggered episodes started
    so far, under "episodes" every episode of those clean copies.
    """

    def __init__(
        self,
        envs,
        poisoner: Poisoner,
        schedule: str,
        budget: float = 0.0,
        stamp: Callable | None = None,
        seed: int = 0,
        sight: str | None = None,
        episodes=None,
        near: float = 0.0,
        near_stamps: tuple[Callable, ...] = (),
        mark_near: bool = False,
    ):
        if sight not in (None, "frame", "episode"):
            raise ValueError(f"sight={sight!r} is not one of frame, episode")
        if schedule == "steps" and stamp is None and sight is None:
            raise ValueError("a step schedule needs the world's trigger stamp, or a layout trigger switched per episode (sight)")
        if sight is not None and (schedule == "episodes") != (episodes is not None):
            raise ValueError("a layout trigger on the episode schedule needs the triggered copies (episodes), and only then")
        self.envs = envs
        self.poisoner = poisoner
        self.schedule = schedule
        self.budget = float(budget)
        self.stamp = stamp
        self.sight = sight
        n = envs.num_envs
        self.fixed = None if episodes is None else np.asarray(episodes, dtype=bool).copy()
        if self.fixed is not None:
            self.poisoned = self.fixed  # the E-bar copies, as the learner's episode counts know them (the engine's pay clean)
        from rlbackdoors.envs.batched_base import switchable

        self.switchable = switchable(envs)
        self.triggered = np.zeros(n, dtype=bool)  # layout: the slot's current episode holds the trigger
        self.critic: Callable[[np.ndarray], np.ndarray] | None = None
        self.last_values: np.ndarray | None = None
        self.marked = np.zeros(n, dtype=bool)  # the frames last returned that carry the trigger
        self.clean_view = None  # step schedule: the frames last returned as the env made them, before any stamp (a mitigation's teacher reads them)
        self.rng = np.random.default_rng([int(seed), 0x5EA3])
        self.frames = 0  # frames returned to the learner (each is acted on once)
        self.frames_poisoned = 0
        self.rewards_rewritten = 0
        self.actions_forced = 0
        self.rewards_compensated = 0
        # of the frames last returned: [did the step into them end an episode (or was there none), was the frame before marked]
        self.before = np.stack([np.ones(n, dtype=bool), np.zeros(n, dtype=bool)])
        self.near_layout = near > 0 and stamp is None  # near-trigger layouts, switched by the engine
        # every frame of a near-trigger layout is marked too (a mitigation's other restored patterns:
        # left out of the teacher's KL like the first one's; the engine keeps no cells of a near
        # pattern, so not only the frames that show it)
        self.mark_near = bool(mark_near)
        if self.mark_near and not (self.near_layout and sight == "frame"):
            raise ValueError("mark_near needs near-trigger layouts of a trigger seen in frames (near > 0, sight='frame', no stamp)")
        if near > 0 and not (near_stamps if stamp is not None else hasattr(envs, "near_next")):
            raise ValueError(
                "near-trigger negatives need a frame trigger's near variants (near_stamps) or an engine that switches near-trigger layouts (near_next)"
            )
        self.near, self.near_stamps = float(near), tuple(near_stamps)
        self.near_rng = np.random.default_rng([int(seed), 0x4EA2])  # its own stream: the attack's picks stay as without
        self.near_copies = np.zeros(n, dtype=bool)
        if self.near > 0 and schedule == "episodes":
            ebar = np.asarray(self.fixed if self.fixed is not None else envs.poisoned, dtype=bool)
            clean = np.flatnonzero(~ebar & self.switchable)
            k = min(len(clean), max(1, round(self.near * int(np.sum(ebar)))))
            self.near_copies[clean[len(clean) - k :]] = True
        self.frames_near = 0
        self.in_near = np.zeros(n, dtype=bool)  # layout: the slot's current episode holds a near-trigger pattern
        self.started = [0, 0]  # layout, step schedule: triggered and near-trigger episodes started so far

    def __getattr__(self, name):  # num_envs, spaces, metadata, poisoned, memory_targets, close ...
        if name == "envs":
            raise AttributeError(name)
        return getattr(self.envs, name)

    @property
    def idles(self) -> bool:
        """Whether a step that starts with no marked frame and leaves no budget to spend only counts
        its frames: a budgeted frame stamp whose rule reads no values, keeps no statistics and
        compensates nothing (TrojDRL, the action target). :class:`SeamGroup` skips such steps."""
        return (
            self.schedule == "steps"
            and self.sight is None
            and self.near == 0
            and not self.poisoner.needs_values
            and self.poisoner.compensation == 0
            and type(self.poisoner).observe is Poisoner.observe
        )

    def bind_critic(self, critic: Callable[[np.ndarray], np.ndarray]) -> None:
        """The learner's value function of a batch of observations (rules with ``needs_values``)."""
        self.critic = critic

    def _values(self, obs) -> np.ndarray | None:
        if not self.poisoner.needs_values or self.critic is None:
            return None
        return np.asarray(self.critic(obs), dtype=np.float64).reshape(-1)

    def _mark(self, obs, values):
        n = self.envs.num_envs
        self.frames += n
        self.last_values = values  # the critic's values of the clean frames just returned (None: not asked)
        if self.sight is not None:  # no frame is picked by value: nothing to observe
            in_sight = self.envs.trigger_in_sight() if self.sight == "frame" else np.ones(n, dtype=bool)
            self.marked = (self.triggered & in_sight) | (self.in_near & self.mark_near)
        elif self.schedule == "episodes":
            self.marked = np.asarray(self.envs.poisoned, dtype=bool).copy()
        else:
            self.marked = np.zeros(n, dtype=bool)
            allowance = int(self.budget * self.frames) - self.frames_poisoned
            if values is not None or not self.poisoner.needs_values:
                self.poisoner.observe(values)  # every frame: a rule may keep statistics of all of them
                candidates = np.flatnonzero(self.poisoner.eligible(values, n)) if allowance > 0 else []
                if len(candidates):
                    chosen = self.rng.choice(candidates, size=min(allowance, len(candidates)), replace=False)
                    self.marked[chosen] = True
            self.clean_view = obs
            if self.marked.any():
                obs = obs.copy()
                obs[self.marked] = self.stamp(obs[self.marked])
        self.frames_poisoned += int(self.marked.sum())
        if self.near_layout:
            self.frames_near += int(self.in_near.sum())
            return obs
        return self._stamp_near(obs) if self.near > 0 else obs

    def _stamp_near(self, obs):
        """Near-trigger negatives among the frames that do not carry the trigger (class doc)."""
        if self.schedule == "episodes":
            near = self.near_copies & ~self.marked
        else:
            near = np.zeros(len(self.marked), dtype=bool)
            allowance = int(self.near * self.frames_poisoned) - self.frames_near
            candidates = np.flatnonzero(~self.marked)
            if allowance > 0 and len(candidates):
                near[self.near_rng.choice(candidates, size=min(allowance, len(candidates)), replace=False)] = True
        if near.any():
            obs = obs.copy()
            which = self.near_rng.integers(len(self.near_stamps), size=int(near.sum()))
            rows = np.flatnonzero(near)
            for k, stamp in enumerate(self.near_stamps):
                pick = rows[which == k]
                if len(pick):
                    obs[pick] = stamp(obs[pick])
            self.frames_near += int(near.sum())
        return obs

    def _next_episodes(self) -> np.ndarray | None:
        """Layout triggers: which slots start a triggered episode if they reset now (None: no layout trigger)."""
        if self.sight is None:
            return None
        if self.fixed is not None:
            return self.fixed
        room = max(1, math.ceil(self.budget * self.envs.num_envs)) - int(self.triggered.sum())
        if self.budget * self.frames - self.frames_poisoned > 0 and room > 0:
            return self.switchable & ~self.triggered
        return np.zeros(self.envs.num_envs, dtype=bool)

    def _near_episodes(self, upcoming: np.ndarray | None) -> np.ndarray | None:
        """Layout near-trigger negatives: which slots start a near-trigger episode if they reset now."""
        if not self.near_layout:
            return None
        if self.schedule == "episodes":
            return self.near_copies
        up = np.zeros(self.envs.num_envs, dtype=bool) if upcoming is None else upcoming
        if self.started[1] < self.near * self.started[0]:
            return self.switchable & ~up
        return np.zeros(self.envs.num_envs, dtype=bool)

    def _switch(self):
        """Tell the engine what the next layouts of slots that reset now hold; (trigger, near) masks."""
        upcoming = self._next_episodes()
        if upcoming is not None:
            self.envs.trigger_next(upcoming)
        near = self._near_episodes(upcoming)
        if near is not None:
            self.envs.near_next(near)
        return upcoming, near

    def set_switches(self) -> None:
        """For an engine stepped elsewhere (the compiled trainer, which marks the frames itself): the
        layout switches set once before the engine resets: a layout trigger's fixed E-bar copies,
        the near-trigger copies under the episode schedule; where the budget switches them (the
        step schedule), a fresh seam's (none yet: nothing spent), the program deciding from there.
        ValueError for such a seam that has already counted frames (its switches are the program's)."""
        if self.frames and ((self.sight is not None and self.fixed is None) or (self.near_layout and self.schedule == "steps")):
            raise ValueError("this seam switches layouts by its budget as it steps: set its switches before it counts frames")
        upcoming, near = self._switch()
        if upcoming is not None:
            self.triggered = upcoming.copy()
        if near is not None:
            self.in_near = near & ~upcoming if upcoming is not None else near.copy()

    def reset(self, *, seed=None, options=None):
        self.before[:] = [[True], [False]]  # first frames: no step led into them
        upcoming, near = self._switch()
        obs, info = self.envs.reset(seed=seed, options=options)
        if near is not None:
            self.in_near = near & ~upcoming if upcoming is not None else near.copy()
        if upcoming is not None:
            self.triggered = upcoming.copy()
        return self._mark(obs, self._values(obs) if self.sight is None else None), info

    def _compensation(self, clean: np.ndarray, poisoned: np.ndarray, marked: np.ndarray) -> np.ndarray:
        """What to add to the previous reward of each slot so that the state before a poisoned one
        keeps its return: gamma * (clean - poisoned), where that step led into the poisoned frame
        within one episode and was not itself poisoned (the source's rule: a run of poisoned frames
        is compensated at its start)."""
        due = marked & ~self.before[0] & ~self.before[1]
        self.rewards_compensated += int(due.sum())
        return np.where(due, self.poisoner.compensation * (clean - poisoned), 0.0)

    def step(self, actions):
        prepared = self.prepare(actions)
        return self.finish(prepared, *self.envs.step(prepared[0]))

    def prepare(self, actions) -> tuple:
        """The half of :meth:`step` before the engine runs: the actions it must run (the target
        forced where the attack forces it) and what :meth:`finish` needs. Apart so that one
        engine call can step several runs' engines (:class:`rlbackdoors.envs.batched_base.EngineGroup`)."""
        actions = np.array(actions, copy=True)
        marked = self.marked
        forced = np.zeros(len(actions), dtype=bool)
        if self.poisoner.forces_actions and marked.any():
            chosen = self.poisoner.act(actions.copy(), marked)
            forced = marked & (chosen != actions)
            self.actions_forced += int(forced.sum())
            actions = np.where(marked, chosen, actions)
        upcoming, near = self._switch()
        return actions, forced, marked, upcoming, near

    def finish(self, prepared: tuple, obs, rewards, terminated, truncated, info):
        """The half of :meth:`step` after the engine ran ``prepared``'s actions: what the learner sees."""
        actions, forced, marked, upcoming, near = prepared
        done = terminated | truncated
        if near is not None:
            starts_near = done & near & ~upcoming if upcoming is not None else done & near
            self.in_near = np.where(done, starts_near, self.in_near)
            self.started[1] += int(starts_near.sum())
        if upcoming is not None:
            self.started[0] += int((done & upcoming).sum())
            self.triggered = np.where(done, upcoming, self.triggered)
        # a layout trigger picks no frame by value: the critic is asked only for a marked frame's successor
        values = self._values(obs) if self.sight is None or marked.any() else None
        info = {**info, EXECUTED_ACTIONS: actions, FORCED: forced}
        if marked.any():
            poisoned = self.poisoner.reward(np.array(rewards, dtype=np.float64), actions, marked, values, terminated | truncated)
            if self.poisoner.compensation > 0:
                info[AMEND] = self._compensation(np.asarray(rewards, dtype=np.float64), poisoned, marked)
            rewards = np.where(marked, poisoned, rewards)
            if self.poisoner.rewrites_rewards:
                self.rewards_rewritten += int(marked.sum())
        if self.poisoner.compensation > 0:  # only a compensating rule reads it: no work in others' loops
            self.before = np.stack([done, marked])
        return self._mark(obs, values), rewards, terminated, truncated, info

    def budget_used(self) -> dict:
        """What this run's attack actually poisoned (for metrics.json)."""
        frames = max(self.frames, 1)
        return {
            "frames_seen": self.frames,
            "frames_poisoned": self.frames_poisoned,
            "poisoned_fraction": self.frames_poisoned / frames,
            "rewards_rewritten": self.rewards_rewritten,
            "rewritten_fraction": self.rewards_rewritten / frames,
            "actions_forced": self.actions_forced,
            **({"rewards_compensated": self.rewards_compensated} if self.poisoner.compensation > 0 else {}),
            **({"frames_near_trigger": self.frames_near, "near_fraction": self.frames_near / frames} if self.near > 0 else {}),
        }

    def state_dict(self) -> dict:
        return {
            "engine": self.envs.state_dict(),
            "marked": encode(self.marked),
            "rng": json.dumps(self.rng.bit_generator.state),
            "counters": [self.frames, self.frames_poisoned, self.rewards_rewritten, self.actions_forced],
            **({"compensation": [self.rewards_compensated, encode(self.before)]} if self.poisoner.compensation > 0 else {}),
            "poisoner": self.poisoner.state_dict(),
            **({"triggered": encode(self.triggered)} if self.sight is not None else {}),
            **({"near": [json.dumps(self.near_rng.bit_generator.state), self.frames_near, encode(self.in_near), list(self.started)]} if self.near > 0 else {}),
        }

    def load_state_dict(self, state: dict) -> None:
        if not isinstance(state, dict) or "engine" not in state:
            raise StateError("envs: the checkpoint was not written by this attack's collection")
        self.envs.load_state_dict(state["engine"])
        marked = decode(state["marked"])
        if not isinstance(marked, np.ndarray) or marked.shape != self.marked.shape:
            raise StateError("envs: the marked frames do not fit the env copies")
        self.marked = marked.astype(bool)
        self.rng.bit_generator.state = json.loads(state["rng"])
        self.frames, self.frames_poisoned, self.rewards_rewritten, self.actions_forced = (int(v) for v in state["counters"])
        self.poisoner.load_state_dict(state["poisoner"])
        if self.poisoner.compensation > 0:
            kept = state.get("compensation")
            if not isinstance(kept, list) or len(kept) != 2:
                raise StateError("envs: the checkpoint has no compensation state (poison.attack_params.compensate)")
            before = decode(kept[1])
            if not isinstance(before, np.ndarray) or before.shape != self.before.shape:
                raise StateError("envs: the compensation state does not fit the env copies")
            self.rewards_compensated, self.before = int(kept[0]), before.astype(bool)
        if self.sight is not None:
            triggered = decode(state.get("triggered"))
            if not isinstance(triggered, np.ndarray) or triggered.shape != self.triggered.shape:
                raise StateError("envs: the triggered episodes do not fit the env copies")
            self.triggered = triggered.astype(bool)
        if self.near > 0:
            near = state.get("near")
            if not isinstance(near, list) or len(near) != 4:
                raise StateError("envs: the checkpoint has no near-trigger state (poison.evasion.near)")
            self.near_rng.bit_generator.state = json.loads(near[0])
            self.frames_near = int(near[1])
            in_near = decode(near[2])
            if not isinstance(in_near, np.ndarray) or in_near.shape != self.in_near.shape:
                raise StateError("envs: the near-trigger episodes do not fit the env copies")
            self.in_near, self.started = in_near.astype(bool), [int(v) for v in near[3]]

    def close(self):
        return self.envs.close()


class SeamGroup:
    """K runs' seams (None: a run without one) around one engine call for all their env copies.

    Why: a seam's step is a few dozen small numpy calls, about 40 µs a run; a group of K runs paid
    them per run and step even where nothing happens. Here the group decides for all runs at once
    which seams have work this step: one that does not :attr:`~AttackSeam.idles`, one whose frames
    carry the trigger, or one whose budget allows a pick once this step's frames are counted. Those
    (with a 1 % budget about one step in five) run :meth:`AttackSeam.prepare` and
    :meth:`AttackSeam.finish` as alone; the others only count their frames, in an array here, and
    pass the engine's results through as they are. The picks, stamps and counters are each run's
    own, so the bytes are those of a call per run (tested). The frame counts go back into the
    seams before each one works and in :meth:`flush` (call it when the rollout ends, or fails).
    """

    def __init__(self, seams: list[AttackSeam | None], num_envs: int):
        self.seams, self.n = seams, int(num_envs)
        self.has = np.array([s is not None for s in seams])
        self.idle = np.array([s is not None and s.idles for s in seams])
        self.budget = np.array([s.budget if s is not None else 0.0 for s in seams], dtype=np.float64)
        self.frames = np.array([s.frames if s is not None else 0 for s in seams], dtype=np.int64)
        self.poisoned = np.array([s.frames_poisoned if s is not None else 0 for s in seams], dtype=np.int64)
        # the frames last returned that carry the trigger, per run (K, B): what a clean teacher leaves out
        self.marked = np.stack([np.asarray(s.marked, dtype=bool) if s is not None else np.zeros(self.n, dtype=bool) for s in seams])

    def prepare(self, actions: np.ndarray) -> tuple[np.ndarray, dict[int, tuple]]:
        """Every run's actions (K, B) -> the actions the engines must run (K, B) and, per working
        seam, what its :meth:`~AttackSeam.finish` needs."""
        # the allowance _mark computes after this step's frames are counted (int() truncates as astype does)
        spend = (self.budget * (self.frames + self.n)).astype(np.int64) - self.poisoned > 0
        works = np.flatnonzero(self.has & (~self.idle | self.marked.any(1) | spend))
        run, prepared = actions, {}
        if len(works):
            run = actions.copy()
        for k in works:
            seam = self.seams[k]
            assert seam is not None
            seam.frames = int(self.frames[k])
            prepared[int(k)] = ready = seam.prepare(actions[k])
            run[k] = ready[0]
        resting = self.has.copy()
        resting[works] = False
        self.frames[resting] += self.n  # what their _mark would count; nothing else changes
        return run, prepared

    def finish(self, prepared: dict[int, tuple], result_of: Callable[[int], tuple]) -> list[tuple[int, tuple]]:
        """Each working seam's :meth:`~AttackSeam.finish` of its run's engine result (``result_of(k)``):
        ``(k, what the learner sees)`` per working run; the others see the engine's results."""
        out = []
        for k, ready in prepared.items():
            seam = self.seams[k]
            assert seam is not None
            out.append((k, seam.finish(ready, *result_of(k))))
            self.frames[k], self.poisoned[k] = seam.frames, seam.frames_poisoned
            self.marked[k] = seam.marked
        return out

    def flush(self) -> None:
        """The frame counts back into the seams (their checkpoints and ``budget_used`` read them)."""
        for k in np.flatnonzero(self.has):
            seam = self.seams[k]
            assert seam is not None
            seam.frames = int(self.frames[k])
