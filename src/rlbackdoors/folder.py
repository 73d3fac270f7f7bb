"""The model folder, the unit of a zoo (TrojAI layout).

``model.pt`` (state dict), ``config.json`` (everything to rebuild and retrain),
``metrics.json`` (written last: its presence marks the folder complete),
``log.csv`` (one row per evaluation), ``ground_truth.csv`` (1 poisoned / 0 clean),
``training_curve.png``, and while training runs, ``checkpoint.pt`` (and ``replay/`` for
OPAC²) for resuming.

A finished zoo entry also holds ``manifest.json`` (:func:`write_manifest`, written last): the
sha256 and size of every file in the folder, so a tampered, truncated, swapped or deleted file
is named (:func:`manifest_problems`) before anything downstream reads it.

A folder is trained by one process at a time: :meth:`ModelFolder.begin` takes its lock
(``.lock``, released by the kernel however the holder ends) and removes temp files that a
killed writer left. Everything read back (weights, checkpoints) is loaded as plain data.
"""

from __future__ import annotations

import csv
import functools
import hashlib
import io
import json
import os
import stat
from pathlib import Path

from rlbackdoors.config import RunConfig
from rlbackdoors.io import (
    LOCK_NAME,
    FolderLock,
    LinkError,
    LockedError,
    UnsafeFileError,
    atomic_write_text,
    load_torch,
    remove_stale_temp_files,
    remove_tree,
    save_torch,
)

MANIFEST = "manifest.json"
MANIFEST_FORMAT = 1
# Not hashed: the folder's lock (rewritten by every holder), the manifest itself, and the zoo
# job's log (its last lines are written after the manifest; nothing reads it back).
UNHASHED = (LOCK_NAME, MANIFEST, "train.log")
WEIGHTS_LEFT_OUT = "weights-left-out.json"  # in place of model.pt in a pack without non-converged weights (zoo pack)
FILES = (
    "model.pt",
    "config.json",
    "metrics.json",
    "log.csv",
    "ground_truth.csv",
    "training_curve.png",
    "clean_vs_triggered.gif",
    "checkpoint.pt",
    MANIFEST,
    WEIGHTS_LEFT_OUT,
)
CHECKPOINT_FORMAT = 2  # 1: pickled objects (refused); 2: plain data (rlbackdoors.state)


class FolderError(RuntimeError):
    """The folder cannot be used as asked (already complete, or holds another run)."""


