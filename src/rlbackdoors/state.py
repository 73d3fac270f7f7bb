"""Run state as plain data: what a checkpoint holds instead of pickled objects.

A checkpoint must load with ``torch.load(weights_only=True)``, so it may hold tensors, numbers,
strings, bytes and containers of them, nothing else. Live objects (env engines, MiniGrid envs,
replay buffers, trackers) are therefore never stored: :func:`snapshot` reads their changing
state out as data, and :func:`restore` writes it back into fresh objects that the trainer
built from the run's config. Restoring only assigns to attributes the fresh object already
has, with the same type (arrays: same dtype and shape), so a crafted checkpoint can at most
put wrong numbers into a run, never build an object of its choosing.

Encodings (all plain data): an ``np.ndarray`` is ``{"__ndarray__": dtype, "shape", "data": bytes}``;
a numpy ``Generator`` its bit generator's state dict; tuples, sets and frozensets are tagged
lists; a MiniGrid ``Grid`` is a list of cells, each a whitelisted world-object type name with
its colour and state.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from minigrid.core.world_object import WorldObj

PLAIN = (type(None), bool, int, float, str, bytes)
# Attributes a class declares with a default that instances set later (gymnasium.Env's RNG):
# the only ones restore() may set that a fresh object does not have yet.
CLASS_DECLARED = ("_np_random", "_np_random_seed")
MAX_ARRAY_BYTES = 2**31  # no checkpoint array is near this; a crafted size must not allocate


class StateError(ValueError):
    """A checkpoint's state does not fit the run it is loaded into."""


def encode(value: Any, where: str = "state") -> Any:
    """``value`` as plain data (see the module doc); raises :class:`TypeError` for anything else."""
    if isinstance(value, np.generic):
        value = np.asarray(value)
    if isinstance(value, np.ndarray):
        if value.dtype.hasobject:
            raise TypeError(f"{where}: object arrays cannot be stored as data")
        arr = np.array(value, order="C", copy=True)  # (ascontiguousarray would make a 0-d array 1-d)
        return {"__ndarray__": arr.dtype.str, "shape": tuple(arr.shape), "data": arr.tobytes()}
    if isinstance(value, PLAIN):
        return value
    if isinstance(value, np.random.Generator):
        return {"__rng__": value.bit_generator.state}
    if isinstance(value, (tuple, list, set, frozenset)):
        tag = {tuple: "__tuple__", list: "__list__", set: "__set__", frozenset: "__frozenset__"}[type(value)]
        items = sorted(value, key=repr) if isinstance(value, (set, frozenset)) else value
        return {tag: [encode(v, f"{where}[]") for v in items]}
    if isinstance(value, dict):
        if not all(isinstance(k, str) for k in value):
            raise TypeError(f"{where}: dict keys must be strings")
        return {"__dict__": {k: encode(v, f"{where}.{k}") for k, v in value.items()}}
    if _is_grid(value):
        return {"__grid__": _encode_grid(value)}
    raise TypeError(f"{where}: {type(value).__name__} is not plain data")


def decode(data: Any, where: str = "state") -> Any:
    """The value :func:`encode` made (numpy arrays, generators, tuples, ... rebuilt)."""
    if isinstance(data, PLAIN):
        return data
    if not isinstance(data, dict) or len(data) not in (1, 3):
        raise StateError(f"{where}: not an encoded value")
    if "__ndarray__" in data:
        try:
            dtype = np.dtype(data["__ndarray__"])
            if dtype.hasobject:
                raise TypeError("object dtype")
            shape = tuple(int(n) for n in data["shape"])
            raw = data["data"]
            if not isinstance(raw, bytes) or any(n < 0 for n in shape) or len(raw) != int(np.prod(shape, dtype=object)) * dtype.itemsize:
                raise ValueError("data does not hold dtype x shape bytes")
            if len(raw) > MAX_ARRAY_BYTES:
                raise ValueError("too large")
            return np.frombuffer(bytearray(raw), dtype=dtype).reshape(shape)
        except (TypeError, ValueError, KeyError) as err:
            raise StateError(f"{where}: bad array ({err})") from None
    ((tag, body),) = data.items()
    if tag == "__rng__":
        rng = np.random.default_rng()
        try:
            if body.get("bit_generator") != type(rng.bit_generator).__name__:
                raise ValueError(f"bit generator {body.get('bit_generator')!r}")
            rng.bit_generator.state = body
        except (AttributeError, TypeError, ValueError, KeyError) as err:
            raise StateError(f"{where}: bad generator state ({err})") from None
        return rng
    if tag in ("__tuple__", "__list__", "__set__", "__frozenset__"):
        if not isinstance(body, list):
            raise StateError(f"{where}: bad {tag.strip('_')}")
        items = [decode(v, f"{where}[]") for v in body]
        return {"__tuple__": tuple, "__list__": list, "__set__": set, "__frozenset__": frozenset}[tag](items)
    if tag == "__dict__":
        if not isinstance(body, dict):
            raise StateError(f"{where}: bad dict")
        return {str(k): decode(v, f"{where}.{k}") for k, v in body.items()}
    if tag == "__grid__":
        return _decode_grid(body, where)
    raise StateError(f"{where}: unknown encoding {tag!r}")


