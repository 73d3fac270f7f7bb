"""``rlbackdoors zoo pack ZOO --out DIR``: a copy of a zoo small enough to keep in git.

Why: a zoo is priced in CPU-hours (a CNN model takes several CPU-minutes), and the
machines that train it keep no file from one day to the next. A pack keeps what detectors and the
zoo's own commands read, and nothing else:

* every finished model's weights, config, reduced config, ground truth and metrics
  (:data:`KEPT`), with a manifest of exactly those files;
* a failed model's record (``failed.json``), and every other planned folder's planned files (its
  config and ground truth): a run in progress restarts from its first frame (the same bytes);
* ``zoo.json``, and a ``METADATA.csv`` written from the pack's own folders (a run in progress
  has not written the zoo's yet).

Left out: logs, curves, GIFs, example episodes and checkpoints; with ``--converged-weights-only``
also the weights of finished models that did not converge (no detector reads them: they are not
dataset models), replaced by :data:`WEIGHTS_LEFT_OUT`, which records their sha256 and size. Such a
model still counts as a finished attempt, so ``zoo run`` on a copy does not train it again, and its
metrics stay. Why: a benchmark whose evasive cells converge one attempt in five spends most of its
megabytes on attempts no table reads. The pack is itself a zoo: ``zoo
verify`` passes on it (checked before the pack is put in place), detectors fit and score it, and
``zoo run`` on a copy of it trains only the models still missing. Packing again into the same
``DIR`` replaces the pack of the same zoo (never another zoo's) once the new one is complete.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

from rlbackdoors.folder import WEIGHTS_LEFT_OUT, sha256_file, write_manifest
from rlbackdoors.zoo.job import COMPLETE_MARK, FAILED
from rlbackdoors.zoo.spec import ZooError

KEPT = ("model.pt", "config.json", COMPLETE_MARK, "ground_truth.csv", "metrics.json")  # a finished model
PLANNED = ("config.json", "ground_truth.csv", FAILED)  # a model not finished: its plan (and failure record)


@dataclass
class Packed:
    """What ``pack`` wrote: models finished (weights kept), failed, planned only; bytes in all."""

    out: Path
    finished: int = 0
    failed: int = 0
    planned: int = 0
    bytes: int = 0
    weights_left_out: int = 0  # finished, not converged, weights not packed (--converged-weights-only)

    def line(self) -> str:
        left = f" ({self.weights_left_out} not converged, their weights left out)" if self.weights_left_out else " (weights kept)"
        return (
            f"{self.out}: {self.finished} finished models{left}, {self.failed} failed, {self.planned} planned or in progress "
            f"(to train again); {self.bytes / 1e6:.2f} MB"
        )


def pack(zoo_path: str | Path, out: str | Path, converged_weights_only: bool = False) -> Packed:
    """Write the pack of the zoo at ``zoo_path`` to ``out`` (module doc; ``converged_weights_only``:
    leave out the weights of finished models that did not converge). Refuses a zoo that fails
    ``zoo verify``, an ``out`` inside the zoo, and an ``out`` that holds anything but a pack of
    this same zoo."""
    from rlbackdoors.zoo.index import model_state, write_metadata
    from rlbackdoors.zoo.plan import Zoo
    from rlbackdoors.zoo.verify import verify

    root, out = Path(zoo_path), Path(out)
    result = verify(root)
    if not result.ok:
        raise ZooError(f"{result.summary()}; {result.remedy()}")
    if (root / "trojai.json").exists() or not (root / "zoo.json").is_file():
        raise ZooError(f"zoo pack: {str(root)!r} is not a zoo planned by zoo plan (an imported round is packed by TrojAI's own files)")
    if out.resolve() == root.resolve() or root.resolve() in out.resolve().parents:
        raise ZooError(f"zoo pack: --out {str(out)!r} is inside the zoo {str(root)!r}; write the pack elsewhere")
    if os.path.lexists(out):
        if out.is_symlink() or not out.is_dir() or not (out / "zoo.json").is_file() or (out / "zoo.json").read_bytes() != (root / "zoo.json").read_bytes():
            raise ZooError(f"zoo pack: --out {str(out)!r} exists and is not a pack of this zoo (its zoo.json differs); choose another folder")
    zoo = Zoo.open(root)
    out.parent.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".rlbtmp", dir=out.parent))
    try:
        packed = Packed(out)  # written into ``work``, put in place by one rename at the end
        shutil.copyfile(root / "zoo.json", work / "zoo.json")
        (work / "models").mkdir()
        for model in zoo.all_planned():
            state = model_state(zoo, model)
            folder, dest = zoo.folder(model), work / "models" / model.name
            dest.mkdir()
            names = KEPT if state.status == "done" else PLANNED
            drop = converged_weights_only and state.status == "done" and not state.converged
            for name in names:
                if drop and name == "model.pt":
                    weights = folder / name
                    note = {
                        "file": name,
                        "sha256": sha256_file(weights),
                        "bytes": weights.stat().st_size,
                        "why": "not converged (zoo pack --converged-weights-only)",
                    }
                    (dest / WEIGHTS_LEFT_OUT).write_text(json.dumps(note, indent=1) + "\n")
                    packed.weights_left_out += 1
                elif (folder / name).is_file():
                    shutil.copyfile(folder / name, dest / name)
            if state.status == "done":
                write_manifest(dest)
                packed.finished += 1
            elif state.status == "failed":
                packed.failed += 1
            else:
                packed.planned += 1
        write_metadata(Zoo.open(work))
        packed.bytes = sum(p.stat().st_size for p in work.rglob("*") if p.is_file())
        check = verify(work)
        if not check.ok:  # a pack that would not verify is never put in place
            raise ZooError(f"zoo pack: the pack failed verification ({check.lines()[0]}); nothing was replaced")
        if os.path.lexists(out):
            old = out.with_name(f".{out.name}.old.rlbtmp")
            shutil.rmtree(old, ignore_errors=True)
            os.rename(out, old)
            os.rename(work, out)
            shutil.rmtree(old)
        else:
            os.rename(work, out)
        return packed
    finally:
        if work.exists():
            shutil.rmtree(work, ignore_errors=True)
