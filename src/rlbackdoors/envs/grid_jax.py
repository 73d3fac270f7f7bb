"""MiniGrid's step and egocentric view as pure JAX functions: a grid world's slots stepped inside
one XLA program (the compiled trainer's rollout), exact to the numba engine
(:mod:`rlbackdoors.envs.grid_engine`).

The design is :mod:`rlbackdoors.envs.grid_device`'s (the torch device engine), made functional:
the slots' state is a pytree (:class:`Slots`) that a step takes and returns, so ``lax.scan`` can
carry it through a rollout and ``vmap`` can add an axis of agents. Nothing in a step depends on
the data's values for its shapes, and nothing returns to the host.

What stays on the host is what is sequential and rare: drawing layouts, with the numba engine's
own layout hook (``Kernels.layouts``) from each slot's own SplitMix64 stream. Before a block of
steps (a rollout) the host hands the program each slot's next ``depth`` layouts in draw order
(:class:`Layouts`, from :class:`HostLayouts`, which keeps the ones a block did not take for the
next); an autoreset takes the slot's next one. A block whose slot ended more episodes than it
was handed layouts says so (``starved``); the host then draws deeper and runs the block again
from the same state (:meth:`HostLayouts.run`), so the slots always see the layouts, in the order,
their numba engine's autoresets would draw: same state and actions, same bytes.

``Grid.process_vis`` is the torch engine's tabulated row sweep (:func:`visibility_table`), V
lookups on bit rows. Integers are int32 and rewards float32 (JAX's defaults without x64): the
reward is the numba engine's float64 ``1 - 0.9 t/T`` rounded once to float32 (a table by step
count, computed on the host, so no fused multiply-add can move it by an ulp), which is what the
compiled trainer's float32 program reads; the tests compare it so.

A world supplies its terminal rule and what it adds to a view, as functions of the slots and its
own parameters (:class:`GridWorld`), in a module beside its numba engine's. A world with per-slot
state of its own (a pattern's cells, a flag of the episode) carries it in ``Slots.world``, draws it
with each layout (``Layouts.world``, from what its ``seen`` hook writes of a fresh layout) and hands
it back (:class:`WorldState`).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any, Callable, NamedTuple

import numpy as np

from rlbackdoors.envs import grid_engine as ge
from rlbackdoors.envs.batched_base import BatchedGridEnv, EngineGroup, switchable
from rlbackdoors.envs.grid_device import draw_layouts, handed_over, pad_grid, view_offsets, visibility_table
from rlbackdoors.envs.rewards import success_reward


def _jnp():
    import jax.numpy as jnp  # JAX only where a compiled program is built

    return jnp


class Slots(NamedTuple):
    """Every slot's state (a pytree; leading axis: the slots). ``grid`` is padded with ``V - 1``
    grey walls (:func:`pad_grid`), so a view or a move reads any cell without a bounds test."""

    grid: Any  # (B, S + 2P, S + 2P, 3) uint8
    pos: Any  # (B, 2) int32
    dirs: Any  # (B,) int32
    steps: Any  # (B,) int32
    final_obs: Any  # (B, V, V, 3) uint8: the terminal view of slots that just ended
    world: Any = ()  # the world's own per-slot state (a tuple of (B, ...) arrays; GridWorld.advance)


class Layouts(NamedTuple):
    """Each slot's next ``depth`` layouts in draw order, and how many of them it has taken."""

    grid: Any  # (B, D, S, S, 3) uint8 (padded in the program as a slot takes one: a fifth of the bytes to hand over)
    pos: Any  # (B, D, 2) int32
    dirs: Any  # (B, D) int32
    view: Any  # (B, D, V, V, 3) uint8: the slot's first view of each, the world's additions in
    world: Any  # the world's own state of each (a tuple of (B, D, ...) arrays; WorldState.drawn)
    taken: Any  # (B,) int32
    starved: Any  # () bool: a slot ended more episodes than it had layouts


