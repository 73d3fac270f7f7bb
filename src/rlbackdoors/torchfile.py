"""Tensors out of a torch file that holds pickled Python objects, without running any of it.

Other tools save more than a state dict: TrojAI's RL rounds pickled whole ``nn.Module``
objects (Jul 2023), a dict with gymnasium spaces and a numpy generator beside the state dict
(Aug 2023), a ``box.Box`` of state dicts (Oct 2024). ``torch.load(weights_only=True)``
refuses those (:func:`rlbackdoors.io.load_torch`), and a full ``torch.load`` would import and
call whatever the file names: a file can run any code that way.

:func:`read_torch_file` reads the zip archive ``torch.save`` writes with a restricted
:class:`pickle.Unpickler`:

* ``find_class`` hands back a real object only for a short allowlist of inert names (torch's
  tensor and parameter rebuild functions, the ``torch.*Storage`` markers, ``OrderedDict``,
  ``set``, ``torch.Size``, ``_codecs.encode`` of latin-1 text), each reimplemented or checked
  here. Every other global (a class, ``os.system``, ``builtins.eval``) becomes an
  :class:`Inert` placeholder class that records its name; calling it (REDUCE, NEWOBJ, BUILD,
  SETITEMS, APPENDS) records the arguments, state and items, and runs nothing.
* ``persistent_load`` reads each tensor storage from the archive's ``data/`` entries as raw
  bytes of the declared dtype (byte order from the archive's ``byteorder``).

:class:`TorchFile` then finds the tensors by path: a module placeholder's ``_parameters`` and
``_buffers`` (persistent ones) and ``_modules`` (what ``state_dict()`` would give), dict keys,
list indices, a placeholder's items and state. Accepting such a file is a separate decision,
taken by its caller on :attr:`TorchFile.globals` (e.g. only known TrojAI formats:
:func:`rlbackdoors.models.read_weights`).
"""

from __future__ import annotations

import _compat_pickle
import collections
import io
import pickle
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

MAX_PICKLE_BYTES = 256 << 20  # data.pkl of a model is kilobytes; a bigger one is not a model
MAX_DEPTH = 200  # of the object tree walked for tensors

# torch's legacy storage class names -> dtype (what persistent ids name)
STORAGE_DTYPES = {
    "FloatStorage": torch.float32,
    "DoubleStorage": torch.float64,
    "HalfStorage": torch.float16,
    "BFloat16Storage": torch.bfloat16,
    "LongStorage": torch.int64,
    "IntStorage": torch.int32,
    "ShortStorage": torch.int16,
    "CharStorage": torch.int8,
    "ByteStorage": torch.uint8,
    "BoolStorage": torch.bool,
}


class Inert:
    """A placeholder for a global the file names: records, never runs.

    Each global gets its own subclass (``module``/``qualname`` class attributes). Calling the
    class, or ``__new__`` on it, makes an instance holding ``args`` and ``kwargs``; BUILD's
    state goes to ``state``; SETITEMS to ``items``; APPENDS and ADDITEMS to ``elements``.
    """

    module: str = ""
    qualname: str = ""
    args: tuple
    kwargs: dict
    state: Any
    items: dict
    elements: list

    def __new__(cls, *args: Any, **kwargs: Any) -> Inert:
        obj = object.__new__(cls)
        obj.__dict__.update(args=args, kwargs=kwargs, state=None, items={}, elements=[])
        return obj

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        pass

    def __setstate__(self, state: Any) -> None:
        self.__dict__["state"] = state

    def __setitem__(self, key: Any, value: Any) -> None:
        self.items[key] = value

    def append(self, value: Any) -> None:
        self.elements.append(value)

    def extend(self, values: Any) -> None:
        self.elements.extend(values)

    def add(self, value: Any) -> None:
        self.elements.append(value)

    def __reduce__(self):  # a placeholder is never written back out as if it were the object
        raise TypeError(f"{self.global_name} is a placeholder read from a file; it cannot be pickled")

    @classmethod
    def name_of(cls) -> str:
        return f"{cls.module}.{cls.qualname}"

    @property
    def global_name(self) -> str:
        return type(self).name_of()

    @property
    def is_module(self) -> bool:
        """Pickled ``nn.Module`` state: a dict with ``_parameters`` and ``_modules``."""
        return isinstance(self.state, dict) and "_parameters" in self.state and "_modules" in self.state

    def __repr__(self) -> str:
        return f"<inert {self.global_name}>"


class _StorageType:
    """What ``find_class('torch', 'FloatStorage')`` returns: a dtype marker, not callable."""

    def __init__(self, name: str, dtype: torch.dtype):
        self.name, self.dtype = name, dtype


