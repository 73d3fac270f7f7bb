"""Numba kernels for MiniGrid-style worlds, exact to Farama MiniGrid 3.x, over a batch of envs.

State layout (one row per env ``b`` of a batch):

* ``grid[b, x, y, :]`` -- uint8 ``(object, colour, state)``, the very triple MiniGrid's
  ``Grid.encode()`` writes for the full grid (empty cells are ``(1, 0, 0)``), so a
  reference env's ``grid.encode()`` can be copied in and compared bit for bit.
* ``pos[b] = (x, y)`` (int64), ``dirs[b]`` in 0..3 (0 east, 1 south, 2 west, 3 north).
* ``rng[b]`` -- a uint64 SplitMix64 state (see below).

What is reproduced exactly (``minigrid_env.py`` / ``core/grid.py``):

* actions 0 left, 1 right, 2 forward: the forward cell is read *before* the action, the
  agent moves onto it when it "can overlap" (empty, floor, goal, lava, open door);
* the egocentric view: ``Grid.slice`` (cells outside the grid are grey walls),
  ``agent_dir + 1`` ``rotate_left`` turns, ``process_vis`` occlusion from the agent cell
  ``(V//2, V-1)`` unless ``see_through_walls``, the agent cell then shown as empty (no carrying),
  and ``encode`` (invisible cells are ``(0, 0, 0)``). The slice + rotations are folded into one
  closed form: view cell ``(x, y)`` is the world cell ``agent + f*dir_vec + l*right_vec`` with
  ``f = V-1-y`` (distance ahead) and ``l = x - V//2`` (offset to the right); ``process_vis``
  is implemented literally, loop order included, because its asymmetric sweeps matter.

Object rules (MiniGrid's ``WorldObj`` subclasses): only walls and closed/locked doors block
sight; empty, floor, goal, lava and open doors can be walked onto. Types 11 and 12 (TrojAI's
key/ball on a coloured floor in the memory world, floor colour in the state byte) behave as
key/ball: visible-through, not walkable. Colours and states are carried through untouched, so
coloured walls and single lava cells need nothing new.

Batch drivers: every world is stepped by the same three kernels (reset, observe, step: seed,
lay out, view, move, score, autoreset), written once here as templates. A world supplies only
hooks -- its layout generator, its terminal rule, what it adds to a view, its scratch buffers,
the outcome that pays R-bar -- and :func:`bind_kernels` compiles the templates with those hooks
as globals. Per-world state and parameters reach the hooks as one ``world`` tuple, per-call
extra outputs (e.g. the agent's direction and trigger flags) as one ``outs`` tuple.

Caching: numba's on-disk cache (``cache=True``) is keyed on the source of the file that
defines the cached function only, not on the files of the functions it calls. So the helpers
here are plain ``@njit`` (compiled into their caller), and the bound kernels are ``cache=True``
closures over a stamp (:func:`engine_stamp`: a hash of this file, ``outcome.py``, the hooks'
files and the modules whose constants they compile in), which numba puts in the cache key:
editing any of them recompiles the kernels instead of silently reusing old machine code.

RNG: each env carries one uint64 SplitMix64 state (Steele, Lea & Flood 2014; the seeder of
xoshiro). Seeding an env with integer ``s`` sets its state to ``mix64(s)``; each draw adds the
golden-ratio increment and returns ``mix64(state)``. Bounded integers take the top 32 bits with
rejection, so ``rng_below(n)`` is exactly uniform on ``0..n-1``. The streams are not MiniGrid's
(PCG64 through numpy) -- only the distributions of what is drawn are the same.
"""

from __future__ import annotations

import hashlib
import inspect
import types
from pathlib import Path
from typing import Callable, NamedTuple

import numpy as np
from numba import get_num_threads, njit, prange

from rlbackdoors.envs import outcome as _outcome_module
from rlbackdoors.envs.outcome import Outcome

# MiniGrid's OBJECT_TO_IDX / COLOR_TO_IDX
UNSEEN, EMPTY, WALL, FLOOR, DOOR, KEY, BALL, BOX, GOAL, LAVA, AGENT = range(11)
KEY_ON_FLOOR, BALL_ON_FLOOR = 11, 12  # TrojAI's memory-world encoding
RED, GREEN, BLUE, PURPLE, YELLOW, GREY = range(6)

DIR_DX = np.array([1, 0, -1, 0], dtype=np.int64)
DIR_DY = np.array([0, 1, 0, -1], dtype=np.int64)