class ModelFolder:
    def __init__(self, path: str | Path):
        if str(path).strip() == "":
            raise FolderError("the model folder path is empty (give --out DIR)")
        self.path = Path(path)
        if self.path.exists() and not self.path.is_dir():
            raise FolderError(f"{str(self.path)!r} exists and is not a folder")
        self.lock = FolderLock(self.path, "model folder")
        self.created = False  # begin() made the folder: a failed start removes it again
        self._lock_existed = True

    def file(self, name: str) -> Path:
        return self.path / name

    @property
    def complete(self) -> bool:
        return self.file("metrics.json").is_file()

    @property
    def has_checkpoint(self) -> bool:
        return self.file("checkpoint.pt").is_file()

    def clear(self) -> None:
        """Remove only the files this tool writes; anything else in the folder is left alone."""
        for name in FILES:
            self.file(name).unlink(missing_ok=True)
        remove_tree(self.file("replay"))
        remove_stale_temp_files(self.path)

    def _open(self) -> None:
        """Create the folder (checking that it can be written) and take its lock."""
        if self.lock.held:
            return
        existed = self.path.is_dir()
        self._lock_existed = self.lock.path.exists()
        try:
            self.path.mkdir(parents=True, exist_ok=True)
            self.lock.acquire()
        except LockedError as err:
            raise FolderError(str(err)) from None
        except OSError as err:
            raise FolderError(f"cannot write the model folder {str(self.path)!r}: {err.strerror or err}") from None
        self.created = not existed
        remove_stale_temp_files(self.path)  # a killed writer's; we hold the lock, so none is live

    def close(self, failed: bool = False) -> None:
        """Release the lock; after a failed start (``failed``, no checkpoint) remove what begin() made."""
        if not self.lock.held:
            return  # never opened (refused, or the folder could not be made): nothing of ours is there
        if failed and not self.has_checkpoint and not self.complete:
            for name in ("config.json", "log.csv"):
                self.file(name).unlink(missing_ok=True)
            if not self._lock_existed:
                self.lock.path.unlink(missing_ok=True)  # while still held: the folder is as we found it
            if self.created:
                try:
                    self.path.rmdir()
                except OSError:
                    pass  # something else is in it: leave it
        self.lock.release()

    # --- writing -------------------------------------------------------------------------
    def begin(self, cfg, overwrite: bool = False) -> dict | None:
        """Open the folder for training ``cfg`` (a run config): refuse a finished model unless
        ``overwrite``; return the checkpoint of an interrupted run of the same config (None for
        a fresh start); refuse one of another config. Writes ``config.json``. Holds the folder's
        lock until :meth:`close` (or the process ends)."""
        self._open()
        if overwrite:
            self.clear()
        elif self.complete:
            # A run killed between metrics.json and the removal of its checkpoint: finished, so
            # the checkpoint is no longer needed.
            self.file("checkpoint.pt").unlink(missing_ok=True)
            remove_tree(self.file("replay"))
            raise FolderError(f"{str(self.path)!r} already holds a finished model; pass --overwrite to retrain it")
        checkpoint = None
        if self.has_checkpoint:
            try:
                old = type(cfg).load(self.file("config.json")).to_dict()
            except Exception:  # unreadable, or another kind of run: not this run's checkpoint
                old = None
            if old != cfg.to_dict():
                raise FolderError(
                    f"{str(self.path)!r} holds an interrupted run with a different config.json; "
                    "train with that config to resume, or pass --overwrite to start over"
                )
            checkpoint = self.load_checkpoint()
        else:
            remove_tree(self.file("replay"))  # chunks of a checkpoint that never landed
        self.write_config(cfg)
        return checkpoint

    def write_config(self, cfg: RunConfig) -> None:
        atomic_write_text(self.file("config.json"), cfg.to_json())

    def write_json(self, name: str, data: dict) -> None:
        atomic_write_text(self.file(name), json.dumps(data, indent=2, sort_keys=True) + "\n")

    def write_log(self, rows: list[dict]) -> None:
        """One row per evaluation; a column that appears later (losses once learning starts) is
        added to the header and left empty in the rows before it."""
        if not rows:
            return
        fields = list(dict.fromkeys(key for row in rows for key in row))
        buf = io.StringIO()
        writer = csv.DictWriter(buf, fieldnames=fields, restval="")
        writer.writeheader()
        writer.writerows(rows)
        atomic_write_text(self.file("log.csv"), buf.getvalue())

    def write_ground_truth(self, poisoned: bool) -> None:
        atomic_write_text(self.file("ground_truth.csv"), f"{int(poisoned)}\n")

    def save_torch(self, name: str, obj) -> None:
        """Atomically, and the same bytes for the same contents (hashes identify a zoo's models)."""
        save_torch(self.file(name), obj)

    # --- reading -------------------------------------------------------------------------
    def read_config(self) -> RunConfig:
        return RunConfig.load(self.file("config.json"))

    def read_metrics(self) -> dict:
        path = self.file("metrics.json")
        if not path.is_file():
            raise FolderError(f"{str(self.path)!r} holds no finished model (metrics.json missing)")
        try:
            return json.loads(path.read_text())
        except json.JSONDecodeError as err:
            raise FolderError(f"{str(path)!r} is corrupt: {err}") from None

    def read_log(self) -> list[dict]:
        path = self.file("log.csv")
        if not path.is_file():
            return []
        with open(path, newline="") as fh:
            return [{k: _number_or_text(v) for k, v in row.items()} for row in csv.DictReader(fh)]

    def load_checkpoint(self) -> dict:
        """The checkpoint as plain data (never unpickled objects), of this version's format."""
        path = self.file("checkpoint.pt")
        try:
            data = load_torch(path, "checkpoint")
        except UnsafeFileError as err:
            raise FolderError(f"{err}; pass --overwrite to start over") from None
        except (ValueError, OSError) as err:
            raise FolderError(f"checkpoint {str(path)!r} is unreadable ({err}); pass --overwrite to start over") from None
        if not isinstance(data, dict) or data.get("format") != CHECKPOINT_FORMAT:
            found = data.get("format") if isinstance(data, dict) else None
            raise FolderError(
                f"checkpoint {str(path)!r} is not a checkpoint of this version (format {found!r}, expected {CHECKPOINT_FORMAT}); pass --overwrite to start over"
            )
        return data


