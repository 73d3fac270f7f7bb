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
not ``done`` are outside the dataset (a raw zoo keeps them on disk); in a zoo (``zoo.json``), a
folder without a row (a zoo still training has no METADATA.csv yet, and one written earlier lacks
the models finished since) is outside it where its own ``metrics.json`` says ``converged: false``;
otherwise (a bare folder of model folders too) every folder holding ``model.pt`` counts. Why the
zoo rule: without it, a zoo cut short was scored with its failed attempts as trojans (a poisoned
attempt that never learned its trigger).

A dataset is untrusted input: no symbolic link in it is followed (one is refused, naming it);
a model folder with ``manifest.json`` must match it, and in a dataset this package wrote (a
zoo, an import or a split: ``zoo.json`` or ``split.json`` at its root) every model folder must
have one; ``ground_truth.csv``, ``config.json`` and METADATA.csv must agree on the label. A
dataset with a model that fails is refused, or with ``skip_unverified`` the model is left out
and named (:attr:`Dataset.skipped`). A bare folder of model folders (what ``rlbackdoors train``
or TrojAI wrote) has no manifests to check against: only links and labels are checked.
"""

from __future__ import annotations

import csv
import io
import json
from dataclasses import dataclass, field
from pathlib import Path

from rlbackdoors.detect.handle import MODEL_FILE, REDUCED_CONFIG, DetectError
from rlbackdoors.folder import MANIFEST, manifest_problems
from rlbackdoors.io import find_links

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
    try:
        rows = list(csv.DictReader(io.StringIO(path.read_bytes().decode("utf-8"), newline="")))
    except (UnicodeDecodeError, csv.Error) as err:
        raise DetectError(f"{str(path)!r} is not a METADATA.csv of UTF-8 text ({err})") from None
    if rows and "model_name" not in rows[0]:
        raise DetectError(f"{str(path)!r} has no model_name column")
    return {row["model_name"]: row for row in rows if row.get("model_name")}


def read_label(folder: Path) -> int:
    path = folder / GROUND_TRUTH
    if not path.is_file():
        raise DetectError(f"{str(path)!r} does not exist (the label of model {folder.name!r})")
    text = path.read_text(errors="replace").strip().splitlines()
    if not text or text[0].strip() not in ("0", "1"):
        raise DetectError(f"{str(path)!r} must hold 1 (poisoned) or 0 (clean)")
    return int(text[0].strip())


class Dataset(list):
    """The dataset's models (a ``list[ZooModel]``), and ``skipped``: the models left out because
    they failed verification (name -> why), for every output to name."""

    def __init__(self, models: list[ZooModel], skipped: dict[str, str]):
        super().__init__(models)
        self.skipped = skipped


def _label_text(path: Path) -> str | None:
    if not path.is_file():
        return None
    text = path.read_bytes().decode("utf-8", errors="replace").strip()
    return text if text in ("0", "1") else None


def model_problems(folder: Path, row: dict[str, str], written_here: bool) -> list[str]:
    """Why the model folder cannot be trusted (empty: it can): its manifest (required in a
    dataset this package wrote), and its label as ground_truth.csv, config.json and METADATA.csv
    give it."""
    problems = manifest_problems(folder) if (folder / MANIFEST).exists() or (folder / MANIFEST).is_symlink() else []
    if written_here and not problems and not (folder / MANIFEST).exists():
        problems.append(f"no {MANIFEST} (check and adopt the zoo with: rlbackdoors zoo verify ZOO --write-manifest, then split it again)")
    label = _label_text(folder / GROUND_TRUTH)
    poisoned = _section(_json(folder / "config.json"), "poison").get("poisoned")
    if label is not None and isinstance(poisoned, bool) and str(int(poisoned)) != label:
        problems.append(f"{GROUND_TRUTH} says {label}, config.json's poison.poisoned {poisoned}")
    listed = (row.get("poisoned") or "").strip()
    if label is not None and listed in ("True", "False") and str(int(listed == "True")) != label:
        problems.append(f"{METADATA} says poisoned={listed}, {GROUND_TRUTH} {label}")
    return problems


def list_models(zoo: str | Path, skip_unverified: bool = False) -> Dataset:
    """The dataset's models, by name (module doc): DetectError naming the cause if there are
    none, if a link is in the dataset, or if a model fails verification (unless
    ``skip_unverified``: then it is left out and named in ``skipped``)."""
    folder = models_dir(zoo)
    root = Path(zoo)
    links = find_links(root)
    if links:
        raise DetectError(f"{str(links[0])!r} in the dataset {str(root)!r} is a symbolic link; links are never followed in a dataset (remove it)")
    metadata = read_metadata(zoo)
    is_zoo = (root / "zoo.json").is_file()
    written_here = is_zoo or (root / "split.json").is_file()
    out, skipped, folders, left_out = [], {}, 0, 0
    for path in sorted(p for p in folder.iterdir() if p.is_dir() and not p.name.startswith(".")):
        row = metadata.get(path.name, {})
        folders += 1
        if row and (row.get("converged", "True").strip().lower() == "false" or row.get("status", "done") not in ("", "done")):
            left_out += 1
            continue
        if is_zoo and not row and _json(path / "metrics.json").get("converged") is False:  # no row for it yet: its run's own record
            left_out += 1
            continue
        if not (path / MODEL_FILE).is_file() and not row and not (path / MANIFEST).exists():
            continue
        problems = model_problems(path, row, written_here)
        if not problems and not (path / MODEL_FILE).is_file():
            problems = [f"{MODEL_FILE} is missing ({METADATA} lists it)"]
        if problems:
            skipped[path.name] = "; ".join(problems)
            continue
        out.append(ZooModel(path.name, path, read_label(path), row))
    if skipped and not skip_unverified:
        name, why = next(iter(skipped.items()))
        raise DetectError(
            f"zoo {str(zoo)!r} failed verification ({len(skipped)} models; first: {name}: {why}); "
            "see every problem with rlbackdoors zoo verify, or pass --skip-unverified to leave them out"
        )
    if not out:
        if left_out:
            raise DetectError(
                f"zoo {str(zoo)!r} holds {folders} model folders but no finished, converged model ({left_out} are not converged or not done "
                f"in {METADATA}); detectors are fitted and scored on converged models only"
            )
        if skipped:
            raise DetectError(f"zoo {str(zoo)!r}: every model failed verification ({len(skipped)}); see rlbackdoors zoo verify")
        raise DetectError(f"zoo {str(zoo)!r} holds no model folders with {MODEL_FILE} (looked in {str(folder)!r})")
    return Dataset(out, skipped)


__all__ = ["FACTORS", "Dataset", "ZooModel", "list_models", "model_problems", "models_dir", "read_label", "read_metadata"]