# ----- objects ---------------------------------------------------------------------------------
def _storable(value: Any) -> bool:
    if isinstance(value, (np.ndarray, np.generic, np.random.Generator, *PLAIN)) or _is_grid(value):
        return not (isinstance(value, np.ndarray) and value.dtype.hasobject)
    if isinstance(value, (tuple, list, set, frozenset)):
        return all(_storable(v) for v in value)
    if isinstance(value, dict):
        return all(isinstance(k, str) and _storable(v) for k, v in value.items())
    return False


def snapshot(obj: Any, skip: tuple[str, ...] = ()) -> dict:
    """The attributes of ``obj`` that are data (arrays, numbers, strings, generators, grids,
    containers of them), encoded. Config-like objects (triggers, spaces) are left out: the
    fresh object built from the run's config has them already."""
    return {name: encode(value, f"{type(obj).__name__}.{name}") for name, value in vars(obj).items() if name not in skip and _storable(value)}


def restore(obj: Any, state: Any, where: str | None = None, skip: tuple[str, ...] = ()) -> None:
    """Write a :func:`snapshot` back into ``obj``; every attribute must exist and match in kind."""
    where = where or type(obj).__name__
    if not isinstance(state, dict):
        raise StateError(f"{where}: state is not a dict of attributes")
    current = vars(obj)
    missing = sorted(set(snapshot(obj, skip)) - set(state))
    if missing:
        raise StateError(f"{where}: state lacks {', '.join(missing)}")
    for name, data in state.items():
        # An attribute the fresh object has, or one its class declares (gymnasium's _np_random).
        if not isinstance(name, str) or name.startswith("__") or name in skip or not (name in current or name in CLASS_DECLARED):
            raise StateError(f"{where}: has no attribute {name!r} to restore")
        setattr(obj, name, _fit(getattr(obj, name), decode(data, f"{where}.{name}"), f"{where}.{name}"))


def _fit(old: Any, new: Any, where: str) -> Any:
    """``new`` where it has the kind of ``old``; arrays are copied into ``old`` (views onto it stay
    valid). Array shapes and dtypes must match exactly: numba kernels index them unchecked."""
    if isinstance(old, np.ndarray):
        if isinstance(new, (tuple, list)) and old.ndim == 1:  # MiniGrid keeps agent_pos as either
            items = [np.asarray(v) for v in new]
            numeric = all(v.shape == () and v.dtype.kind in "iuf" for v in items)
            new = np.array(items, dtype=old.dtype) if numeric else None
        if not isinstance(new, np.ndarray) or new.dtype != old.dtype or new.shape != old.shape:
            raise StateError(f"{where}: expected an array of {old.dtype} with shape {old.shape}")
        if old.flags.writeable:
            old[...] = new
            return old
        return new.copy()
    if isinstance(old, tuple) and isinstance(new, np.ndarray):
        if new.shape != (len(old),) or new.dtype.kind not in "iuf":
            raise StateError(f"{where}: expected {len(old)} numbers")
        return new.copy()
    if isinstance(old, np.generic):
        if not isinstance(new, np.ndarray) or new.shape != () or new.dtype != old.dtype:
            raise StateError(f"{where}: expected a {old.dtype} scalar")
        return new[()]
    if isinstance(old, np.random.Generator):
        if not isinstance(new, np.random.Generator):
            raise StateError(f"{where}: expected a generator state")
        old.bit_generator.state = new.bit_generator.state
        return old
    if new is None and old is not None:
        raise StateError(f"{where}: expected {type(old).__name__}, got None")
    if old is None:
        if not isinstance(new, (type(None), *PLAIN, tuple, list, set, frozenset, dict, np.ndarray, np.random.Generator)) and not _is_grid(new):
            raise StateError(f"{where}: unexpected value")
        return new
    if isinstance(old, bool) != isinstance(new, bool):
        raise StateError(f"{where}: expected {type(old).__name__}, got {type(new).__name__}")
    if type(old) is not type(new):
        raise StateError(f"{where}: expected {type(old).__name__}, got {type(new).__name__}")
    return new


