"""MiniGrid's step and egocentric view as batched torch tensor ops: a grid world's slots stepped on
the device the learners run on, exact to the numba engine (:mod:`rlbackdoors.envs.grid_engine`).

Issue 55 asks whether a GPU group is better fed by the numba engines over the host's cores or by
an engine on the device, measured on the same work; this is the device side
(``benchmarks/engine_threads.py --device``). The state lives in tensors (grid, position,
direction, step count, which slots are poisoned); a step is a fixed sequence of tensor ops over
all slots, with no Python per slot and no host round trip, so it can be captured or compiled.

What stays on the host is what is sequential and rare: drawing layouts. For a world whose
layouts depend only on the slot's own SplitMix64 stream (not on the episode before), the host
draws each slot's next ``refill_every`` layouts ahead, with the numba engine's own layout hook
(``Kernels.layouts``), into a queue on the device, each with the slot's first view of it (so a
step renders one view, not also the fresh episode's); an autoreset takes the slot's next one. Every
``refill_every`` steps one small copy tops the queues up (a slot takes at most one layout a
step). The slots therefore see the layouts, in the order, their numba engine's autoresets would
draw: same state and actions, same bytes (each world's device engine is tested against its numba
engine). The host's streams run ahead of the slots by the queued layouts.

``Grid.process_vis`` is a sweep over the view's rows (far from the agent last), each row swept
right then left, whose outcome for a row is a function of the row's visibility on entry and of
which of its cells can be seen behind: 2**V x 2**V cases, tabulated once from the literal loop
(:func:`visibility_table`), so a view's occlusion is V table lookups on bit rows.

A world supplies its terminal rule (:meth:`DeviceGridGroup._outcome`) and what it adds to a
view (:meth:`DeviceGridGroup._seen`), in a module beside its numba engine's.
"""

from __future__ import annotations

import functools
import importlib

import numpy as np
import torch

from rlbackdoors.envs import grid_engine as ge
from rlbackdoors.envs.batched_base import ACTIONS_DOC, BatchedGridEnv, EngineGroup
from rlbackdoors.envs.rewards import success_reward


@functools.cache  # a Python loop of some 50 ms: once a process, not once a rollout's engine
def visibility_table(n: int) -> np.ndarray:
    """``Grid.process_vis`` for one row, tabulated: entry ``(m << n) | s`` (``m``: the row's visible
    cells on entry, ``s``: its cells one can see behind, bit ``i`` for column ``i``) holds
    ``(visible << n) | marked``: the row's visible cells after its two sweeps, and the cells of
    the next row (one nearer the view's top) the sweeps mark visible. The loop is
    :func:`rlbackdoors.envs.grid_engine.process_vis`'s, row by row."""
    table = np.zeros(1 << (2 * n), dtype=np.int64)
    for m in range(1 << n):
        for s in range(1 << n):
            vis = [bool(m >> i & 1) for i in range(n)]
            see = [bool(s >> i & 1) for i in range(n)]
            nxt = [False] * n
            for i in range(n - 1):
                if vis[i] and see[i]:
                    vis[i + 1] = nxt[i + 1] = nxt[i] = True
            for i in range(n - 1, 0, -1):
                if vis[i] and see[i]:
                    vis[i - 1] = nxt[i - 1] = nxt[i] = True
            table[(m << n) | s] = (sum(1 << i for i in range(n) if vis[i]) << n) | sum(1 << i for i in range(n) if nxt[i])
    table.flags.writeable = False  # shared by every caller
    return table


def view_offsets(n: int) -> np.ndarray:
    """(4, n, n, 2): the world offset of view cell ``(x, y)`` from the agent, per direction
    (``gen_view``'s closed form: ``ahead * dir + lateral * right``)."""
    out = np.zeros((4, n, n, 2), dtype=np.int64)
    for d in range(4):
        dx, dy = int(ge.DIR_DX[d]), int(ge.DIR_DY[d])
        for x in range(n):
            for y in range(n):
                ahead, lat = n - 1 - y, x - n // 2
                out[d, x, y] = (ahead * dx - lat * dy, ahead * dy + lat * dx)
    return out


