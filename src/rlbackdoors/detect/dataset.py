"""The models of a zoo or TrojAI dataset, their labels, and report-only facts about them.

Layout (TrojAI round style, what ``rlbackdoors zoo`` and ``zoo split`` write): ``ZOO/models/
id-XXXXXXXX/`` with ``model.pt``, ``reduced-config.json``, ``clean-example-data/``,
``ground_truth.csv``, ``config.json``; and ``ZOO/METADATA.csv``, one row per model
(``model_name`` first). A folder of model folders without ``models/`` is read too (TrojAI's
``--configure_models_dirpath``).

Only the scorer and the fitting code read labels, METADATA.csv and config.json, never a
detector: a detector gets :class:`rlbackdoors.detect.handle.ModelHandle` objects. config.json
is read here for the report only (the true trigger next to the one a search found).

Which models count: with METADATA.csv, rows whose ``converged`` is false or whose ``status`` is
not ``done`` are outside the dataset (a raw zoo keeps them on disk); without it, every folder
holding ``model.pt``.
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass, field
from pathlib import Path

from rlbackdoors.detect.handle import MODEL_FILE, REDUCED_CONFIG, DetectError

METADATA = "METADATA.csv"
GROUND_TRUTH = "ground_truth.csv"
FACTORS = ("world", "arch", "trigger_family")  # METADATA.csv columns the score breaks down by


@dataclass
class ZooModel:
    name: str
    folder: Path
    label: int
    metadata: dict[str, str] = field(default_factory=dict)

    def facts(self) -> dict[str, str]:
        """Report-only facts: world, arch, trigger family and the true trigger (METADATA.csv first,
        else config.json and the reduced config)."""
        config = _json(self.folder / "config.json")
        reduced = _json(self.folder / REDUCED_CONFIG)
        poison, env, model = (_section(config, k) for k in ("poison", "env", "model"))
        trigger = self.metadata.get("poison.trigger") or poison.get("trigger")
        facts = {
            "world": self.metadata.get("world") or reduced.get("world") or env.get("name") or "",
            "arch": self.metadata.get("arch") or reduced.get("arch") or model.get("arch") or "",
            "trigger_family": self.metadata.get("trigger_family") or (str(trigger).split(":")[0] if trigger else ""),
            "true_trigger": str(trigger) if trigger and self.label == 1 else "",
        }
        return {k: str(v) for k, v in facts.items()}


def _section(config: dict, key: str) -> dict:
    value = config.get(key)
    return value if isinstance(value, dict) else {}


def _json(path: Path) -> dict:
    try:
        data = json.loads(path.read_bytes().decode("utf-8"))
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


def models_dir(zoo: str | Path) -> Path:
    root = Path(zoo)
    if not root.is_dir():
        raise DetectError(f"zoo {str(root)!r} does not exist")
    return root / "models" if (root / "models").is_dir() else root


def read_metadata(zoo: str | Path) -> dict[str, dict[str, str]]:
    path = Path(zoo) / METADATA
    if not path.is_file():
        return {}
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    return {row["model_name"]: row for row in rows if row.get("model_name")}


def read_label(folder: Path) -> int:
    path = folder / GROUND_TRUTH
    if not path.is_file():
        raise DetectError(f"{str(path)!r} does not exist (the label of model {folder.name!r})")
    text = path.read_text(errors="replace").strip().splitlines()
    if not text or text[0].strip() not in ("0", "1"):
        raise DetectError(f"{str(path)!r} must hold 1 (poisoned) or 0 (clean)")
    return int(text[0].strip())


def list_models(zoo: str | Path) -> list[ZooModel]:
    """The dataset's models, by name (module doc); DetectError if there are none."""
    folder = models_dir(zoo)
    metadata = read_metadata(zoo)
    out = []
    for path in sorted(p for p in folder.iterdir() if p.is_dir() and not p.name.startswith(".")):
        row = metadata.get(path.name, {})
        if row and (row.get("converged", "True").strip().lower() == "false" or row.get("status", "done") not in ("", "done")):
            continue
        if not (path / MODEL_FILE).is_file():
            if row:
                raise DetectError(f"{str(path / MODEL_FILE)!r} does not exist (METADATA.csv lists model {path.name!r})")
            continue
        out.append(ZooModel(path.name, path, read_label(path), row))
    if not out:
        raise DetectError(f"zoo {str(zoo)!r} holds no model folders with {MODEL_FILE} (looked in {str(folder)!r})")
    return out


__all__ = ["FACTORS", "ZooModel", "list_models", "models_dir", "read_label", "read_metadata"]
