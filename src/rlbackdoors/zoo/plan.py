"""Planning: every model's full config drawn from the master seed, written before anything trains.

Model ``attempt`` of group ``g`` (a cell's clean or poisoned models) draws its training seed and
trigger from ``SeedSequence(master seed, spawn_key=(g, attempt))``: a pure function of the
spec, so planning twice gives the same bytes, and the models a top-up adds never change the
ones before them. Its id comes from a seeded permutation of the zoo's id space (the sum of the
groups' ``max_attempts``), so ids are fixed by (group, attempt) whatever order models finish
in, and say nothing about ground truth.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np

from rlbackdoors import worlds
from rlbackdoors.config import AUTO_BACKEND, migrate
from rlbackdoors.io import FolderLock, LockedError, atomic_write_text, refuse_links
from rlbackdoors.validate import ConfigError
from rlbackdoors.zoo.spec import EVASION, Group, ZooError, ZooSpec, draw_all, deep_merge, first_difference, load_spec, nested, parse_spec

ZOO_FORMAT = 1
# zoo.json's "update_backend": its PPO models' ppo.update_backend where the spec leaves it open.
# A new zoo's is "auto" (config.preferred_update_backend's pick, one a cell, recorded in each
# config.json); a zoo planned before the key existed is torch's, so its top-ups train as it did.
ZOO_BACKENDS = ("torch", AUTO_BACKEND)
ID_KEY = 2**32  # spawn key of the id permutation (group keys are (group, attempt) pairs)


def build_config(data: dict):
    """The run config of one model from its config dict (checked: ConfigError names the field)."""
    from rlbackdoors.config import RunConfig

    return RunConfig.from_dict(data)


def config_data(world: str, arch: str | None, overrides: dict, poisoned: bool, seed: int, trigger: str | None) -> dict:
    """A model's config dict: the spec's overrides with the fields the zoo draws on top."""
    data = deep_merge(overrides, {"env": {"name": world}, "poison": {"poisoned": poisoned, "trigger": trigger}, "train": {"seed": seed}})
    if not poisoned:  # a cell's clean models are trained clean: evasive variants hide a trojan they do not have
        data["poison"].pop("evasion", None)
    if arch is not None:
        data.setdefault("model", {})["arch"] = arch
    return data


def model_rng(spec: ZooSpec, group: Group, attempt: int) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence(spec.seed, spawn_key=(group.index, attempt)))


@dataclass(frozen=True)
class PlannedModel:
    id: int
    group: Group
    attempt: int

    @property
    def name(self) -> str:
        return model_name(self.id)


def model_name(model_id: int) -> str:
    return f"id-{model_id:08d}"


class Zoo:
    """A zoo folder: ``zoo.json`` (spec and versions), ``models/id-XXXXXXXX/``, ``METADATA.csv``, ``report/``."""

    def __init__(self, path: str | Path, spec: ZooSpec, update_backend: str = "torch"):
        self.path = Path(path)
        self.spec = spec
        self.update_backend = update_backend  # zoo.json's (ZOO_BACKENDS)
        self._sizes: dict[int, int | None] = {}
        self._backends: dict[str, str] = {}  # a cell's (by its world, arch and overrides)

    @classmethod
    def open(cls, path: str | Path) -> Zoo:
        path = Path(path)
        meta = read_zoo_json(path)
        try:
            spec = parse_spec(meta["spec"])
        except ConfigError as err:
            raise ConfigError(f"zoo {str(path)!r}: its zoo.json spec no longer validates ({err})") from None
        return cls(path, spec, zoo_backend(path, meta))

    @property
    def models_dir(self) -> Path:
        return self.path / "models"

    def lock(self) -> FolderLock:
        """The coordinator's lock: one ``plan`` or ``run`` per zoo at a time."""
        lock = FolderLock(self.path, "zoo")
        try:
            return lock.acquire()
        except LockedError as err:
            raise ZooError(str(err)) from None

    @cached_property
    def _permutation(self) -> np.ndarray:
        """Slot -> id: each block's slots (cells' ``block``) shuffled among themselves, a later
        block's ids after every earlier one's. Block 0 is the permutation a zoo always had."""
        parts, start = [], 0
        for block in sorted({g.cell.block for g in self.spec.groups}):
            size = sum(g.max_attempts for g in self.spec.groups if g.cell.block == block)
            key = (ID_KEY,) if block == 0 else (ID_KEY, block)
            parts.append(start + np.random.default_rng(np.random.SeedSequence(self.spec.seed, spawn_key=key)).permutation(size))
            start += size
        return np.concatenate(parts)

    @cached_property
    def _slots(self) -> dict[int, tuple[int, int]]:
        """id -> (group index, attempt)."""
        out = {}
        for group in self.spec.groups:
            for attempt in range(group.max_attempts):
                out[int(self._permutation[group.id_offset + attempt])] = (group.index, attempt)
        return out

    def model(self, group: Group, attempt: int) -> PlannedModel:
        if not 0 <= attempt < group.max_attempts:
            raise ValueError(f"attempt {attempt} is outside {group.key}'s max_attempts={group.max_attempts}")
        return PlannedModel(int(self._permutation[group.id_offset + attempt]), group, attempt)

    def lookup(self, model_id: int) -> PlannedModel | None:
        slot = self._slots.get(model_id)
        if slot is None:
            return None
        return PlannedModel(model_id, self.spec.groups[slot[0]], slot[1])

    def folder(self, model: PlannedModel) -> Path:
        return self.models_dir / model.name

    def planned(self, group: Group) -> list[PlannedModel]:
        """The group's models that have a folder: attempts 0, 1, ... in order (a folder is made
        only by planning, so its config.json, if a failed start removed it, can be put back)."""
        out = []
        for attempt in range(group.max_attempts):
            model = self.model(group, attempt)
            if self.folder(model).is_symlink():
                refuse_links(self.path, self.folder(model))  # raises: never read through it
            if not self.folder(model).is_dir():
                break
            out.append(model)
        return out

    def all_planned(self) -> list[PlannedModel]:
        return sorted((m for g in self.spec.groups for m in self.planned(g)), key=lambda m: m.id)

    # --- drawing ---------------------------------------------------------------------------
    def _size(self, group: Group) -> int | None:
        """The grid size the cell's triggers are drawn for (from a config of the cell)."""
        cell = group.cell
        if group.index not in self._sizes:
            cfg = build_config(config_data(cell.world, cell.arch, cell.overrides, group.poisoned, 0, None))
            self._sizes[group.index] = getattr(cfg.env, "size", None)
        return self._sizes[group.index]

    def _cell_backend(self, group: Group) -> str:
        """The zoo's ``auto`` as one backend for a whole cell: compiled only where its clean and
        its poisoned models would both take it (a clean model has no evasive variant, a poisoned
        one may), so a cell's labels never differ by trainer."""
        cell = group.cell
        drawn_evasion = any(name.startswith(EVASION) for name, _ in cell.attack.ranges)
        key = json.dumps([cell.world, cell.arch, cell.overrides, drawn_evasion], sort_keys=True)
        if key not in self._backends and drawn_evasion:
            self._backends[key] = "torch"  # drawn evasive variants: auto takes torch's for those (config.preferred_update_backend)
        if key not in self._backends:
            choices = set()
            for poisoned in (False, True):
                data = config_data(cell.world, cell.arch, deep_merge(cell.overrides, {"ppo": {"update_backend": AUTO_BACKEND}}), poisoned, 0, None)
                try:
                    ppo = build_config(data).ppo
                    choices.add(ppo.update_backend if ppo is not None else "torch")
                except ConfigError:
                    choices.add(AUTO_BACKEND)  # the model's own draw names the problem
            self._backends[key] = choices.pop() if len(choices) == 1 else "torch"
        return self._backends[key]

    def draw(self, group: Group, attempt: int, written: bool = False):
        """The run config of model ``attempt`` of ``group``: a pure function of the spec
        (``written``: its ranges in the spec's order, :func:`~rlbackdoors.zoo.spec.draw_all`)."""
        rng = model_rng(self.spec, group, attempt)
        seed = int(rng.integers(0, 2**31))
        twin = self.spec.twin(group) if self.spec.matched else None
        if twin is not None:  # a matched zoo: poisoned model k starts from clean model k's seed (and weights)
            seed = int(model_rng(self.spec, twin, attempt).integers(0, 2**31))
        cell = group.cell
        trigger = cell.trigger.draw(worlds.get(cell.world), rng, self._size(group))
        overrides = cell.overrides
        if worlds.get(cell.world).algorithm == "ppo" and (overrides.get("ppo") or {}).get("update_backend", self.update_backend) == AUTO_BACKEND:
            overrides = deep_merge(overrides, {"ppo": {"update_backend": self._cell_backend(group)}})  # the spec's own choice before the zoo's
        if cell.attack.ranges:  # drawn after the trigger: models of cells without ranges draw as they always did
            overrides = deep_merge(overrides, {"poison": cell.attack.draw(rng, written)})
        ranges = cell.label_ranges(group.poisoned)
        if ranges:  # then the cell's own (both labels; clean_ranges for clean models): e.g. a round's training lengths
            overrides = deep_merge(overrides, nested(draw_all(ranges, rng, written)))
        return build_config(config_data(cell.world, cell.arch, overrides, group.poisoned, seed, trigger))

    def drawn(self, group: Group, attempt: int, config: dict, expected: dict | None = None) -> bool:
        """Is ``config`` (a config.json's data) the one the spec draws for this slot: ``expected``
        (the draw's data, drawn here when not given), or, from a spec read as written, the draw of
        its ranges in that order (what ``zoo plan`` wrote before 2026-12-08)."""
        if config == (expected if expected is not None else json.loads(self.draw(group, attempt).to_json())):
            return True
        return config == json.loads(self.draw(group, attempt, written=True).to_json())

    def ensure(self, group: Group, attempt: int, text: str | None = None, verify: bool = True) -> bool:
        """Write the model's config.json and ground_truth.csv if missing; True if anything was written.

        With ``verify``, a config.json that is there must be the one the spec draws, read as the
        run it means where an older version wrote it (the zoo never overwrites a model folder's
        config with another). A run does not verify: a config.json
        written by an older version of the package stays what its model was trained with.
        """
        model = self.model(group, attempt)
        folder = self.folder(model)
        if os.path.lexists(folder):
            refuse_links(self.path, folder)
        refuse_links(self.path, self.models_dir)
        path = folder / "config.json"
        wrote = False
        if not path.is_file():
            atomic_write_text(path, text if text is not None else self.draw(group, attempt).to_json())
            wrote = True
        elif verify:
            expected = json.loads(text if text is not None else self.draw(group, attempt).to_json())
            try:
                old = json.loads(path.read_bytes().decode("utf-8"))
            except (ValueError, OSError) as err:
                raise ZooError(f"{str(path)!r} is unreadable ({err}); remove the folder to plan it again") from None
            if not self.drawn(group, attempt, migrate(old), expected):  # one an older version wrote stands for the run it meant
                raise ZooError(f"{str(path)!r} is not the config the zoo's spec draws for {group.key} attempt {attempt}; remove the folder to plan it again")
        truth = folder / "ground_truth.csv"
        if not truth.is_file() or truth.read_text() != f"{int(group.poisoned)}\n":
            from rlbackdoors.folder import ModelFolder  # the same ground_truth.csv training writes

            ModelFolder(folder).write_ground_truth(group.poisoned)
            wrote = True
        return wrote


