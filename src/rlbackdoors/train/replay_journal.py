"""Replay buffers in a checkpoint, written once: a journal of chunks beside ``checkpoint.pt``.

Pickling the buffers into every checkpoint made an OPAC² checkpoint grow by ~1.2 kB
per frame (730 MB at 1.5M frames, GBs for a zoo). Instead each checkpoint appends the rows
added since the previous one as ``replay/KIND-FIRST-END.npz`` (plain arrays, loaded with
``allow_pickle=False``) and lists in ``checkpoint.pt`` the chunks the ring still needs.
Chunks wholly overwritten by newer rows are deleted once a checkpoint no longer lists them,
so the journal holds at most about one buffer's worth of rows.

Inside a chunk, ``next_obs`` is stored only where it is not simply the ``obs`` of the same
env's next row (episode ends), halving its size; loading rebuilds it exactly.

Order of writes: new chunks first, then ``checkpoint.pt`` (atomic), then deletion of chunks
it does not list. A kill at any point leaves a checkpoint whose chunks all exist.
"""

from __future__ import annotations

import io
import re
from pathlib import Path
from typing import Any

import numpy as np

from rlbackdoors.algos.opac2 import COLUMNS, MultitaskReplay
from rlbackdoors.io import atomic_write_bytes

CHUNK = re.compile(r"^(?P<kind>[a-z]+)-(?P<first>\d{12})-(?P<end>\d{12})\.npz$")


class ReplayJournal:
    def __init__(self, folder: str | Path, stride: dict[str, int]):
        """``folder``: where chunks live; ``stride[kind]``: rows one collection step adds to that
        kind's buffer (its env copies), so row ``r``'s next observation is row ``r + stride``'s."""
        self.folder = Path(folder)
        self.stride = dict(stride)
        self.saved = {kind: 0 for kind in stride}  # rows journaled so far, per kind
        self.chunks: dict[str, list[str]] = {kind: [] for kind in stride}

    def _check_folder(self) -> None:
        if self.folder.is_symlink() or (self.folder.exists() and not self.folder.is_dir()):
            raise ValueError(f"{str(self.folder)!r} must be a folder of replay chunks, not a link or a file")

    def append(self, replay: MultitaskReplay) -> dict:
        """Write the rows added since the last call; return the manifest for ``checkpoint.pt``."""
        self._check_folder()
        for kind, buffer in replay.buffers.items():
            if buffer.added > self.saved[kind]:
                first, columns = buffer.rows_since(self.saved[kind])
                name = f"{kind}-{first:012d}-{buffer.added:012d}.npz"
                atomic_write_bytes(self.folder / name, _pack(columns, self.stride[kind]))
                self.chunks[kind].append(name)
                self.saved[kind] = buffer.added
            # Chunks that end before the ring's oldest row are no longer needed.
            oldest = buffer.added - buffer.size
            self.chunks[kind] = [c for c in self.chunks[kind] if _chunk_end(c) > oldest]
        return {"format": 1, "added": dict(self.saved), "chunks": {k: list(v) for k, v in self.chunks.items()}}

    def prune(self) -> None:
        """Delete chunk files the last manifest does not list (call after ``checkpoint.pt`` is written)."""
        keep = {c for chunks in self.chunks.values() for c in chunks}
        self._check_folder()
        if self.folder.is_dir():
            for path in self.folder.iterdir():
                if CHUNK.match(path.name) and path.name not in keep:
                    path.unlink(missing_ok=True)

    def load(self, replay: MultitaskReplay, manifest: dict) -> None:
        """Refill fresh buffers from the chunks ``manifest`` lists (checked, plain arrays only)."""
        self._check_folder()
        if not isinstance(manifest, dict) or manifest.get("format") != 1:
            raise ValueError("checkpoint's replay manifest is missing or of an unknown format")
        added, chunks = manifest.get("added"), manifest.get("chunks")
        if not isinstance(added, dict) or not isinstance(chunks, dict) or set(added) != set(replay.buffers) or set(chunks) != set(replay.buffers):
            raise ValueError(f"checkpoint's replay manifest does not name the buffers {sorted(replay.buffers)}")
        for kind, buffer in replay.buffers.items():
            names = chunks[kind]
            if not isinstance(names, list):
                raise ValueError(f"checkpoint's replay manifest: bad chunk list for {kind!r}")
            for name in names:
                match = CHUNK.match(name) if isinstance(name, str) else None
                if match is None or match["kind"] != kind:
                    raise ValueError(f"checkpoint's replay manifest names a bad chunk {name!r}")
                path = self.folder / name
                if not path.is_file():
                    raise ValueError(f"replay chunk {str(path)!r} is missing")
                columns = _unpack(path, self.stride[kind])
                first, end = int(match["first"]), int(match["end"])
                if len(columns["rew"]) != end - first:
                    raise ValueError(f"replay chunk {str(path)!r} holds {len(columns['rew'])} rows, its name says {end - first}")
                buffer.put_rows(first, columns)
            buffer.set_counters(added[kind])
            self.saved[kind], self.chunks[kind] = added[kind], list(names)


def _chunk_end(name: str) -> int:
    match = CHUNK.match(name)
    assert match is not None  # a name this journal wrote, or one load() checked
    return int(match["end"])


def _pack(columns: dict[str, np.ndarray], stride: int) -> bytes:
    obs, next_obs = columns["obs"], columns["next_obs"]
    n = len(obs)
    # Row r's next_obs is row r + stride's obs unless the episode ended (or the chunk does).
    same = np.zeros(n, bool)
    if n > stride:
        bits = lambda a: a.view(np.uint8).reshape(len(a), -1)  # bit patterns: -0.0 and NaNs stay exact
        same[: n - stride] = np.all(bits(next_obs[: n - stride]) == bits(obs[stride:]), axis=1)
    buf = io.BytesIO()
    arrays: dict[str, Any] = {name: columns[name] for name in COLUMNS if name != "next_obs"}  # Any: numpy's savez stub types **kwds as allow_pickle too
    np.savez(buf, **arrays, next_obs_same=same, next_obs_rest=next_obs[~same])
    return buf.getvalue()


def _unpack(path: Path, stride: int) -> dict[str, np.ndarray]:
    try:
        with np.load(path, allow_pickle=False) as data:
            columns = {name: data[name] for name in COLUMNS if name != "next_obs"}
            same, rest = data["next_obs_same"], data["next_obs_rest"]
    except Exception as err:  # truncated or foreign file: BadZipFile, EOFError, object arrays, ...
        raise ValueError(f"replay chunk {str(path)!r} is unreadable ({type(err).__name__}: {err})") from None
    obs = columns["obs"]
    n = len(obs)
    if same.dtype != np.bool_ or same.shape != (n,) or rest.shape != (int((~same).sum()), *obs.shape[1:]) or same[max(n - stride, 0) :].any():
        raise ValueError(f"replay chunk {str(path)!r} is inconsistent")
    next_obs = np.empty_like(obs)
    next_obs[~same] = rest
    idx = np.flatnonzero(same)
    next_obs[idx] = obs[idx + stride]
    columns["next_obs"] = next_obs
    return columns
