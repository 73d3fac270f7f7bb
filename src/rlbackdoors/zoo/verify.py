"""``rlbackdoors zoo verify ZOO``: a zoo is untrusted input until it is checked.

Zoos are passed around as archives, so every command that reads one checks it first:

* **Links.** No symbolic link anywhere in the zoo is followed, whatever it points at (outside,
  another model of the same zoo): each is named and the zoo refused.
* **Manifests.** Every finished model folder holds ``manifest.json`` (the sha256 and size of
  each file, :func:`rlbackdoors.folder.write_manifest`); a missing, changed, truncated or extra
  file is named, and so is a finished folder without a manifest.
* **Consistency.** A planned model's ``config.json`` must be the one the spec draws for it (the
  fields the zoo sets: world, arch, label, trigger, seed), so a config swapped with another
  model's is named; ``ground_truth.csv`` and ``metrics.json`` must carry the label of its group;
  ``METADATA.csv`` must be UTF-8 CSV whose rows name the zoo's folders with their labels, and
  an attempt's folder may not be missing while a later one is there.

``status``, ``report`` and ``split`` refuse a zoo that fails (``--skip-unverified`` leaves the
failing models out and names them); ``zoo run`` refuses it unless ``--retrain-tampered``, which
trains those models again (same config, same bytes). A zoo built before manifests is adopted
with ``zoo verify --write-manifest``: each finished folder that passes the other checks (its
files present, ``reduced-config.json`` matching ``model.pt``'s tensors) gets its manifest.

:attr:`Verification.digest` (sha256 over ``zoo.json`` and every manifest) is what a zoo's
builder publishes beside the archive: ``zoo verify --expect DIGEST`` then proves the whole
zoo unchanged, which manifests inside the archive alone cannot (they travel with it).
"""

from __future__ import annotations

import csv
import hashlib
import io
import os
from dataclasses import dataclass, field
from pathlib import Path

from rlbackdoors.folder import MANIFEST, manifest_problems, write_manifest
from rlbackdoors.io import LOCK_NAME, find_links
from rlbackdoors.zoo.index import read_json
from rlbackdoors.zoo.job import COMPLETE_MARK, is_locked
from rlbackdoors.zoo.spec import ZooError

ZOO_LEVEL = ""  # the key of problems that belong to the zoo, not to one model
DRAWN = (("env", "name"), ("model", "arch"), ("poison", "poisoned"), ("poison", "trigger"), ("train", "seed"))  # what the zoo sets
ENTRY_FILES = ("model.pt", "config.json", "ground_truth.csv", "metrics.json", COMPLETE_MARK)  # a finished dataset entry
NO_MANIFEST = f"no {MANIFEST}"


@dataclass
class Verification:
    """What ``zoo verify`` found: problems per model name (``""``: the zoo's own files)."""

    zoo: Path
    models: int = 0  # model folders looked at
    problems: dict[str, list[str]] = field(default_factory=dict)
    adopted: list[str] = field(default_factory=list)  # folders given a manifest (--write-manifest)
    links: bool = False  # a link was found: nothing may go on, whatever the flags
    digest: str = ""

    def add(self, model: str, problem: str) -> None:
        self.problems.setdefault(model, []).append(problem)

    @property
    def ok(self) -> bool:
        return not self.problems

    def model_problems(self) -> dict[str, str]:
        """Each failing model and why, in one phrase (what ``--skip-unverified`` leaves out)."""
        return {name: "; ".join(found) for name, found in sorted(self.problems.items()) if name != ZOO_LEVEL}

    def lines(self) -> list[str]:
        out = [f"{self.zoo}: {problem}" for problem in self.problems.get(ZOO_LEVEL, [])]
        out += [f"{name}: {why}" for name, why in self.model_problems().items()]
        return out

    def summary(self) -> str:
        bad = self.model_problems()
        parts = [f"{len(bad)} of {self.models} models"] if bad else []
        if self.problems.get(ZOO_LEVEL):
            parts.append(f"{len(self.problems[ZOO_LEVEL])} zoo file problem(s)")
        first = self.lines()[0] if self.lines() else ""
        return f"zoo {str(self.zoo)!r} failed verification ({', '.join(parts)}; first: {first})"

    def remedy(self) -> str:
        if self.links:
            return "remove the links (they are never followed)"
        if self.problems and all(p == [NO_MANIFEST] for k, p in self.problems.items() if k != ZOO_LEVEL) and ZOO_LEVEL not in self.problems:
            return f"a zoo built before manifests is adopted, after its other checks, with: rlbackdoors zoo verify {self.zoo} --write-manifest"
        return f"see every problem with: rlbackdoors zoo verify {self.zoo}"


def _get(config: dict, path: tuple[str, str]):
    section = config.get(path[0])
    return section.get(path[1]) if isinstance(section, dict) else None