def read_zoo_json(path: Path) -> dict:
    meta_path = path / "zoo.json"
    refuse_links(path, meta_path)
    if not meta_path.is_file():
        raise ZooError(f"{str(path)!r} is not a zoo (no zoo.json); make one with: rlbackdoors zoo plan SPEC --out {path}")
    try:
        meta = json.loads(meta_path.read_bytes().decode("utf-8"))
    except (ValueError, OSError) as err:
        raise ZooError(f"{str(meta_path)!r} is unreadable: {err}") from None
    if not isinstance(meta, dict) or meta.get("format") != ZOO_FORMAT or not isinstance(meta.get("spec"), dict):
        raise ZooError(f"{str(meta_path)!r} is not a zoo.json of this version (format {ZOO_FORMAT})")
    return meta


def zoo_backend(path: Path, meta: dict) -> str:
    """zoo.json's ``update_backend`` (torch's where a zoo planned before it has none)."""
    backend = meta.get("update_backend", "torch")
    if backend not in ZOO_BACKENDS:
        raise ZooError(f"{str(path / 'zoo.json')!r}: update_backend={backend!r} is not allowed (allowed: {', '.join(ZOO_BACKENDS)})")
    return backend


def plan(spec: ZooSpec | str | Path, out: str | Path) -> tuple[Zoo, int]:
    """Plan a zoo into ``out``: zoo.json and each group's first ``wanted`` model folders
    (config.json, ground_truth.csv). Returns the zoo and how many folders were written.

    Planning the same spec again writes nothing; another spec is refused before anything is
    touched. Every config is drawn (and checked) before the first file is written.
    """
    from rlbackdoors.folder import stack_versions

    if not isinstance(spec, ZooSpec):
        spec = load_spec(spec)
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ZooError(f"{str(out)!r} exists and is not a folder")
    existing = None
    if (out / "zoo.json").is_file():
        existing = read_zoo_json(out)
        diff = first_difference(existing["spec"], spec.to_dict())
        if diff is not None:
            raise ConfigError(f"zoo {str(out)!r} was planned from another spec ({diff} differs); plan this spec into a new folder")
    elif out.is_dir() and any(p.name != ".lock" for p in out.iterdir()):
        raise ZooError(f"{str(out)!r} is not empty and holds no zoo.json; plan a zoo into a new or empty folder")
    zoo = Zoo(out, spec, zoo_backend(out, existing) if existing is not None else AUTO_BACKEND)
    drawn = []
    for group in spec.groups:
        for attempt in range(group.wanted):
            try:
                drawn.append((group, attempt, zoo.draw(group, attempt).to_json()))
            except ConfigError as err:
                raise ConfigError(f"cells[{group.cell.entry}] ({group.key}, attempt {attempt}): {err}") from None
    lock = zoo.lock()
    try:
        if existing is None:
            meta = {"format": ZOO_FORMAT, "spec": spec.to_dict(), "update_backend": zoo.update_backend, "versions": stack_versions()}
            atomic_write_text(out / "zoo.json", json.dumps(meta, indent=2, sort_keys=True) + "\n")
        written = sum(zoo.ensure(group, attempt, text) for group, attempt, text in drawn)
    finally:
        lock.release()
    return zoo, written