def pad_grid(grid: np.ndarray, view_size: int) -> np.ndarray:
    """Grids (..., S, S, 3) with a border of ``view_size - 1`` grey walls, what ``Grid.slice``
    shows outside the grid: a view (at most V - 1 cells ahead) and a move then read any cell
    without a bounds test."""
    p = view_size - 1
    out = np.empty((*grid.shape[:-3], grid.shape[-3] + 2 * p, grid.shape[-2] + 2 * p, 3), dtype=np.uint8)
    out[...] = np.array([ge.WALL, ge.GREY, 0], dtype=np.uint8)
    out[..., p : p + grid.shape[-3], p : p + grid.shape[-2], :] = grid
    return out


HELD = ("_grid", "_pos", "_dir", "_steps", "_rng")  # the per-slot state a device engine steps and hands back
StepResult = tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]
GRAPH_STATE = ("grid", "pos", "dirs", "steps", "final_obs", "_head")  # what a step reassigns: static under a CUDA graph


def draw_layouts(host, lead: BatchedGridEnv, see_through_walls: bool, world: tuple, slots: np.ndarray, counts: np.ndarray) -> tuple:
    """The next ``counts[k]`` layouts of slot ``slots[k]`` of handed-over engines (``host``: an engine
    or an :class:`EngineGroup`), from the slots' own streams (``Kernels.layouts``): grids, agent
    places, directions, each stream before its draw, the first views and the world's outputs of
    them (``lead._outputs``: what the world's ``seen`` hook writes of a fresh layout), slot by slot in
    draw order."""
    total, s = int(counts.sum()), lead.size
    grids, pos, dirs = np.empty((total, s, s, 3), np.uint8), np.empty((total, 2), np.int64), np.empty(total, np.int64)
    streams, views, outs = np.empty(total, np.uint64), lead._images(total), lead._outputs(total)
    bad = lead._kernels.layouts(
        host._grid,
        host._pos,
        host._dir,
        host._steps,
        host._rng,
        see_through_walls,
        world,
        slots,
        counts,
        grids,
        pos,
        dirs,
        streams,
        views,
        outs,
    )
    if bad >= 0:
        raise lead._layout_error(None)
    return grids, pos, dirs, streams, views, outs


def handed_over(engines: BatchedGridEnv | EngineGroup, to: str, held: tuple[str, ...] = ()) -> tuple[BatchedGridEnv, tuple]:
    """The lead engine and the hooks' ``world`` of reset engines handed to an engine elsewhere
    (``to``: the device, a JAX engine), which steps the state in :data:`HELD` and the world's own
    per-slot arrays ``held``; ValueError (one line) for engines not reset, with per-slot state it
    does not step, or that cannot share a call."""
    lead = engines.lead if isinstance(engines, EngineGroup) else engines
    if not getattr(lead, "_has_reset", True):
        raise ValueError(f"reset the engines before handing them to {to}")
    extra = set(lead._slot_arrays()) - set(HELD) - set(held)
    if extra:
        raise ValueError(f"{type(lead).__name__} keeps per-slot state {to} does not step: {sorted(extra)}")
    world = engines.world if isinstance(engines, EngineGroup) else lead._world()
    if world is None:
        raise ValueError("these engines cannot share a call (EngineGroup.of says None)")
    return lead, world


def device_engine_for(engines: BatchedGridEnv | EngineGroup, device: str | torch.device, graph: bool = False) -> DeviceGridGroup | None:
    """The world's device engine over ``engines``' slots (:attr:`BatchedGridEnv.device_engine`;
    ``graph``: its step as one CUDA graph), or None where the world has none."""
    lead = engines.lead if isinstance(engines, EngineGroup) else engines
    if lead.device_engine is None:
        return None
    module, _, name = lead.device_engine.partition(":")
    return getattr(importlib.import_module(module), name)(engines, device, graph=graph)