def _label(path: Path) -> str | None:
    """``"0"`` / ``"1"`` from ground_truth.csv, ``"?"`` if it holds something else, None if absent."""
    if not path.is_file():
        return None
    text = path.read_bytes().decode("utf-8", errors="replace").strip()
    return text if text in ("0", "1") else "?"


def _adoptable(folder: Path, config: dict) -> list[str]:
    """Why a finished folder without a manifest cannot be adopted (empty: it can)."""
    from rlbackdoors.zoo.job import reduced_config

    missing = [name for name in ENTRY_FILES if not (folder / name).is_file()]
    if missing:
        return [f"{name} is missing" for name in missing]
    try:
        shapes = reduced_config(folder, config)["layers"]
    except (ValueError, OSError, KeyError, TypeError) as err:
        return [f"model.pt is unreadable ({err})"]
    if (read_json(folder / COMPLETE_MARK) or {}).get("layers") != shapes:
        return [f"{COMPLETE_MARK} does not describe model.pt's tensors"]
    return []


def _check_planned(zoo, v: Verification, write: bool) -> dict[str, bool]:
    """Every folder of a planned zoo against its plan and manifest; returns name -> poisoned of
    the finished ones (what METADATA.csv must say)."""
    from rlbackdoors.zoo.index import model_state
    from rlbackdoors.zoo.plan import model_name

    finished: dict[str, bool] = {}
    planned = set()
    for group in zoo.spec.groups:  # Zoo.planned, counting a link as there (it is named already)
        for attempt in range(group.max_attempts):
            folder = zoo.folder(zoo.model(group, attempt))
            if not os.path.lexists(folder):
                break
            planned.add(folder.name)
    for entry in sorted(zoo.models_dir.iterdir()):
        if entry.name.startswith(".") or entry.name in v.problems:
            continue  # temp folders of a killed writer (removed by the next run); links: named, never read
        name = entry.name
        if not entry.is_dir():
            v.add(name, "is not a model folder")
            continue
        model = zoo.lookup(int(name[3:])) if name.startswith("id-") and name[3:].isdigit() and model_name(int(name[3:])) == name else None
        if model is None:
            v.add(name, "is not a model of this zoo's plan")
            continue
        v.models += 1
        if name not in planned:
            v.add(name, f"is attempt {model.attempt} of {model.group.key}, but an earlier attempt's folder is missing")
            continue
        state = model_state(zoo, model)
        if state.status == "running":
            continue  # being written by a live process; checked once it is done
        config = state.config
        if (entry / "config.json").exists() and config is None:
            v.add(name, "config.json is unreadable")
        elif config is not None:
            expected = zoo.draw(model.group, model.attempt).to_dict()
            for path in DRAWN:
                if _get(config, path) != _get(expected, path):
                    v.add(name, f"config.json is not the one the spec draws for it ({'.'.join(path)}={_get(config, path)!r}, drawn {_get(expected, path)!r})")
                    break
        label = _label(entry / "ground_truth.csv")
        if label is not None and label != str(int(model.group.poisoned)):
            v.add(name, f"ground_truth.csv says {label}, its group {model.group.key} is {int(model.group.poisoned)}")
        if state.status != "done":
            continue
        finished[name] = model.group.poisoned
        if (state.metrics or {}).get("poisoned") != model.group.poisoned:
            v.add(name, f"metrics.json's poisoned={(state.metrics or {}).get('poisoned')!r} is not its group's ({model.group.poisoned})")
        _check_manifest(entry, config or {}, v, write and name not in v.problems)
    return finished


def _check_manifest(folder: Path, config: dict, v: Verification, write: bool) -> None:
    problems = manifest_problems(folder)
    if problems == [NO_MANIFEST] and write:
        problems = _adoptable(folder, config) or problems
        if problems == [NO_MANIFEST]:
            write_manifest(folder)
            v.adopted.append(folder.name)
            return
    for problem in problems:
        v.add(folder.name, problem)


def _check_imported(root: Path, v: Verification, write: bool) -> dict[str, bool]:
    finished: dict[str, bool] = {}
    for entry in sorted((root / "models").iterdir()):
        if entry.name.startswith(".") or entry.name in v.problems:
            continue  # links: named, never read
        if not entry.is_dir():
            v.add(entry.name, "is not a model folder")
            continue
        v.models += 1
        config = read_json(entry / "config.json") or {}
        label = _label(entry / "ground_truth.csv")
        recorded = (read_json(entry / "trojai.json") or {}).get("label")
        if label is not None and recorded is not None and label != str(recorded):
            v.add(entry.name, f"ground_truth.csv says {label}, trojai.json {recorded}")
        if label is not None and config and str(int(bool(_get(config, ("poison", "poisoned"))))) != label:
            v.add(entry.name, f"ground_truth.csv says {label}, config.json's poison.poisoned {_get(config, ('poison', 'poisoned'))}")
        _check_manifest(entry, config, v, write and entry.name not in v.problems)
        if label in ("0", "1"):
            finished[entry.name] = label == "1"
    return finished