def replan(spec: ZooSpec | str | Path, out: str | Path) -> tuple[Zoo, list[str], Path | None]:
    """Plan a changed spec onto the planned zoo ``out`` without retraining what it left unchanged:
    a model folder whose config.json the new spec draws the same (trained, stopped or not yet
    run) stays; every other moves to ``out/replaced/N/`` (nothing is deleted), and its slot is
    planned afresh. Why: a round found to need another range (e.g. longer training lengths for its
    clean models, which converge sooner) keeps the CPU-hours of every model the fix does not touch.
    A folder counts as drawn the same in either order of its ranges (:meth:`Zoo.drawn`: before
    2026-12-08 a first attempt drew them as the TOML wrote them, a top-up as zoo.json sorts them).
    The new spec must keep the master seed and every group with its ``max_attempts``, in order
    (so each model keeps its id and draws); cells after them, in a later ``block``, are new
    groups with ids after the old ones (e.g. for a family a cell's attempts cannot fill). Else
    refused, nothing touched.
    Returns the zoo, the names moved, and where to."""
    from rlbackdoors.folder import stack_versions

    if not isinstance(spec, ZooSpec):
        spec = load_spec(spec)
    out = Path(out)
    meta = read_zoo_json(out)
    old = Zoo.open(out)

    def layout(s: ZooSpec) -> list:
        return [(g.key, g.poisoned, g.max_attempts) for g in s.groups]

    kept = layout(old.spec)
    if spec.seed != old.spec.seed or layout(spec)[: len(kept)] != kept:
        raise ZooError(
            f"zoo {str(out)!r}: a replan keeps the master seed and every cell's groups and max_attempts, in order (each model's id and draw; new cells may follow them); plan a new zoo instead"
        )
    zoo = Zoo(out, spec, zoo_backend(out, meta))
    if len(spec.groups) > len(old.spec.groups) and list(zoo._permutation[: old.spec.id_space]) != list(old._permutation):
        later = max(g.cell.block for g in old.spec.groups) + 1
        raise ZooError(f"zoo {str(out)!r}: the new cells would renumber its models: give them block = {later} (their ids then follow the planned ones)")
    lock = zoo.lock()
    moved: list[str] = []
    into: Path | None = None
    try:
        refuse_links(out, zoo.models_dir)
        changed = []
        for folder in sorted(zoo.models_dir.glob("id-*")) if zoo.models_dir.is_dir() else []:
            refuse_links(out, folder)
            model = zoo.lookup(int(folder.name[3:])) if folder.name[3:].isdigit() else None
            path = folder / "config.json"
            if model is None or not path.is_file():
                continue  # not a slot of the plan, or never planned: left as it is
            try:
                current = migrate(json.loads(path.read_bytes().decode("utf-8")))
            except (ValueError, OSError) as err:
                raise ZooError(f"{str(path)!r} is unreadable ({err}); remove the folder to plan it again") from None
            if not zoo.drawn(model.group, model.attempt, current):
                changed.append(folder)
        if changed:
            n = 0
            while (out / "replaced" / str(n)).exists():
                n += 1
            into = out / "replaced" / str(n)
            into.mkdir(parents=True)
            for folder in changed:
                os.replace(folder, into / folder.name)
                moved.append(folder.name)
        meta = {**meta, "spec": spec.to_dict(), "versions": meta.get("versions", stack_versions())}
        atomic_write_text(out / "zoo.json", json.dumps(meta, indent=2, sort_keys=True) + "\n")
    finally:
        lock.release()
    plan(spec, out)  # the moved slots' first attempts, as a plan writes them
    if (out / "METADATA.csv").is_file():  # its rows of the moved folders are gone: the index as the folders now stand
        from rlbackdoors.zoo.index import write_metadata

        write_metadata(zoo)
    return zoo, moved, into


__all__ = ["PlannedModel", "Zoo", "build_config", "config_data", "model_name", "plan", "read_zoo_json", "replan"]