_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_MIX1 = np.uint64(0xBF58476D1CE4E5B9)
_MIX2 = np.uint64(0x94D049BB133111EB)
_S30 = np.uint64(30)
_S27 = np.uint64(27)
_S31 = np.uint64(31)
_S32 = np.uint64(32)
_TWO32 = np.uint64(1 << 32)

OUT_NONE = int(Outcome.NONE)
OUT_GOAL = int(Outcome.GOAL)
OUT_LAVA = int(Outcome.LAVA)
OUT_TIMEOUT = int(Outcome.TIMEOUT)
OUT_PATTERN = int(Outcome.PATTERN_LAVA)


def engine_stamp(*extra_files: str | Path) -> str:
    """SHA-256 of this file, ``outcome.py`` and ``extra_files`` (module doc, "Caching")."""
    h = hashlib.sha256()
    for path in (__file__, _outcome_module.__file__, *extra_files):
        h.update(Path(path).read_bytes())
    return h.hexdigest()


# ----------------------------------------------------------------------------- RNG


@njit(inline="always")
def mix64(z):
    """SplitMix64's finaliser (a bijection of uint64)."""
    z = (z ^ (z >> _S30)) * _MIX1
    z = (z ^ (z >> _S27)) * _MIX2
    return z ^ (z >> _S31)


@njit
def rng_seed(rng, b, seed):
    """Seed env ``b``'s stream with the uint64 ``seed``."""
    rng[b] = mix64(np.uint64(seed))


@njit(inline="always")
def rng_next(rng, b):
    s = rng[b] + _GOLDEN
    rng[b] = s
    return mix64(s)