def sha256_file(path: Path) -> str:
    """The file's sha256 (hex), read in blocks; a link is refused, never followed."""
    digest = hashlib.sha256()
    fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_CLOEXEC)
    with open(fd, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def folder_files(folder: str | Path) -> tuple[dict[str, Path], list[str]]:
    """The files of ``folder`` the manifest covers (``relative/posix/name`` -> path), and the
    entries that are neither a file nor a folder (links first of all), found without following
    any."""
    folder = Path(folder)
    files: dict[str, Path] = {}
    odd: list[str] = []
    for top, dirs, names in os.walk(folder, followlinks=False):
        for name in sorted(dirs + names):
            path = Path(top) / name
            rel = path.relative_to(folder).as_posix()
            mode = os.lstat(path).st_mode
            if stat.S_ISLNK(mode):
                odd.append(f"{rel} is a symbolic link")
            elif stat.S_ISREG(mode):
                if rel not in UNHASHED:
                    files[rel] = path
            elif not stat.S_ISDIR(mode):
                odd.append(f"{rel} is not a regular file")
    return files, odd


def refuse_left_out_weights(path: str | Path) -> None:
    """A one-line refusal for a folder whose weights a pack left out (``zoo pack --converged-weights-only``)."""
    if (Path(path) / WEIGHTS_LEFT_OUT).is_file():
        raise FolderError(f"{str(path)!r} holds no weights: its zoo was packed without the weights of models that did not converge")


def write_manifest(folder: str | Path, pending: dict[str, bytes] | None = None) -> Path:
    """``folder/manifest.json``: sha256 and size of every file in the folder (but
    :data:`UNHASHED`), written atomically once nothing else will be written. ``pending``: files
    (name -> bytes) the caller writes right after, the folder's completion mark, so a folder
    marked complete always has its manifest. A link or a special file in the folder is refused
    (:class:`LinkError`), never hashed."""
    folder = Path(folder)
    files, odd = folder_files(folder)
    if odd:
        raise LinkError(f"model folder {str(folder)!r}: {odd[0]}; links are never followed in a model folder (remove it)")
    entries = {rel: {"sha256": sha256_file(path), "bytes": path.stat().st_size} for rel, path in files.items()}
    for rel, content in (pending or {}).items():
        entries[rel] = {"sha256": hashlib.sha256(content).hexdigest(), "bytes": len(content)}
    manifest = {"format": MANIFEST_FORMAT, "files": dict(sorted(entries.items()))}
    return atomic_write_text(folder / MANIFEST, json.dumps(manifest, indent=2, sort_keys=True) + "\n")


def read_manifest(folder: str | Path) -> dict[str, dict]:
    """The manifest's ``files``; ValueError naming the file if it is missing or malformed."""
    path = Path(folder) / MANIFEST
    if path.is_symlink() or not path.is_file():
        raise ValueError(f"no {MANIFEST}" if not os.path.lexists(path) else f"{MANIFEST} is not a regular file")
    try:
        data = json.loads(path.read_bytes().decode("utf-8"))
    except (OSError, ValueError) as err:
        raise ValueError(f"{MANIFEST} is unreadable ({err})") from None
    files = data.get("files") if isinstance(data, dict) and data.get("format") == MANIFEST_FORMAT else None
    if not isinstance(files, dict) or not all(
        isinstance(v, dict) and isinstance(v.get("sha256"), str) and isinstance(v.get("bytes"), int) for v in files.values()
    ):
        raise ValueError(f"{MANIFEST} is not a manifest of this version (format {MANIFEST_FORMAT})")
    return files


def manifest_problems(folder: str | Path) -> list[str]:
    """What differs between ``folder`` and its manifest, one phrase each (empty: it matches):
    a missing, changed, truncated or extra file, a link, or no manifest at all."""
    folder = Path(folder)
    files, odd = folder_files(folder)
    try:
        recorded = read_manifest(folder)
    except ValueError as err:
        return [*odd, str(err)]
    problems = list(odd)
    for rel, entry in sorted(recorded.items()):
        path = files.get(rel)
        if path is None:
            problems.append(f"{rel} is missing")
        elif path.stat().st_size != entry["bytes"]:
            problems.append(f"{rel} has {path.stat().st_size:,} bytes, the manifest {entry['bytes']:,}")
        elif sha256_file(path) != entry["sha256"]:
            problems.append(f"{rel} differs from the manifest (sha256)")
    problems += [f"{rel} is not in the manifest" for rel in sorted(set(files) - set(recorded))]
    return problems


STACK = ("torch", "numpy", "numba", "gymnasium", "minigrid", "mujoco")


def stack_versions() -> dict:
    """The versions a model was trained with (metrics.json): a zoo is reproducible only with them."""
    return dict(_stack_versions())


@functools.cache
def _stack_versions() -> tuple[tuple[str, str | None], ...]:
    """Read once a process: each read parses the packages' metadata files (about 10 ms a model,
    which a group finishing 256 models together would spend one after another)."""
    import platform
    from importlib import metadata

    from rlbackdoors import __version__

    versions: dict[str, str | None] = {"python": platform.python_version(), "rlbackdoors": __version__}
    for name in STACK:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = None
    return tuple(versions.items())


def _number_or_text(value: str):
    """log.csv cells are numbers except labels such as the curriculum phase."""
    try:
        return float(value)
    except ValueError:
        return value