class StepOut(NamedTuple):
    """What a step returns, as the numba step does (reward float32, see the module doc)."""

    obs: Any  # (B, V, V, 3) uint8
    reward: Any  # (B,) float32
    terminated: Any  # (B,) bool
    truncated: Any  # (B,) bool
    outcome: Any  # (B,) int32
    steps: Any  # (B,) int32: the episode step count of the step just taken
    dirs: Any  # (B,) int32: the direction ``obs`` is seen in (a fresh layout's where a slot ended)
    sight: Any = None  # (B,) bool: ``obs`` shows the whole trigger (worlds with GridWorld.sight; None elsewhere)
    saw: Any = None  # (B,) bool: the episode's ``saw_trigger`` up to the step's view, the terminal one where it ended (worlds with GridWorld.saw)


@dataclass(frozen=True)
class GridWorld:
    """The static part of a grid world's JAX step: sizes and the tables computed on the host,
    and the world's rules. ``outcome(fwd, slots, params)``: the terminal outcome of each
    slot's last move (``fwd``: the forward cell's object before a forward move, -1 for turns);
    ``seen(img, slots, params)``: a freshly rendered view with the world's additions;
    ``advance(world, slots, seen, done, drawn, params, fresh)`` (worlds with state of their own): ``Slots.world``
    after the step, from the moved slots, their views, which ended and each slot's next layout's
    state (``drawn``: taken where ``done``; ``fresh``: that layout's agent place, direction and
    first view); ``sight(world, slots, views)`` (a layout trigger): which
    views show the whole trigger, the engine's ``trigger_in_sight`` (what an attack that poisons
    frames in sight of it marks); ``saw(world, moved, seen)`` (a world whose engine reports
    ``saw_trigger``): that flag for the moved slots' episodes, their views ``seen`` included (what an
    evaluation scores a triggered episode by); ``memory_targets(world, slots)`` (a memory world): what
    each slot's episode asks the agent to remember, the engine's ``memory_targets`` (PPO's auxiliary
    memory loss); ``widen(pairs)`` (a world whose per-slot arrays are as wide as the slot's trigger):
    ``[(params, Slots.world), ...]`` of engines with other triggers (an evaluation's clean and
    triggered conditions), each padded to the widest so that :func:`join` can stack them. ``params``
    is the world's own pytree (a trigger's tables, which slots are poisoned)."""

    size: int
    view_size: int
    max_steps: int
    see_through_walls: bool
    trojan: int  # the outcome that pays poisoned slots
    outcome: Callable
    seen: Callable
    advance: Callable | None = None
    sight: Callable | None = None
    saw: Callable | None = None
    memory_targets: Callable | None = None
    widen: Callable | None = None

    @property
    def padded(self) -> int:
        return self.size + 2 * (self.view_size - 1)

    @functools.cached_property
    def tables(self) -> dict[str, np.ndarray]:
        """The constants a step reads (numpy; they become constants of the XLA program), computed once."""
        n, sp, p = self.view_size, self.padded, self.view_size - 1
        offsets = view_offsets(n)
        table = visibility_table(n)  # re-packed: (visible << 2n) | (marked << n)
        walkable = np.zeros(256, dtype=bool)
        walkable[[ge.EMPTY, ge.UNSEEN, ge.AGENT, ge.FLOOR, ge.GOAL, ge.LAVA]] = True  # can_overlap, doors apart
        return {
            "view_cells": ((offsets[..., 0] + p) * sp + offsets[..., 1] + p).reshape(4, n * n).astype(np.int32),
            "vis": (((table >> n) << (2 * n)) | ((table & ((1 << n) - 1)) << n)).astype(np.int32),
            "walkable": walkable,
            "dir_vec": np.stack([ge.DIR_DX, ge.DIR_DY], axis=1).astype(np.int32),
            "pay": success_reward(np.arange(self.max_steps + 1), self.max_steps).astype(np.float32),
            "border": pad_grid(np.zeros((self.size, self.size, 3), np.uint8), n),  # the walls around, the grid's cells zero
        }

    def returns(self, outcomes: np.ndarray, steps: np.ndarray, poisoned: np.ndarray) -> np.ndarray:
        """Episode returns (float64, numpy) from how each ended and its length: a grid episode pays
        once, at its end, the numba engine's float64 reward (the step's float32 is that rounded), so
        an evaluation's returns are the engine's to the bit."""
        paying = np.where(np.asarray(poisoned, bool), self.trojan, ge.OUT_GOAL)
        return np.where(np.asarray(outcomes) == paying, success_reward(np.asarray(steps, np.int64), self.max_steps), 0.0)

    def view_cells(self, slots: Slots):
        """(B, V V): the padded grid's flat index of every cell of each slot's view, x-major."""
        jnp = _jnp()
        sp = self.padded
        return (slots.pos[:, 0] * sp + slots.pos[:, 1])[:, None] + jnp.asarray(self.tables["view_cells"])[slots.dirs]

    def render(self, slots: Slots, params: Any):
        """Every slot's egocentric view (B, V, V, 3) uint8, as ``gen_view`` renders it, plus the world's additions."""
        jnp = _jnp()
        t = self.tables
        b, n, sp = slots.grid.shape[0], self.view_size, self.padded
        at = self.view_cells(slots)  # (B, n * n)
        cells = jnp.take_along_axis(slots.grid.reshape(b, sp * sp, 3), at[..., None], axis=1)  # outside the grid: the walls
        if not self.see_through_walls:
            obj, state = cells[..., 0], cells[..., 2]
            behind = ((obj != ge.WALL) & ((obj != ge.DOOR) | (state == 0))).reshape(b, n, n)  # [slot, x, y]
            bits = jnp.asarray([1 << i for i in range(n)], dtype=jnp.int32)
            rows = (behind.astype(jnp.int32) * bits[None, :, None]).sum(1)  # (B, n): row y's see-behind bits over x
            vis, marks = jnp.asarray(t["vis"]), ((1 << n) - 1) << n
            entry = vis[rows[:, n - 1] | ((1 << (n // 2)) << n)]  # the agent's row: its cell visible
            entries = [entry] * n
            for y in range(n - 2, -1, -1):  # far rows last, as process_vis sweeps
                entry = vis[(entry & marks) | rows[:, y]]
                entries[y] = entry
            cols = jnp.arange(2 * n, 3 * n, dtype=jnp.int32)
            seen = (jnp.stack(entries, 1)[:, None, :] >> cols[None, :, None]) & 1  # (B, x, y)
            cells = cells * seen.reshape(b, n * n, 1).astype(jnp.uint8)
        cells = cells.reshape(b, n, n, 3)
        cells = cells.at[:, n // 2, n - 1].set(jnp.asarray([ge.EMPTY, 0, 0], dtype=jnp.uint8))  # what it carries: nothing
        return self.seen(cells, slots, params)

    def step(self, slots: Slots, layouts: Any, params: Any, actions, kind: Any = None) -> tuple[Slots, Any, StepOut]:
        """Every slot one MiniGrid action on (0 left, 1 right, 2 forward; the caller keeps them in
        range), finished slots reset in place from their next layout. ``kind`` ((B,) int32, with
        ``layouts`` a tuple of :class:`Layouts`, one queue a kind of layout): which queue each slot
        takes its next one from, where what its next episode holds is decided in the program (an
        attack's budget switching a layout trigger per episode); the queues come back in a tuple."""
        jnp = _jnp()
        t = self.tables
        p = self.view_size - 1
        acts = actions.astype(jnp.int32)
        d = slots.dirs
        ahead = slots.pos + jnp.asarray(t["dir_vec"])[d]
        index = jnp.arange(slots.grid.shape[0])
        cell = slots.grid[index, ahead[:, 0] + p, ahead[:, 1] + p]  # off the grid: the border's walls
        obj, state = cell[:, 0].astype(jnp.int32), cell[:, 2]
        walkable = jnp.asarray(t["walkable"])[obj] | ((obj == ge.DOOR) & (state == 0))
        forward = acts == 2
        pos = jnp.where((forward & walkable)[:, None], ahead, slots.pos)
        dirs = jnp.where(acts == 0, (d + 3) % 4, jnp.where(acts == 1, (d + 1) % 4, d))
        steps = slots.steps + 1
        moved = slots._replace(pos=pos, dirs=dirs, steps=steps)
        outcome = self.outcome(jnp.where(forward, obj, -1), moved, params).astype(jnp.int32)
        terminated, truncated = outcome != ge.OUT_NONE, steps >= self.max_steps
        outcome = jnp.where(truncated & ~terminated, ge.OUT_TIMEOUT, outcome)
        paying = jnp.where(params_poisoned(params), self.trojan, ge.OUT_GOAL)
        reward = jnp.where(outcome == paying, jnp.asarray(t["pay"])[steps], jnp.float32(0.0))
        done = terminated | truncated
        seen = self.render(moved, params)  # every slot's view after its move: the terminal view of those that ended
        ended = done[:, None, None, None]
        if kind is None:
            grid, nxt_pos, nxt_dirs, view, nxt_world = _next(layouts, index)
            depth = layouts.grid.shape[1]
            after = layouts._replace(taken=layouts.taken + done.astype(jnp.int32), starved=layouts.starved | jnp.any(done & (layouts.taken >= depth)))
        else:  # one queue a kind: each slot's next layout from the queue ``kind`` names, only that one taken
            entries = [_next(q, index) for q in layouts]
            grid, nxt_pos, nxt_dirs, view, nxt_world = entries[0]
            for k, entry in enumerate(entries[1:], 1):
                grid, nxt_pos, nxt_dirs, view, nxt_world = (_where(kind == k, new, old) for new, old in zip(entry, (grid, nxt_pos, nxt_dirs, view, nxt_world)))
            after = tuple(
                q._replace(
                    taken=q.taken + (done & (kind == k)).astype(jnp.int32), starved=q.starved | jnp.any(done & (kind == k) & (q.taken >= q.grid.shape[1]))
                )
                for k, q in enumerate(layouts)
            )
        s = self.size
        drawn = jnp.broadcast_to(jnp.asarray(t["border"]), slots.grid.shape).at[:, p : p + s, p : p + s].set(grid)
        world = slots.world
        if self.advance is not None:
            world = self.advance(self, moved, seen, done, nxt_world, params, (nxt_pos, nxt_dirs, view))
        fresh = Slots(
            grid=jnp.where(ended, drawn, slots.grid),
            pos=jnp.where(done[:, None], nxt_pos, pos),
            dirs=jnp.where(done, nxt_dirs, dirs),
            steps=jnp.where(done, 0, steps),
            final_obs=jnp.where(ended, seen, slots.final_obs),
            world=world,
        )
        obs = jnp.where(ended, view, seen)
        sight = self.sight(self, fresh, obs) if self.sight is not None else None
        saw = self.saw(self, moved, seen) if self.saw is not None else None
        return fresh, after, StepOut(obs, reward, terminated, truncated, outcome, steps, fresh.dirs, sight, saw)

    def rollout(self, slots: Slots, layouts: Layouts, params: Any, actions):
        """``len(actions)`` steps of :meth:`step` in one ``lax.scan``: the final state and each step's outputs, stacked."""
        import jax

        def body(carry, acts):
            s, q = carry
            s, q, out = self.step(s, q, params, acts)
            return (s, q), out

        (slots, layouts), outs = jax.lax.scan(body, (slots, layouts), actions)
        return slots, layouts, outs


def _next(layouts: Layouts, index) -> tuple:
    """Each slot's next layout of a queue: grid, agent place, direction, first view, the world's own state."""
    at = _jnp().minimum(layouts.taken, layouts.grid.shape[1] - 1)
    return layouts.grid[index, at], layouts.pos[index, at], layouts.dirs[index, at], layouts.view[index, at], tuple(a[index, at] for a in layouts.world)


def _where(mask, new, old):
    """``new`` where the slot's ``mask`` (B,) holds, else ``old``: arrays, or tuples of them, leading with the slots."""
    jnp = _jnp()
    if isinstance(new, tuple):
        return tuple(_where(mask, n, o) for n, o in zip(new, old))
    return jnp.where(mask.reshape(mask.shape + (1,) * (new.ndim - 1)), new, old)


def params_poisoned(params: Any):
    """Which slots are poisoned: every world's params carry the mask as ``poisoned``."""
    return params.poisoned


class WorldState(NamedTuple):
    """How a world's own per-slot state (``Slots.world``) crosses between its numba engines and
    the JAX step: ``names``, the engines' per-slot arrays the JAX side handles (carried, or read
    by the layouts' draws: :func:`rlbackdoors.envs.grid_device.handed_over`); ``initial(engines)``,
    the state as the engines hold it; ``drawn(outs, rows, grids)``, each drawn layout's (from the
    world's outputs of its first view, ``lead._outputs``, the slot it was drawn for and its grid);
    ``hand_back(engines, state)``, written back."""

    names: tuple[str, ...]
    initial: Callable
    drawn: Callable
    hand_back: Callable


def join(trees: list) -> Any:
    """Several hosts' pytrees of numpy arrays (Slots, Layouts, a world's params) as one, row-wise."""
    import jax

    return jax.tree_util.tree_map(lambda *a: np.concatenate(a), *trees)


class HostLayouts:
    """The host side of a JAX grid engine: the slots of reset numba engines (a
    :class:`BatchedGridEnv`, or an :class:`EngineGroup` of several), their state as a :class:`Slots`
    pytree (numpy), and their next layouts drawn ahead from their own streams.

    The engines are handed over, not shared: their streams draw the layouts and their state
    arrays are the drawing's scratch, so step them no more until :meth:`hand_back`. Layouts a block
    did not take are kept, in order, for the next; :meth:`layouts` tops each slot up to ``depth``."""

    def __init__(self, engines: BatchedGridEnv | EngineGroup, state: WorldState | None = None):
        lead, world = handed_over(engines, "a JAX engine", () if state is None else state.names)
        self.host, self.lead, self.world, self.state = engines, lead, world, state
        self.num_envs, self.size, self.view_size = engines.num_envs, lead.size, lead.view_size
        self.see_through_walls = bool(lead.see_through_walls)
        b, s, n = self.num_envs, self.size, self.view_size
        self.slots = Slots(
            grid=pad_grid(np.array(engines._grid), n),
            pos=np.array(engines._pos, dtype=np.int32),
            dirs=np.array(engines._dir, dtype=np.int32),
            steps=np.array(engines._steps, dtype=np.int32),
            final_obs=np.array(type(lead)._final_image(engines)),  # type: ignore[arg-type]  # a group carries the engines' names
            world=() if state is None else tuple(state.initial(engines)),
        )
        # the drawn layouts not yet taken: slot b's first have[b] columns, in draw order; the
        # columns of grid, position, direction, first view, the stream before the draw (to hand
        # back where a slot stopped), then the world's own state
        self._have = np.zeros(b, np.int64)
        self._store: list[np.ndarray] = [
            np.zeros((b, 0, s, s, 3), np.uint8),
            np.zeros((b, 0, 2), np.int32),
            np.zeros((b, 0), np.int32),
            np.zeros((b, 0, n, n, 3), np.uint8),
            np.zeros((b, 0), np.uint64),
            *(
                np.zeros((b, 0, *a.shape[1:]), a.dtype)
                for a in (() if state is None else state.drawn(lead._outputs(0), np.zeros(0, np.int64), np.zeros((0, s, s, 3), np.uint8)))
            ),
        ]

    def _draw(self, depth: int) -> None:
        """Draw until every slot has ``depth`` layouts waiting."""
        need = np.maximum(0, depth - self._have)
        slots = np.flatnonzero(need > 0)
        if not len(slots):
            return
        width = self._store[0].shape[1]
        if width < depth:  # room for depth layouts a slot
            grow = depth - width
            self._store = [np.concatenate([a, np.zeros((self.num_envs, grow, *a.shape[2:]), a.dtype)], axis=1) for a in self._store]
        counts = need[slots]
        grids, pos, dirs, streams, views, outs = draw_layouts(self.host, self.lead, self.see_through_walls, self.world, slots, counts)
        total = int(counts.sum())
        rows = np.repeat(slots, counts)  # the kernel's rows: slot by slot, each in draw order
        cols = np.repeat(self._have[slots] - np.cumsum(counts) + counts, counts) + np.arange(total)
        drawn = (grids, pos, dirs, np.asarray(views), streams, *(() if self.state is None else self.state.drawn(outs, rows, grids)))
        for store, values in zip(self._store, drawn, strict=True):
            store[rows, cols] = values
        self._have[slots] += counts

    def layouts(self, depth: int) -> Layouts:
        """The next ``depth`` layouts of every slot (numpy), none taken yet."""
        self._draw(depth)
        grid, pos, dirs, view, _, *world = (a[:, :depth] for a in self._store)
        return Layouts(
            grid=grid,
            pos=pos,
            dirs=dirs,
            view=view,
            world=tuple(world),
            taken=np.zeros(self.num_envs, np.int32),
            starved=np.bool_(False),
        )

    def idle(self) -> Layouts:
        """One blank layout a slot (zeros, nothing drawn): what a block reads whose slots each play
        one episode (an evaluation), where the slot an autoreset refills is no longer read."""
        zero = [np.zeros((self.num_envs, 1, *a.shape[2:]), a.dtype) for a in self._store]
        grid, pos, dirs, view, _, *world = zero
        return Layouts(grid=grid, pos=pos, dirs=dirs, view=view, world=tuple(world), taken=np.zeros(self.num_envs, np.int32), starved=np.bool_(False))

    def took(self, taken: np.ndarray) -> None:
        """Slot ``b`` took its next ``taken[b]`` layouts: drop them, keep the rest in order."""
        taken = np.asarray(taken, dtype=np.int64)
        if (taken > self._have).any() or (taken < 0).any():
            raise ValueError("a slot took more layouts than it was handed")
        width = self._store[0].shape[1]
        cols = np.minimum(taken[:, None] + np.arange(width)[None, :], max(width - 1, 0))  # past have: stale, unread
        rows = np.arange(self.num_envs)[:, None]
        self._store = [a[rows, cols] for a in self._store]
        self._have = self._have - taken

    def run(self, block: Callable[[Layouts], tuple[Any, Layouts, Any]], depth: int) -> tuple[Any, Any]:
        """Run ``block`` (a compiled function of the layouts: ``(state, layouts, result)``) with
        every slot's next ``depth`` layouts; where a slot ended more episodes than that, again from
        the same inputs with twice as many, so the result is the one an unbounded queue gives (a
        block of T steps takes at most T a slot). Returns the block's state and result; the layouts
        it took are dropped here."""
        return run_hosts([self], block, depth)[0]

    def hand_back(self, slots: Slots) -> None:
        """Write the slots' state into the host engines, as if they had stepped them: grid,
        position, direction, step count, terminal views, and each stream where the slot's next
        autoreset will draw from (before the drawn layouts it has not taken), and the world's own."""
        h, p, s = self.host, self.view_size - 1, self.size
        h._grid[:] = np.asarray(slots.grid)[:, p : p + s, p : p + s]
        h._pos[:] = np.asarray(slots.pos)
        h._dir[:] = np.asarray(slots.dirs)
        h._steps[:] = np.asarray(slots.steps)
        type(self.lead)._final_image(h)[:] = np.asarray(slots.final_obs)  # type: ignore[arg-type]  # (as above)
        if self.state is not None:
            self.state.hand_back(h, tuple(np.asarray(a) for a in slots.world))
        queued = self._have > 0  # else the host stream is already where the next draw starts
        if queued.any():  # (a host that never drew has no column to read)
            h._rng[queued] = self._store[4][queued, 0]
        self._have[:] = 0


class KindLayouts(HostLayouts):
    """A queue of one kind of layout (``kind`` "trigger": each holds the trigger; "near": a
    near-trigger pattern) beside a :class:`HostLayouts`' own, drawn by the same handed-over engine
    from streams of its own (the engine's XOR ``salt``). Why: where the program decides at each
    autoreset what a slot's next episode holds (an attack's budget switching a layout trigger per
    episode), the host cannot draw that episode ahead in the engine's one stream, whose draws
    depend on the decision; so each kind is drawn ahead in its own queue and the program takes from
    the one it decides on (``GridWorld.step``'s ``kind``). The engine's streams and switches are
    borrowed for each draw and put back, so the main queue draws as before."""

    SWITCHES = {"trigger": ("trigger_next", "triggered"), "near": ("near_next", "near")}

    def __init__(self, main: HostLayouts, kind: str, salt: int):
        if isinstance(main.host, EngineGroup):
            raise ValueError("a queue of one kind of layout draws from one engine, not an EngineGroup")
        super().__init__(main.host, main.state)
        self.kind = kind
        self.streams = np.asarray(main.host._rng, dtype=np.uint64) ^ np.uint64(salt)

    def _draw(self, depth: int) -> None:
        h = self.host
        switch, flags = self.SWITCHES[self.kind]
        own, before = h._rng.copy(), getattr(h, flags).copy()
        h._rng[:] = self.streams
        getattr(h, switch)(switchable(h))  # (a close copy stays one)
        try:
            super()._draw(depth)
        finally:
            self.streams = h._rng.copy()
            getattr(h, switch)(before)
            h._rng[:] = own

    def rewind(self) -> np.ndarray:
        """Drop the queued layouts and go back to where the first of them was drawn: the streams
        a checkpoint keeps (returned), from which the same layouts are drawn again."""
        queued = self._have > 0
        self.streams = np.where(queued, self._store[4][:, 0] if self._store[4].shape[1] else self.streams, self.streams).astype(np.uint64)
        self._have[:] = 0
        return self.streams.copy()

    def hand_back(self, slots: Slots) -> None:
        raise TypeError("a queue of one kind of layout holds no slots: rewind() it")


def run_hosts(hosts: list, block: Callable[[Any], tuple[Any, Any, Any]], depth: int, takers: int | None = None) -> tuple[tuple[Any, Any], int]:
    """:meth:`HostLayouts.run` for several hosts' slots side by side (in order, as one block's
    batch): ``((state, result), depth)``, the depth the block last ran with. Only the first
    ``takers`` hosts (default: all) drop the layouts their slots took; the rest pad a batch (a host
    may appear twice: its layouts are read, not taken, the second time). A host may be a tuple of
    them, one per kind of layout (:class:`KindLayouts`): the block then gets and returns a tuple of
    :class:`Layouts`, one per kind."""
    takers = len(hosts) if takers is None else takers
    kinds = isinstance(hosts[0], tuple)
    rows = hosts if kinds else [(h,) for h in hosts]
    while True:
        layouts = tuple(
            join([row[k].layouts(depth)._replace(starved=np.zeros(1, bool)) for row in rows])._replace(starved=np.bool_(False))  # none starved yet
            for k in range(len(rows[0]))
        )
        state, after, result = block(layouts if kinds else layouts[0])
        after = after if kinds else (after,)
        if not any(bool(np.asarray(a.starved)) for a in after):
            break
        depth *= 2
    for k, queue in enumerate(after):
        taken, start = np.asarray(queue.taken), 0
        for row in rows[:takers]:
            row[k].took(taken[start : start + row[k].num_envs])
            start += row[k].num_envs
    return (state, result), depth


__all__ = ["GridWorld", "HostLayouts", "KindLayouts", "Layouts", "Slots", "StepOut", "WorldState", "join", "run_hosts"]