def _check_ints(values: Any, what: str) -> tuple[int, ...]:
    if not isinstance(values, (tuple, list)) or not all(isinstance(v, int) and not isinstance(v, bool) and v >= 0 for v in values):
        raise pickle.UnpicklingError(f"tensor {what} must be non-negative integers, got {values!r}")
    return tuple(values)


def _rebuild_tensor(storage: Any, offset: Any, size: Any, stride: Any, *_rest: Any) -> torch.Tensor:
    """``torch._utils._rebuild_tensor(_v2)``: a view of the storage, bounds checked, copied."""
    if not isinstance(storage, torch.Tensor) or storage.dim() != 1:
        raise pickle.UnpicklingError("a tensor's storage is not a storage of this archive")
    if not isinstance(offset, int) or isinstance(offset, bool) or offset < 0:
        raise pickle.UnpicklingError(f"tensor storage offset must be a non-negative integer, got {offset!r}")
    size, stride = _check_ints(size, "size"), _check_ints(stride, "stride")
    if len(size) != len(stride):
        raise pickle.UnpicklingError(f"tensor size {size} and stride {stride} differ in length")
    if any(s == 0 for s in size):
        return torch.empty(size, dtype=storage.dtype)
    last = offset + sum((s - 1) * st for s, st in zip(size, stride))
    if last >= storage.numel():
        raise pickle.UnpicklingError(f"tensor of size {size} reaches past its storage ({storage.numel()} elements)")
    return torch.as_strided(storage, size, stride, offset).clone()


def _rebuild_parameter(data: Any, *_rest: Any) -> Any:
    """``torch._utils._rebuild_parameter(_with_state)``: the tensor itself (no Parameter)."""
    return data


def _rebuild_from_type(func: Any, new_type: Any, args: Any, state: Any) -> Any:
    """``torch._tensor._rebuild_from_type_v2``: the tensor ``func(*args)`` builds, when ``func``
    is one of ours; the tensor subclass and its state are dropped."""
    if func in (_rebuild_tensor, _rebuild_parameter) and isinstance(args, tuple):
        return func(*args)
    return Inert.__new__(_inert_class("torch._tensor", "_rebuild_from_type_v2"), func, new_type, args, state)


def _encode(text: Any, encoding: Any = "utf-8", *_rest: Any) -> bytes:
    """``_codecs.encode`` as protocol-2 pickles of bytes use it: latin-1 text only."""
    if not isinstance(text, str) or encoding not in ("latin1", "latin-1"):
        raise pickle.UnpicklingError(f"_codecs.encode is allowed for latin-1 text only, got encoding {encoding!r}")
    return text.encode("latin-1")


def _set(items: Any = ()) -> set:
    return set(items) if isinstance(items, (list, tuple, set, frozenset)) else set()


def _frozenset(items: Any = ()) -> frozenset:
    return frozenset(_set(items))


ALLOWED = {
    ("torch._utils", "_rebuild_tensor_v2"): _rebuild_tensor,
    ("torch._utils", "_rebuild_tensor"): _rebuild_tensor,
    ("torch._utils", "_rebuild_parameter"): _rebuild_parameter,
    ("torch._utils", "_rebuild_parameter_with_state"): _rebuild_parameter,
    ("torch._tensor", "_rebuild_from_type_v2"): _rebuild_from_type,
    ("collections", "OrderedDict"): collections.OrderedDict,
    ("builtins", "set"): _set,
    ("builtins", "frozenset"): _frozenset,
    ("torch", "Size"): torch.Size,
    ("_codecs", "encode"): _encode,
}

_INERT_CLASSES: dict[tuple[str, str], type[Inert]] = {}


def _inert_class(module: str, name: str) -> type[Inert]:
    key = (module, name)
    cls = _INERT_CLASSES.get(key)
    if cls is None:
        cls = type("Inert", (Inert,), {"module": module, "qualname": name, "__module__": __name__})
        _INERT_CLASSES[key] = cls
    return cls