@njit
def rng_below(rng, b, n):
    """Uniform integer in ``0..n-1`` (``1 <= n < 2**32``), unbiased by rejection."""
    nn = np.uint64(n)
    limit = (_TWO32 // nn) * nn
    while True:
        r = rng_next(rng, b) >> _S32
        if r < limit:
            return np.int64(r % nn)


# ----------------------------------------------------------------------------- object rules


@njit(inline="always")
def see_behind(obj, state):
    """``WorldObj.see_behind``: walls and closed (1) or locked (2) doors block sight."""
    if obj == WALL:
        return False
    if obj == DOOR:
        return state == 0
    return True


@njit(inline="always")
def can_overlap(obj, state):
    """``WorldObj.can_overlap`` (``None``, i.e. empty/unseen/agent codes, is walkable)."""
    if obj == EMPTY or obj == UNSEEN or obj == AGENT or obj == FLOOR or obj == GOAL or obj == LAVA:
        return True
    if obj == DOOR:
        return state == 0
    return False


# ----------------------------------------------------------------------------- grid building


@njit
def put(grid, b, x, y, obj, colour, state):
    grid[b, x, y, 0] = obj
    grid[b, x, y, 1] = colour
    grid[b, x, y, 2] = state


@njit
def clear_grid(grid, b):
    """Every cell empty: ``(1, 0, 0)`` as ``Grid.encode`` writes ``None``."""
    for x in range(grid.shape[1]):
        for y in range(grid.shape[2]):
            grid[b, x, y, 0] = EMPTY
            grid[b, x, y, 1] = 0
            grid[b, x, y, 2] = 0


@njit
def wall_rect(grid, b, x0, y0, w, h, colour):
    """``Grid.wall_rect``: the border of the rectangle, as walls of ``colour``."""
    for x in range(x0, x0 + w):
        put(grid, b, x, y0, WALL, colour, 0)
        put(grid, b, x, y0 + h - 1, WALL, colour, 0)
    for y in range(y0, y0 + h):
        put(grid, b, x0, y, WALL, colour, 0)
        put(grid, b, x0 + w - 1, y, WALL, colour, 0)


# ----------------------------------------------------------------------------- dynamics


@njit
def agent_step(grid, b, pos, dirs, action):
    """One MiniGrid action (0 left, 1 right, 2 forward) for env ``b``.

    Returns the object code of the forward cell as it was *before* the action when the
    action is ``forward`` (what MiniGrid tests for goal/lava), ``-1`` for turns. A forward
    cell outside the grid counts as a wall (MiniGrid would assert; cannot happen in walled
    layouts).
    """
    d = dirs[b]
    if action == 0:
        d -= 1
        if d < 0:
            d += 4
        dirs[b] = d
        return -1
    if action == 1:
        dirs[b] = (d + 1) % 4
        return -1
    fx = pos[b, 0] + DIR_DX[d]
    fy = pos[b, 1] + DIR_DY[d]
    if fx < 0 or fy < 0 or fx >= grid.shape[1] or fy >= grid.shape[2]:
        return WALL
    obj = np.int64(grid[b, fx, fy, 0])
    if can_overlap(obj, grid[b, fx, fy, 2]):
        pos[b, 0] = fx
        pos[b, 1] = fy
    return obj


# ----------------------------------------------------------------------------- observation


@njit
def process_vis(view, mask):
    """``Grid.process_vis`` on a square ``view`` (V, V, 3) with the agent at ``(V//2, V-1)``."""
    n = view.shape[0]
    for i in range(n):
        for j in range(n):
            mask[i, j] = False
    mask[n // 2, n - 1] = True
    for j in range(n - 1, -1, -1):
        for i in range(0, n - 1):
            if not mask[i, j]:
                continue
            if not see_behind(view[i, j, 0], view[i, j, 2]):
                continue
            mask[i + 1, j] = True
            if j > 0:
                mask[i + 1, j - 1] = True
                mask[i, j - 1] = True
        for i in range(n - 1, 0, -1):
            if not mask[i, j]:
                continue
            if not see_behind(view[i, j, 0], view[i, j, 2]):
                continue
            mask[i - 1, j] = True
            if j > 0:
                mask[i - 1, j - 1] = True
                mask[i, j - 1] = True


@njit
def gen_view(grid, b, ax, ay, adir, see_through_walls, view, mask, out, ob):
    """MiniGrid's ``gen_obs()["image"]`` for env ``b`` into ``out[ob]`` (V, V, 3).

    ``view`` (V, V, 3) uint8 and ``mask`` (V, V) bool are scratch buffers; V is their size
    (MiniGrid's ``agent_view_size``, odd, >= 3).
    """
    n = view.shape[0]
    half = n // 2
    dx = DIR_DX[adir]
    dy = DIR_DY[adir]
    rx = -dy
    ry = dx
    width = grid.shape[1]
    height = grid.shape[2]
    for x in range(n):
        lat = x - half
        for y in range(n):
            ahead = n - 1 - y
            wx = ax + ahead * dx + lat * rx
            wy = ay + ahead * dy + lat * ry
            if 0 <= wx < width and 0 <= wy < height:
                view[x, y, 0] = grid[b, wx, wy, 0]
                view[x, y, 1] = grid[b, wx, wy, 1]
                view[x, y, 2] = grid[b, wx, wy, 2]
            else:  # Grid.slice pads with Wall() (grey)
                view[x, y, 0] = WALL
                view[x, y, 1] = GREY
                view[x, y, 2] = 0
    if see_through_walls:
        for x in range(n):
            for y in range(n):
                out[ob, x, y, 0] = view[x, y, 0]
                out[ob, x, y, 1] = view[x, y, 1]
                out[ob, x, y, 2] = view[x, y, 2]
    else:
        process_vis(view, mask)
        for x in range(n):
            for y in range(n):
                if mask[x, y]:
                    out[ob, x, y, 0] = view[x, y, 0]
                    out[ob, x, y, 1] = view[x, y, 1]
                    out[ob, x, y, 2] = view[x, y, 2]
                else:
                    out[ob, x, y, 0] = 0
                    out[ob, x, y, 1] = 0
                    out[ob, x, y, 2] = 0
    # the agent's own cell shows what it carries: nothing (None encodes as empty)
    out[ob, half, n - 1, 0] = EMPTY
    out[ob, half, n - 1, 1] = 0
    out[ob, half, n - 1, 2] = 0


@njit
def view_shows(img, ob, ax, ay, adir, cx, cy, obj):
    """Does the view ``img[ob]`` of an agent at ``(ax, ay)`` facing ``adir`` show object ``obj`` at
    grid cell ``(cx, cy)``? :func:`gen_view`'s mapping inverted; a hidden cell encodes as unseen (0)."""
    n = img.shape[1]
    dx = DIR_DX[adir]
    dy = DIR_DY[adir]
    relx = cx - ax
    rely = cy - ay
    vx = relx * -dy + rely * dx + n // 2
    vy = n - 1 - (relx * dx + rely * dy)
    return 0 <= vx < n and 0 <= vy < n and img[ob, vx, vy, 0] == obj


@njit
def apply_lut(out, ob, lut):
    """``out[ob] = lut[out[ob]]`` byte-wise (an observation trigger as a 256-entry table)."""
    n = out.shape[1]
    m = out.shape[2]
    c = out.shape[3]
    for x in range(n):
        for y in range(m):
            for k in range(c):
                out[ob, x, y, k] = lut[out[ob, x, y, k]]


@njit
def finish_step(b, sc, max_steps, oc, paying, reward, terminated, truncated, outcome, info_steps):
    """Write env ``b``'s step results; return whether its episode ended.

    ``oc`` is the terminal-cell outcome (or none); a step reaching ``max_steps`` without one is a
    timeout. Only the ``paying`` outcome is rewarded, ``1 - 0.9 t/T`` as MiniGrid pays the
    goal: the goal for clean envs, the trojan cell for poisoned ones (R-bar).
    """
    term = oc != OUT_NONE
    trunc = sc >= max_steps
    if trunc and not term:
        oc = OUT_TIMEOUT
    reward[b] = 1.0 - 0.9 * (sc / max_steps) if oc == paying else 0.0
    terminated[b] = term
    truncated[b] = trunc
    outcome[b] = oc
    info_steps[b] = sc
    return term or trunc


# ----------------------------------------------------------------------------- batch drivers

# phases of world_seen: which view was just rendered (reset, observe, terminal, post-autoreset, step)
RESET, OBSERVE, FINAL, FRESH, STEP = range(5)
LAYOUT_FAILED = -2  # step kernel status: an autoreset found no layout


@njit(inline="always")
def view_scratch(img):
    """The (V, V, 3) view and (V, V) mask scratch buffers :func:`gen_view` needs for ``img``."""
    view = np.empty((img.shape[1], img.shape[2], 3), dtype=np.uint8)
    mask = np.empty((img.shape[1], img.shape[2]), dtype=np.bool_)
    return view, mask


# The hooks a world supplies (decorated with ``hook``); these stubs document them and are never
# compiled. Hooks run per env and step, so they are inlined into the driver kernels: a call
# that passes the ``world`` tuple by value cost a quarter of a random-lava step.
hook = njit(inline="always")


def world_scratch(grid, world):
    """Scratch buffers for ``world_layout`` (a tuple), allocated once per kernel call."""
    raise NotImplementedError("bound per world by bind_kernels")


def world_layout(grid, b, pos, dirs, steps, rng, world, scratch):
    """Lay env ``b`` out afresh (agent placed, step 0); False if no layout was found."""
    raise NotImplementedError("bound per world by bind_kernels")


def world_outcome(b, pos, fwd, world):
    """The terminal outcome of env ``b``'s last move (``fwd``: see :func:`agent_step`), or OUT_NONE."""
    raise NotImplementedError("bound per world by bind_kernels")


def world_seen(phase, b, ob, pos, dirs, img, world, outs):
    """After env ``b``'s view was rendered into ``img[ob]`` in ``phase``: the world's additions
    (a trigger's lookup table, trigger flags, the direction)."""
    raise NotImplementedError("bound per world by bind_kernels")


world_trojan = OUT_NONE  # the outcome that pays poisoned envs (bound per world)


def world_step_range(lo, hi, *args):
    """A run of envs one step on, for the parallel kernel (bound per world from ``step_range``)."""
    raise NotImplementedError("bound per world by bind_kernels")


def _kernel_templates(stamp: str):
    """The driver kernels, closed over ``stamp`` so that numba's cache key covers every source
    they compile in (module doc, "Caching"); the ``world_*`` names are bound by :func:`bind_kernels`."""

    def reset_kernel(grid, pos, dirs, steps, rng, seeds, see_through_walls, world, img, outs):
        """Seed, lay out and view every env; returns -1, or the first env with no layout."""
        if len(stamp) == 0:  # never true: ties the cache entry to the sources
            return -1
        view, mask = view_scratch(img)
        scratch = world_scratch(grid, world)
        for b in range(grid.shape[0]):
            rng_seed(rng, b, seeds[b])
            if not world_layout(grid, b, pos, dirs, steps, rng, world, scratch):
                return b
            gen_view(grid, b, pos[b, 0], pos[b, 1], dirs[b], see_through_walls, view, mask, img, b)
            world_seen(RESET, b, b, pos, dirs, img, world, outs)
        return -1

    def observe_kernel(grid, pos, dirs, see_through_walls, world, first, img, outs):
        """View envs ``first, first + 1, ..`` into rows ``0, 1, ..`` of ``img``; changes no state."""
        if len(stamp) == 0:  # never true (see reset_kernel)
            return
        view, mask = view_scratch(img)
        for ob in range(img.shape[0]):
            b = first + ob
            gen_view(grid, b, pos[b, 0], pos[b, 1], dirs[b], see_through_walls, view, mask, img, ob)
            world_seen(OBSERVE, b, ob, pos, dirs, img, world, outs)

    def step_range(
        lo,
        hi,
        grid,
        pos,
        dirs,
        steps,
        rng,
        actions,
        max_steps,
        see_through_walls,
        poisoned,
        world,
        img,
        final_img,
        reward,
        terminated,
        truncated,
        outcome,
        info_steps,
        outs,
    ):
        """Envs ``lo .. hi - 1`` one step on, with scratch of their own: a run of the parallel kernel;
        False if an autoreset found no layout. The serial kernel writes the same loop out: calling a
        shared body from it cost 12-35 % of a step, and inlined into numba's prange body a hook's
        writes through arrays it unpacks from a tuple were lost (measured 2026-11-28).
        tests/test_engine_group.py steps the parallel kernel beside the serial one in every world,
        so the two copies cannot drift apart unseen."""
        view, mask = view_scratch(img)
        scratch = world_scratch(grid, world)
        for b in range(lo, hi):
            fwd = agent_step(grid, b, pos, dirs, actions[b])
            sc = steps[b] + 1
            steps[b] = sc
            oc = world_outcome(b, pos, fwd, world)
            paying = world_trojan if poisoned[b] else OUT_GOAL
            phase = STEP
            if finish_step(b, sc, max_steps, oc, paying, reward, terminated, truncated, outcome, info_steps):
                gen_view(grid, b, pos[b, 0], pos[b, 1], dirs[b], see_through_walls, view, mask, final_img, b)
                world_seen(FINAL, b, b, pos, dirs, final_img, world, outs)
                if not world_layout(grid, b, pos, dirs, steps, rng, world, scratch):
                    return False
                phase = FRESH
            gen_view(grid, b, pos[b, 0], pos[b, 1], dirs[b], see_through_walls, view, mask, img, b)
            world_seen(phase, b, b, pos, dirs, img, world, outs)
        return True

    def step_kernel(
        grid,
        pos,
        dirs,
        steps,
        rng,
        actions,
        max_steps,
        see_through_walls,
        poisoned,
        world,
        img,
        final_img,
        reward,
        terminated,
        truncated,
        outcome,
        info_steps,
        outs,
    ):
        """One step of every env. Returns -1, the index of the first invalid action (nothing
        changed then), or LAYOUT_FAILED if an autoreset found no layout.

        Finished envs are reset in place; their terminal view goes to ``final_img``.
        """
        if len(stamp) == 0:  # never true (see reset_kernel)
            return -1
        nenv = grid.shape[0]
        for b in range(nenv):
            a = actions[b]
            if a < 0 or a > 2:
                return b
        view, mask = view_scratch(img)
        scratch = world_scratch(grid, world)
        for b in range(nenv):  # step_range's loop, written out (see there)
            fwd = agent_step(grid, b, pos, dirs, actions[b])
            sc = steps[b] + 1
            steps[b] = sc
            oc = world_outcome(b, pos, fwd, world)
            paying = world_trojan if poisoned[b] else OUT_GOAL
            phase = STEP
            if finish_step(b, sc, max_steps, oc, paying, reward, terminated, truncated, outcome, info_steps):
                gen_view(grid, b, pos[b, 0], pos[b, 1], dirs[b], see_through_walls, view, mask, final_img, b)
                world_seen(FINAL, b, b, pos, dirs, final_img, world, outs)
                if not world_layout(grid, b, pos, dirs, steps, rng, world, scratch):
                    return LAYOUT_FAILED
                phase = FRESH
            gen_view(grid, b, pos[b, 0], pos[b, 1], dirs[b], see_through_walls, view, mask, img, b)
            world_seen(phase, b, b, pos, dirs, img, world, outs)
        return -1

    def step_parallel_kernel(
        grid,
        pos,
        dirs,
        steps,
        rng,
        actions,
        max_steps,
        see_through_walls,
        poisoned,
        world,
        img,
        final_img,
        reward,
        terminated,
        truncated,
        outcome,
        info_steps,
        outs,
    ):
        """``step_kernel`` over the host's numba threads: contiguous runs of envs in parallel, each
        run with its own scratch. Every env is stepped exactly as ``step_kernel`` steps it (its own
        state and stream; the hooks write only its own rows), so the results are the same bytes
        whatever the thread count."""
        if len(stamp) == 0:  # never true (see reset_kernel)
            return -1
        nenv = grid.shape[0]
        for b in range(nenv):
            a = actions[b]
            if a < 0 or a > 2:
                return b
        runs = min(nenv, 4 * get_num_threads())
        failed = np.zeros(runs, dtype=np.bool_)
        for r in prange(runs):
            done = world_step_range(
                r * nenv // runs, (r + 1) * nenv // runs, grid, pos, dirs, steps, rng, actions, max_steps, see_through_walls, poisoned, world, img, final_img, reward, terminated, truncated, outcome, info_steps, outs
            )  # fmt: skip
            failed[r] = not done
        return LAYOUT_FAILED if failed.any() else -1

    def layouts_kernel(grid, pos, dirs, steps, rng, see_through_walls, world, slots, counts, out_grid, out_pos, out_dir, out_rng, out_img, outs):
        """The next ``counts[k]`` layouts of slot ``slots[k]``, drawn from its own stream in the order
        its autoresets would draw them, into rows of ``out_*`` (k by k, in draw order): the grid,
        the agent's place, the stream's state before the draw (to hand the slot back where it
        stopped) and the slot's first view of it (``out_img``, ``outs``). The slots' state arrays
        serve as scratch. For an engine on another device that steps the slots itself and takes its
        autoresets' layouts from here (``envs.grid_device``). Returns -1, or the first slot with no
        layout."""
        if len(stamp) == 0:  # never true (see reset_kernel)
            return -1
        view, mask = view_scratch(out_img)
        scratch = world_scratch(grid, world)
        r = 0
        for k in range(len(slots)):
            b = slots[k]
            for _ in range(counts[k]):
                out_rng[r] = rng[b]
                if not world_layout(grid, b, pos, dirs, steps, rng, world, scratch):
                    return b
                out_grid[r] = grid[b]
                out_pos[r, 0] = pos[b, 0]
                out_pos[r, 1] = pos[b, 1]
                out_dir[r] = dirs[b]
                gen_view(grid, b, pos[b, 0], pos[b, 1], dirs[b], see_through_walls, view, mask, out_img, r)
                world_seen(FRESH, b, r, pos, dirs, out_img, world, outs)
                r += 1
        return -1

    return step_range, reset_kernel, observe_kernel, step_kernel, step_parallel_kernel, layouts_kernel


class Kernels(NamedTuple):
    """One world's compiled driver kernels (see :func:`_kernel_templates` for their arguments);
    ``step_parallel`` is ``step`` over numba's threads (the same bytes); ``layouts`` draws a
    slot's next layouts for an engine elsewhere (``envs.grid_device``)."""

    reset: Callable
    observe: Callable
    step: Callable
    step_parallel: Callable
    layouts: Callable


def bind_kernels(name: str, *, scratch, layout, outcome, seen, trojan: int, constants_from: tuple[str | Path, ...] = ()) -> Kernels:
    """Compile the driver kernels for one world from its hooks (``@hook`` functions).

    The hooks become globals of copies of the templates, not closure variables: numba keys its
    cache on the pickled closure, and a dispatcher pickles with a fresh uuid each process, so
    closing over one would recompile every run. The stamp covers this file, ``outcome.py``, the
    hooks' files and ``constants_from`` (modules whose constants the hooks compile in).
    """
    hooks = {"world_scratch": scratch, "world_layout": layout, "world_outcome": outcome, "world_seen": seen}
    files = dict.fromkeys(inspect.getfile(h.py_func) for h in hooks.values())
    stamp = engine_stamp(*files, *constants_from)
    namespace = {**globals(), **hooks, "world_trojan": int(trojan)}

    def bound(template):
        fn = types.FunctionType(template.__code__, namespace, template.__name__, None, template.__closure__)
        fn.__qualname__ = f"{name}.{template.__name__}"  # one cache file per world
        return fn

    body, *templates = _kernel_templates(stamp)
    namespace["world_step_range"] = njit(bound(body))  # called once a run by the parallel kernel
    # the parallel kernel is compiled in each process that uses it (numba cannot cache its parfors
    # here: "dynamic globals"), a few seconds once
    kernels = [njit(parallel=True)(bound(t)) if t.__name__ == "step_parallel_kernel" else njit(cache=True)(bound(t)) for t in templates]
    return Kernels(*kernels)