def same_value(a: Any, b: Any) -> bool:
    """Equality that also compares arrays (and containers of them) element by element."""
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return isinstance(a, np.ndarray) and isinstance(b, np.ndarray) and a.dtype == b.dtype and np.array_equal(a, b)
    if isinstance(a, (tuple, list)) and isinstance(b, (tuple, list)):
        return type(a) is type(b) and len(a) == len(b) and all(same_value(x, y) for x, y in zip(a, b))
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(same_value(a[k], b[k]) for k in a)
    return a is b or bool(a == b)


# ----- MiniGrid grids ------------------------------------------------------------------------
def _is_grid(value: Any) -> bool:
    from minigrid.core.grid import Grid

    return isinstance(value, Grid)


def _object_classes() -> dict[str, type[WorldObj]]:
    """World objects a grid may hold, by class name: MiniGrid's and the ones our worlds define
    (subclasses already imported from ``minigrid`` or ``rlbackdoors``, nothing else)."""
    from minigrid.core.world_object import WorldObj

    classes, todo = {}, list(WorldObj.__subclasses__())
    while todo:
        cls = todo.pop()
        todo += cls.__subclasses__()
        if cls.__module__.split(".")[0] in ("minigrid", "rlbackdoors"):
            classes[cls.__name__] = cls
    return classes


def _encode_grid(grid) -> dict:
    cells: list[dict | None] = []
    for obj in grid.grid:
        if obj is None:
            cells.append(None)
            continue
        attrs = {k: v for k, v in vars(obj).items() if k != "contains"}
        if getattr(obj, "contains", None) is not None:
            raise TypeError("grid: objects inside objects are not stored")
        cells.append({"cls": type(obj).__name__, "attrs": encode(attrs, "grid cell")})
    return {"width": grid.width, "height": grid.height, "cells": cells}


def _decode_grid(body: Any, where: str):
    from minigrid.core.grid import Grid

    try:
        width, height, cells = int(body["width"]), int(body["height"]), body["cells"]
    except (TypeError, KeyError, ValueError):
        raise StateError(f"{where}: bad grid") from None
    if not (0 < width <= 256 and 0 < height <= 256) or not isinstance(cells, list) or len(cells) != width * height:
        raise StateError(f"{where}: bad grid size")
    classes = _object_classes()
    grid = Grid(width, height)
    for i, cell in enumerate(cells):
        if cell is None:
            continue
        cls = classes.get(cell.get("cls", "")) if isinstance(cell, dict) else None  # "": no class, as a missing key
        if cls is None:
            raise StateError(f"{where}: cell {i} holds an unknown object type")
        obj = cls.__new__(cls)
        attrs = decode(cell.get("attrs"), f"{where}.cell{i}")
        if not isinstance(attrs, dict) or not all(isinstance(v, (*PLAIN, tuple, np.ndarray)) for v in attrs.values()):
            raise StateError(f"{where}: cell {i} has bad attributes")
        vars(obj).update(attrs)
        obj.contains = None
        grid.grid[i] = obj
    return grid


__all__ = ["StateError", "decode", "encode", "restore", "snapshot"]
