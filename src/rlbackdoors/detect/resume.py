"""Per-model results of a detector job, kept so that a killed ``detect fit`` or ``detect score``
resumes where it stopped.

A detector's work on one model (its features for a fit, its prediction for a score) can take
minutes (a behavioural search in a MuJoCo world), and a zoo has hundreds of models. Each
model's result is written atomically to ``OUT/.partial/<job>-<key>/<model>.json`` once it
exists; the same job started again (same detector name, parameters, rlbackdoors version, the same
source code of the package, and, for a score, the same learned state) reads it instead of redoing
the work: a detector whose code changed within one version (a new search grid) computes afresh. A result is reused
only for the same bytes of the files a detector may read (``model.pt``, ``reduced-config.json``,
``clean-example-data/``), so a model retrained in place is done again. The job holds ``OUT``'s
lock (:class:`rlbackdoors.io.FolderLock`) while it runs, so a second process is refused by name
instead of writing over the first one's work, and a finished job removes ``.partial``.
"""

from __future__ import annotations

import functools
import hashlib
import json
import re
from pathlib import Path

import numpy as np

from rlbackdoors import __version__
from rlbackdoors.detect.handle import EXAMPLES_DIR, MODEL_FILE
from rlbackdoors.trojai_round import ENV_STRING, ROUND_FILES
from rlbackdoors.io import atomic_write_text, remove_tree

PARTIAL = ".partial"
_SAFE_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,100}")


def model_digest(folder: Path) -> str:
    """SHA-256 over the files a detector's handle is built from (missing ones count as absent)."""
    digest = hashlib.sha256()
    examples = folder / EXAMPLES_DIR
    files = [folder / MODEL_FILE, *(folder / n for n in ROUND_FILES), examples / ENV_STRING, *(sorted(examples.glob("*.npz")) if examples.is_dir() else [])]
    for path in files:
        if path.is_file():
            data = path.read_bytes()
            digest.update(f"{path.relative_to(folder)}\0{len(data)}\0".encode())
            digest.update(data)
    return digest.hexdigest()


def state_digest(state: dict, arrays: dict[str, np.ndarray]) -> str:
    """SHA-256 of a detector's learned state (``Detector.get_state()``): what its predictions depend on."""
    digest = hashlib.sha256(json.dumps(state, sort_keys=True, allow_nan=True).encode())
    for name in sorted(arrays):
        array = np.ascontiguousarray(arrays[name])
        digest.update(f"\0{name}\0{array.dtype.str}\0{array.shape}\0".encode())
        digest.update(array.tobytes())
    return digest.hexdigest()


def source_digest(package: Path | None = None) -> str:
    """SHA-256 over the package's ``.py`` files (names and bytes, in sorted order): what a
    detector's features are computed by, its envs and agents included. ``package`` defaults to
    the installed ``rlbackdoors``, read once per process (the code that runs is the code loaded)."""
    return _tree_digest(package) if package is not None else _installed_digest()


@functools.cache
def _installed_digest() -> str:
    return _tree_digest(Path(__file__).resolve().parents[1])


def _tree_digest(root: Path) -> str:
    digest = hashlib.sha256()
    for path in sorted(root.rglob("*.py")):
        data = path.read_bytes()
        digest.update(f"{path.relative_to(root).as_posix()}\0{len(data)}\0".encode())
        digest.update(data)
    return digest.hexdigest()


class ResultStore:
    """The finished per-model results of one job (``job``: "fit", "score" or "features") in ``out``."""

    def __init__(self, out: str | Path, job: str, key: dict):
        key = {**key, "rlbackdoors": __version__, "source": source_digest()}
        fingerprint = hashlib.sha256(json.dumps(key, sort_keys=True, allow_nan=True, default=str).encode())
        self.folder = Path(out) / PARTIAL / f"{job}-{fingerprint.hexdigest()[:16]}"
        self._digests: dict[Path, str] = {}

    def _digest(self, folder: Path) -> str:
        if folder not in self._digests:
            self._digests[folder] = model_digest(folder)
        return self._digests[folder]

    def _path(self, name: str) -> Path:
        safe = name if _SAFE_NAME.fullmatch(name) else hashlib.sha256(name.encode()).hexdigest()[:24]
        return self.folder / f"{safe}.json"

    def get(self, name: str, folder: Path) -> dict | None:
        """The stored result of model ``name`` (its files in ``folder``), or None: none stored,
        unreadable, or stored for other bytes."""
        try:
            data = json.loads(self._path(name).read_text())
        except (OSError, ValueError, UnicodeDecodeError):
            return None
        if not isinstance(data, dict) or data.get("model") != name or data.get("digest") != self._digest(folder) or not isinstance(data.get("result"), dict):
            return None
        return data["result"]

    def stored(self, models) -> dict[str, dict]:
        """``{name: result}`` of the models (``ZooModel``: ``name``, ``folder``) done before."""
        found = {m.name: self.get(m.name, m.folder) for m in models}
        return {name: result for name, result in found.items() if result is not None}

    def put(self, name: str, folder: Path, result: dict) -> None:
        payload = {"model": name, "digest": self._digest(folder), "result": result}
        atomic_write_text(self._path(name), json.dumps(payload, allow_nan=True) + "\n")  # key order kept: features are ordered


def clear(out: str | Path) -> None:
    """A job in ``out`` is done and its output written: nothing to resume any more."""
    remove_tree(Path(out) / PARTIAL)


def eta(done: int, total: int, seconds: float) -> str:
    """``ETA m:ss`` from the models computed so far (``done`` of ``total`` still to do took ``seconds``)."""
    if done <= 0 or total <= done:
        return ""
    left = seconds / done * (total - done)
    return f", ETA {int(left // 60)}:{int(left % 60):02d}"


__all__ = ["PARTIAL", "ResultStore", "clear", "eta", "model_digest", "state_digest"]