def _check_metadata(root: Path, finished: dict[str, bool], folders: set[str], v: Verification, running: bool) -> None:
    """METADATA.csv: UTF-8 CSV with model_name, rows naming folders, labels as the folders say."""
    path = root / "METADATA.csv"
    if not path.is_file() or path.is_symlink():
        return  # none yet (a run writes it at its end); a link is named already
    try:
        rows = list(csv.DictReader(io.StringIO(path.read_bytes().decode("utf-8"), newline="")))
    except UnicodeDecodeError as err:
        v.add(ZOO_LEVEL, f"METADATA.csv is not UTF-8 text (byte {err.object[err.start]:#04x} at offset {err.start}); zoo report rewrites it")
        return
    except csv.Error as err:
        v.add(ZOO_LEVEL, f"METADATA.csv is not valid CSV ({err}); zoo report rewrites it")
        return
    if rows and "model_name" not in rows[0]:
        v.add(ZOO_LEVEL, "METADATA.csv has no model_name column; zoo report rewrites it")
        return
    if running:
        return  # a run in progress rewrites it at its end
    named = {row.get("model_name") for row in rows}
    for name in sorted(n for n in named if n and n not in folders):
        v.add(ZOO_LEVEL, f"METADATA.csv lists {name}, which has no model folder")
    for row in rows:
        name = row.get("model_name") or ""
        if name in finished and row.get("poisoned", "") not in ("", str(finished[name])):
            v.add(name, f"METADATA.csv says poisoned={row.get('poisoned')}, its folder {finished[name]}")
    for name in sorted(set(finished) - named):
        v.add(ZOO_LEVEL, f"METADATA.csv has no row for the finished model {name}; zoo report rewrites it")


def _digest(root: Path) -> str:
    digest = hashlib.sha256((root / "zoo.json").read_bytes())
    for path in sorted((root / "models").glob(f"*/{MANIFEST}")):
        digest.update(path.parent.name.encode() + b"\0" + path.read_bytes())
    return digest.hexdigest()


def verify(path: str | Path, write_manifest: bool = False, expect: str | None = None) -> Verification:
    """Check the zoo at ``path`` (module doc); ``write_manifest`` adopts finished folders that
    have none; ``expect`` is a published digest the zoo must have. Reads nothing through a link."""
    from rlbackdoors.zoo.plan import Zoo, read_zoo_json
    from rlbackdoors.zoo.trojai_import import is_imported

    root = Path(path)
    v = Verification(root)
    if not root.is_dir():
        raise ZooError(f"zoo {str(root)!r} does not exist")
    for link in find_links(root):
        rel = link.relative_to(root)
        owner = rel.parts[1] if len(rel.parts) >= 2 and rel.parts[0] == "models" and not rel.parts[1].startswith(".") else ZOO_LEVEL
        inner = rel.as_posix() if owner == ZOO_LEVEL else (Path(*rel.parts[2:]).as_posix() if len(rel.parts) > 2 else "the model folder")
        v.add(owner, f"{inner} is a symbolic link (never followed)")
        v.links = True
    if (root / "zoo.json").is_symlink() or (root / "models").is_symlink():
        return v  # nothing more can be read without following it
    imported = is_imported(root)
    if not imported:
        read_zoo_json(root)  # ZooError: not a zoo
    if not (root / "models").is_dir():
        return v
    folders = {p.name for p in (root / "models").iterdir() if not p.name.startswith(".")}
    finished = _check_imported(root, v, write_manifest) if imported else _check_planned(Zoo.open(root), v, write_manifest)
    running = _zoo_in_use(root)
    _check_metadata(root, finished, folders, v, running)
    v.digest = _digest(root)
    if expect is not None and expect.removeprefix("sha256:") != v.digest:
        v.add(ZOO_LEVEL, f"its digest is sha256:{v.digest}, not the expected {expect}")
    return v


def _zoo_in_use(root: Path) -> bool:
    return (root / LOCK_NAME).is_file() and is_locked(root)


def guard(path: str | Path, command: str, skip: bool) -> dict[str, str]:
    """Verify the zoo before ``command`` reads it: a failing zoo is refused (ZooError naming the
    first problem), unless ``skip``; then the failing models are returned, name -> why, for the
    command to leave out and name. Links are refused whatever ``skip`` says."""
    v = verify(path)
    if v.ok:
        return {}
    if v.links or not skip:
        flag = "" if v.links else f", or pass --skip-unverified to leave the failing models out of zoo {command}"
        raise ZooError(f"{v.summary()}; {v.remedy()}{flag}")
    return v.model_problems()


def skipped_lines(skipped: dict[str, str]) -> list[str]:
    return [f"skipped {name} (failed verification: {why})" for name, why in sorted(skipped.items())]


__all__ = ["Verification", "guard", "skipped_lines", "verify"]