class _Unpickler(pickle.Unpickler):
    def __init__(self, data: bytes, archive: zipfile.ZipFile, prefix: str, little_endian: bool):
        super().__init__(io.BytesIO(data), encoding="utf-8")
        self.archive, self.prefix, self.little_endian = archive, prefix, little_endian
        self.storages: dict[str, torch.Tensor] = {}
        self.globals: set[str] = set()

    def find_class(self, module: str, name: str) -> Any:
        # Python 2 names (protocols < 3 write "__builtin__"), mapped as pickle's own find_class does
        if (module, name) in _compat_pickle.NAME_MAPPING:
            module, name = _compat_pickle.NAME_MAPPING[(module, name)]
        elif module in _compat_pickle.IMPORT_MAPPING:
            module = _compat_pickle.IMPORT_MAPPING[module]
        self.globals.add(f"{module}.{name}")
        if module == "torch" and name in STORAGE_DTYPES:
            return _StorageType(name, STORAGE_DTYPES[name])
        allowed = ALLOWED.get((module, name))
        return allowed if allowed is not None else _inert_class(module, name)

    def persistent_load(self, pid: Any) -> Any:
        if not (isinstance(pid, tuple) and len(pid) == 5 and pid[0] == "storage"):
            raise pickle.UnpicklingError(f"unsupported persistent id {pid!r:.80}")
        _, storage_type, key, _location, numel = pid
        if not isinstance(storage_type, _StorageType):
            raise pickle.UnpicklingError(f"storage of unknown type {storage_type!r:.80}")
        if not isinstance(key, str) or not key.isdigit():
            raise pickle.UnpicklingError(f"bad storage key {key!r:.40}")
        if key not in self.storages:
            self.storages[key] = self._read_storage(key, storage_type.dtype, numel)
        storage = self.storages[key]
        if storage.dtype != storage_type.dtype:
            raise pickle.UnpicklingError(f"storage {key} is read as two dtypes")
        return storage

    def _read_storage(self, key: str, dtype: torch.dtype, numel: Any) -> torch.Tensor:
        try:
            raw = self.archive.read(f"{self.prefix}data/{key}")
        except KeyError:
            raise pickle.UnpicklingError(f"storage {key} is missing from the archive") from None
        itemsize = torch.empty((), dtype=dtype).element_size()
        if not isinstance(numel, int) or len(raw) != numel * itemsize:
            raise pickle.UnpicklingError(f"storage {key} holds {len(raw)} bytes, not {numel!r} x {itemsize}")
        buffer = bytearray(raw)
        if not buffer:
            return torch.empty(0, dtype=dtype)
        if not self.little_endian and itemsize > 1:
            swapped = torch.frombuffer(buffer, dtype=torch.uint8).view(-1, itemsize).flip(1).contiguous()
            buffer = bytearray(swapped.numpy().tobytes())
        return torch.frombuffer(buffer, dtype=dtype).clone()


def _join(prefix: str, key: Any) -> str:
    return f"{prefix}.{key}" if prefix else str(key)


@dataclass
class TorchFile:
    """What :func:`read_torch_file` found: ``root`` (the unpickled tree, with :class:`Inert`
    placeholders for every global outside the allowlist) and ``globals`` (every global the
    pickle named, ``module.name``)."""

    root: Any
    globals: frozenset[str] = field(default_factory=frozenset)

    # ----- tensors by path ------------------------------------------------------------------
    def tensors(self) -> dict[str, torch.Tensor]:
        """Every tensor reachable from the root, by dotted path (modules as ``state_dict()``)."""
        out: dict[str, torch.Tensor] = {}
        _walk(self.root, "", out, set(), 0)
        return out

    def module_class(self) -> str | None:
        """The class name of a pickled module at the root (or under the root dict's ``model``)."""
        for obj in (self.root, self.root.get("model") if isinstance(self.root, dict) else None):
            if isinstance(obj, Inert) and obj.is_module:
                return obj.qualname
        return None

    def model_class(self) -> str | None:
        """The model's class name: a pickled module's, or a dict's ``"model"`` entry when it is
        a string (TrojAI's Aug 2023 round files: ``{"model": "FCModel", "state_dict": ...}``)."""
        name = self.module_class()
        if name is None and isinstance(self.root, dict) and isinstance(self.root.get("model"), str):
            name = self.root["model"]
        return name

    def state_dict(self) -> dict[str, torch.Tensor] | None:
        """The model's flat state dict, from the formats tools write: a flat dict of tensors; a
        dict holding one under ``state_dict`` or ``model_state``; a pickled module (at the root or
        under ``model``). None if none of these is there."""
        root = self.root
        candidates = [root]
        if isinstance(root, dict):
            candidates += [root.get(k) for k in ("state_dict", "model_state", "model")]
        for obj in candidates:
            if isinstance(obj, dict) and obj and all(isinstance(k, str) and isinstance(v, torch.Tensor) for k, v in obj.items()):
                return dict(obj)
            if isinstance(obj, Inert) and obj.is_module:
                out: dict[str, torch.Tensor] = {}
                _walk_module(obj, "", out, set(), 0)
                return out
        return None