class DeviceGridGroup:
    """The slots of a numba engine, or of an :class:`EngineGroup` of several, stepped on ``device``.

    Built from engines that have been reset: their state is copied over, and from then on this
    object steps the slots. The engines are handed over, not shared: their streams draw the queued
    layouts and their state arrays are the drawing's scratch, so step them no more until
    :meth:`hand_back` gives them the slots' state again. :meth:`step` takes int64 actions on the
    device and returns tensors on it: observations, rewards, terminations, truncations, outcomes
    and episode steps, as the numba step returns them; :attr:`final_obs` holds the terminal views
    of the slots that just ended. ``graph``: the step as one CUDA graph (:meth:`_graphed`).
    """

    def __init__(self, engines: BatchedGridEnv | EngineGroup, device: str | torch.device = "cpu", refill_every: int = 8, graph: bool = False):
        lead, world = handed_over(engines, "the device")
        if refill_every < 1:
            raise ValueError(f"refill_every must be >= 1, got {refill_every}")
        self.host, self.lead = engines, lead
        self.world: tuple = world
        self.device = torch.device(device)
        self.num_envs, self.size, self.view_size = engines.num_envs, lead.size, lead.view_size
        self.max_steps, self.see_through_walls = int(lead.max_steps), bool(lead.see_through_walls)
        self.refill_every = int(refill_every)
        if graph and self.device.type != "cuda":
            raise ValueError(f"graph=True needs a CUDA device, not {self.device}")
        self._run = self._graphed if graph else self._advance  # the graph is captured at the first step
        dev = self.device

        def put(a: np.ndarray) -> torch.Tensor:  # a copy, also on the CPU (the host arrays become scratch)
            return torch.from_numpy(np.array(a)).to(dev)

        self.grid = put(pad_grid(engines._grid, self.view_size))  # (B, S + 2P, S + 2P, 3): P = V - 1 cells of wall around
        self.pos, self.dirs, self.steps = put(engines._pos), put(engines._dir), put(engines._steps)
        self.poisoned = put(engines.poisoned)
        self.final_obs = put(np.asarray(engines.final_obs))
        n, b = self.view_size, self.num_envs
        self._slots = torch.arange(b, device=dev)
        # each direction's view cells as flat offsets into the padded grid (from the agent's flat cell)
        sp, p = self.grid.shape[1], n - 1
        offsets = view_offsets(n)
        self._view_cells = put(((offsets[..., 0] + p) * sp + offsets[..., 1] + p).reshape(4, n * n))
        table = visibility_table(n)  # re-packed: (visible << 2n) | (marked << n)
        self._vis = put(((table >> n) << (2 * n)) | ((table & ((1 << n) - 1)) << n))
        self._marks = ((1 << n) - 1) << n
        self._cols = torch.arange(2 * n, 3 * n, device=dev)  # a visible bit's place in an entry
        walkable = np.zeros(256, dtype=bool)
        walkable[[ge.EMPTY, ge.UNSEEN, ge.AGENT, ge.FLOOR, ge.GOAL, ge.LAVA]] = True  # can_overlap, doors apart
        self._walkable = put(walkable)
        self._bits = torch.tensor([1 << i for i in range(n)], device=dev)
        self._empty = torch.tensor([ge.EMPTY, 0, 0], dtype=torch.uint8, device=dev)
        self._dir_vec = put(np.stack([ge.DIR_DX, ge.DIR_DY], axis=1))
        # the paying reward by step count, computed on the host: a GPU kernel may fuse the product
        # and difference of 1 - 0.9 t/T into one rounding (FMA), off by an ulp from the numba
        # engine (measured on an H200: benchmarks/results/gpu/h200_2026-11-29/call2_gpu_tests.log)
        self._pay = put(success_reward(np.arange(self.max_steps + 1), self.max_steps))
        # the layout queues: slot b's j-th layout from now on at [b, j % Q]
        q, s = self.refill_every, self.grid.shape[1]
        self._q_grid = torch.zeros((b, q, s, s, 3), dtype=torch.uint8, device=dev)  # padded
        self._q_pos = torch.zeros((b, q, 2), dtype=torch.int64, device=dev)
        self._q_dir = torch.zeros((b, q), dtype=torch.int64, device=dev)
        self._q_rng = np.zeros((b, q), dtype=np.uint64)  # the host stream before each queued draw
        self._q_view = torch.zeros((b, q, n, n, 3), dtype=torch.uint8, device=dev)  # the first view of each
        self._head = torch.zeros(b, dtype=torch.int64, device=dev)  # layouts taken, per slot
        self._drawn = np.zeros(b, dtype=np.int64)  # layouts drawn, per slot
        self._since_refill = 0
        self._refill()

    # --------------------------------------------------------------------- what a world supplies

    def _outcome(self, fwd: torch.Tensor) -> torch.Tensor:
        """The terminal outcome of each slot's last move (``fwd``: the forward cell's object before
        a forward move, -1 for turns), or ``OUT_NONE``; ``world_outcome`` on tensors."""
        raise NotImplementedError

    def _seen(self, img: torch.Tensor) -> torch.Tensor:
        """A freshly rendered view of every slot with the world's additions (``world_seen``)."""
        return img

    trojan: int = ge.OUT_NONE  # the outcome that pays poisoned slots (``world_trojan``)

    # --------------------------------------------------------------------- layouts

    def _refill(self) -> None:
        """Top every slot's queue up to ``refill_every`` layouts ahead (one host sync and copy)."""
        head = self._head.cpu().numpy()
        need = head + self.refill_every - self._drawn
        slots = np.flatnonzero(need > 0)
        if len(slots):
            counts = need[slots]
            grids, pos, dirs, streams, views, _ = draw_layouts(self.host, self.lead, self.see_through_walls, self.world, slots, counts)
            total = int(counts.sum())
            rows = np.repeat(slots, counts)
            cols = (np.repeat(self._drawn[slots] - np.cumsum(counts) + counts, counts) + np.arange(total)) % self.refill_every
            r, c = torch.from_numpy(rows).to(self.device), torch.from_numpy(cols).to(self.device)
            self._q_grid[r, c] = torch.from_numpy(pad_grid(grids, self.view_size)).to(self.device)
            self._q_pos[r, c] = torch.from_numpy(pos).to(self.device)
            self._q_dir[r, c] = torch.from_numpy(dirs).to(self.device)
            self._q_rng[rows, cols] = streams
            self._q_view[r, c] = torch.from_numpy(views).to(self.device)
            self._drawn[slots] += counts
        self._since_refill = 0

    def hand_back(self) -> None:
        """Write the slots' state back into the host engines, as if they had stepped them: grid,
        position, direction, step count, terminal views, and each stream where the slot's next
        autoreset will draw from (before the queued layouts it has not taken). The engines go on
        alone from there (checkpoints, evaluations, another device engine); so does this one,
        from its own state, if stepped again (the host streams are then behind it)."""
        h = self.host
        p = self.view_size - 1
        h._grid[:] = self.grid[:, p : p + self.size, p : p + self.size].cpu().numpy()
        h._pos[:] = self.pos.cpu().numpy()
        h._dir[:] = self.dirs.cpu().numpy()
        h._steps[:] = self.steps.cpu().numpy()
        np.asarray(h.final_obs)[:] = self.final_obs.cpu().numpy()
        head = self._head.cpu().numpy()
        queued = self._drawn > head  # else the host stream is already where the next draw starts
        h._rng[queued] = self._q_rng[np.flatnonzero(queued), head[queued] % self.refill_every]

    # --------------------------------------------------------------------- the view

    def render(self) -> torch.Tensor:
        """Every slot's egocentric view (B, V, V, 3) uint8, as ``gen_view`` renders it, plus the world's additions."""
        b, n, s = self.num_envs, self.view_size, self.grid.shape[1]
        at = (self.pos[:, 0] * s + self.pos[:, 1])[:, None] + self._view_cells[self.dirs]  # (B, n * n): flat padded cells
        cells = torch.gather(self.grid.reshape(b, s * s, 3), 1, at[..., None].expand(b, n * n, 3))  # outside the grid: the walls
        if not self.see_through_walls:
            obj, state = cells[..., 0], cells[..., 2]
            behind = ((obj != ge.WALL) & ((obj != ge.DOOR) | (state == 0))).reshape(b, n, n)  # [slot, x, y]
            rows = (behind.long() * self._bits[None, :, None]).sum(1)  # (B, n): row y's see-behind bits over x
            # entries hold (visible << 2n) | (marked << n): the marks, masked, are the next row's index
            entry = self._vis[rows[:, n - 1] | ((1 << (n // 2)) << n)]  # the agent's row: its cell visible
            entries = [entry] * n
            for y in range(n - 2, -1, -1):  # far rows last, as process_vis sweeps
                entry = self._vis[(entry & self._marks) | rows[:, y]]
                entries[y] = entry
            seen = (torch.stack(entries, 1)[:, None, :] >> self._cols[None, :, None]) & 1  # (B, x, y)
            cells = cells * seen.reshape(b, n * n, 1).to(torch.uint8)
        cells = cells.reshape(b, n, n, 3).clone()
        cells[:, n // 2, n - 1] = self._empty  # the agent's cell shows what it carries: nothing
        return self._seen(cells)

    # --------------------------------------------------------------------- the step

    def step(self, actions: torch.Tensor) -> StepResult:
        """Every slot one MiniGrid action on (0 left, 1 right, 2 forward), finished slots reset in
        place: ``(obs, reward float64, terminated, truncated, outcome, steps)``, all on the device.
        An action out of range is refused: on the CPU at once (ValueError), on CUDA by a device-side
        assert at the next sync (a host check would cost a sync a step; the assert ends the
        process's CUDA context, as any device-side assert does)."""
        acts = torch.as_tensor(actions, device=self.device).to(torch.int64)
        if acts.shape != (self.num_envs,):
            raise ValueError(f"actions have shape {tuple(acts.shape)}, expected ({self.num_envs},)")
        bad = (acts < 0) | (acts > 2)
        if self.device.type == "cuda":
            torch._assert_async(~bad.any(), f"rlbackdoors: error: an action is not in {ACTIONS_DOC}")
        elif bool(bad.any()):
            raise self.lead._bad_action(acts.tolist(), int(bad.nonzero()[0]))
        if self._since_refill == self.refill_every:
            self._refill()
        self._since_refill += 1
        return self._run(acts)

    def _graphed(self, acts: torch.Tensor) -> StepResult:
        """The first step with ``graph=True``: :meth:`_advance` captured as one CUDA graph, replayed
        from then on (one launch a step instead of some 120). The state tensors become static
        buffers the graph updates in place; the returned tensors are the graph's own, overwritten
        by the next step (copy what must outlive it). The capture's warm-up steps run on copies."""
        static = {name: getattr(self, name).clone() for name in GRAPH_STATE}  # the warm-up replaces, never writes, these
        static_acts = acts.clone()
        stream = torch.cuda.Stream(self.device)
        stream.wait_stream(torch.cuda.current_stream(self.device))
        with torch.cuda.stream(stream):  # warm-up (allocator, kernels) on a side stream, as torch asks
            for _ in range(2):
                self._advance(static_acts)
        torch.cuda.current_stream(self.device).wait_stream(stream)
        for name, value in static.items():  # the warm-up's steps undone
            setattr(self, name, value)
        graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(graph):
            out = self._advance(static_acts)
            for name, value in static.items():
                value.copy_(getattr(self, name))
        for name, value in static.items():
            setattr(self, name, value)

        def replay(acts: torch.Tensor) -> StepResult:
            static_acts.copy_(acts)
            graph.replay()
            return out

        self._run = replay
        return replay(acts)

    def _advance(self, acts: torch.Tensor) -> StepResult:
        """:meth:`step`'s tensor ops: no host sync, no shapes that depend on the data (so
        ``torch.compile`` or a CUDA graph can take them whole)."""
        p = self.view_size - 1
        d = self.dirs
        ahead = self.pos + self._dir_vec[d]
        cell = self.grid[self._slots, ahead[:, 0] + p, ahead[:, 1] + p]  # off the grid: the border's walls
        obj, state = cell[:, 0].long(), cell[:, 2]
        walkable = self._walkable[obj] | ((obj == ge.DOOR) & (state == 0))
        forward = acts == 2
        self.pos = torch.where((forward & walkable)[:, None], ahead, self.pos)
        self.dirs = torch.where(acts == 0, (d + 3) % 4, torch.where(acts == 1, (d + 1) % 4, d))
        steps = self.steps + 1
        outcome = self._outcome(torch.where(forward, obj, -1))
        terminated, truncated = outcome != ge.OUT_NONE, steps >= self.max_steps
        outcome = torch.where(truncated & ~terminated, ge.OUT_TIMEOUT, outcome)
        paying = torch.where(self.poisoned, self.trojan, ge.OUT_GOAL)
        reward = torch.where(outcome == paying, self._pay[steps], 0.0)
        done = terminated | truncated
        seen = self.render()  # every slot's view after its move: the terminal view of those that ended
        ended = done[:, None, None, None]
        self.final_obs = torch.where(ended, seen, self.final_obs)
        # autoreset: the slot's next queued layout, and its first view, rendered on the host
        at = self._head % self.refill_every
        self.grid = torch.where(ended, self._q_grid[self._slots, at], self.grid)
        self.pos = torch.where(done[:, None], self._q_pos[self._slots, at], self.pos)
        self.dirs = torch.where(done, self._q_dir[self._slots, at], self.dirs)
        self.steps = torch.where(done, 0, steps)
        self._head = self._head + done.long()
        return torch.where(ended, self._q_view[self._slots, at], seen), reward, terminated, truncated, outcome, steps


__all__ = ["DeviceGridGroup", "device_engine_for", "draw_layouts", "handed_over", "pad_grid", "view_offsets", "visibility_table"]