def _walk(obj: Any, prefix: str, out: dict[str, torch.Tensor], seen: set[int], depth: int) -> None:
    if depth > MAX_DEPTH:
        raise ValueError(f"the object tree is deeper than {MAX_DEPTH} levels")
    if isinstance(obj, torch.Tensor):
        out[prefix] = obj
        return
    if isinstance(obj, (str, bytes, int, float, bool, type(None), type)):
        return
    if id(obj) in seen:
        return
    seen.add(id(obj))
    if isinstance(obj, dict):
        for key, value in obj.items():
            _walk(value, _join(prefix, key), out, seen, depth + 1)
    elif isinstance(obj, (list, tuple)):
        for i, value in enumerate(obj):
            _walk(value, _join(prefix, i), out, seen, depth + 1)
    elif isinstance(obj, Inert):
        if obj.is_module:
            _walk_module(obj, prefix, out, seen, depth)
            return
        for key, value in obj.items.items():
            _walk(value, _join(prefix, key), out, seen, depth + 1)
        for i, value in enumerate(obj.elements):
            _walk(value, _join(prefix, i), out, seen, depth + 1)
        state = obj.state
        if isinstance(state, tuple) and len(state) == 2:  # (dict state, slot state)
            for part in state:
                if isinstance(part, dict):
                    _walk(part, prefix, out, seen, depth + 1)
        elif isinstance(state, dict):
            _walk(state, prefix, out, seen, depth + 1)


def _walk_module(obj: Inert, prefix: str, out: dict[str, torch.Tensor], seen: set[int], depth: int) -> None:
    """What ``state_dict()`` holds: parameters, persistent buffers, then each submodule's."""
    if depth > MAX_DEPTH:
        raise ValueError(f"modules nest deeper than {MAX_DEPTH} levels")
    state = obj.state
    assert isinstance(state, dict)
    skip = state.get("_non_persistent_buffers_set")
    skip = skip if isinstance(skip, (set, frozenset)) else set()
    for section in ("_parameters", "_buffers"):
        entries = state.get(section)
        if isinstance(entries, dict):
            for name, value in entries.items():
                if isinstance(value, torch.Tensor) and not (section == "_buffers" and name in skip):
                    out[_join(prefix, name)] = value
    modules = state.get("_modules")
    if isinstance(modules, dict):
        for name, module in modules.items():
            if isinstance(module, Inert) and module.is_module:
                _walk_module(module, _join(prefix, name), out, seen, depth + 1)


def read_torch_file(path: str | Path, what: str = "file") -> TorchFile:
    """Read a ``torch.save`` zip archive as data (module doc); nothing it names is imported or run.

    Raises :class:`FileNotFoundError`, or :class:`ValueError` naming ``what`` and the path when
    it is no torch archive or its pickle is malformed.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{what} {str(path)!r} does not exist")
    try:
        archive = zipfile.ZipFile(path)
    except (zipfile.BadZipFile, OSError) as err:
        raise ValueError(f"cannot read {what} {str(path)!r}: not a torch zip archive ({err})") from None
    with archive:
        pickles = [info for info in archive.infolist() if info.filename == "data.pkl" or info.filename.endswith("/data.pkl")]
        if len(pickles) != 1:
            raise ValueError(f"cannot read {what} {str(path)!r}: a torch archive holds one data.pkl, this one {len(pickles)}")
        info = pickles[0]
        if info.file_size > MAX_PICKLE_BYTES:
            raise ValueError(f"cannot read {what} {str(path)!r}: data.pkl is larger than {MAX_PICKLE_BYTES} bytes")
        prefix = info.filename[: -len("data.pkl")]
        try:
            order = archive.read(f"{prefix}byteorder").decode("ascii").strip()
        except KeyError:
            order = "little"
        if order not in ("little", "big"):
            raise ValueError(f"cannot read {what} {str(path)!r}: unknown byte order {order[:20]!r}")
        unpickler = _Unpickler(archive.read(info), archive, prefix, order == "little")
        try:
            root = unpickler.load()
        except RecursionError:
            raise ValueError(f"cannot read {what} {str(path)!r}: its pickle nests too deeply") from None
        except Exception as err:  # malformed or hostile pickle: nothing ran, nothing to return
            raise ValueError(f"cannot read {what} {str(path)!r}: {type(err).__name__}: {str(err)[:200]}") from None
    return TorchFile(root, frozenset(unpickler.globals))


__all__ = ["ALLOWED", "Inert", "TorchFile", "read_torch_file"]
