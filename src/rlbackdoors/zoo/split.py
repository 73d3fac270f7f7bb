"""Train and test datasets from a zoo, disjoint by model and by trigger.

Only converged models go in (the dataset). Models are grouped by their trigger string (clean
models carry one too: their poisoned SR is measured under it), and whole groups are dealt to
train or test, so no trigger of the test set occurs in the train set and a detector is tested
on triggers it never saw. Groups are dealt in a seeded random order, each to the split that is
furthest below its share; the result is a pure function of the zoo and the seed.

Each split is a TrojAI-style folder: ``models/id-XXXXXXXX/`` (copied, or hard-linked with
``link``) and ``METADATA.csv`` with the rows of its models, plus ``split.json``. A model folder
is copied under a temp name and renamed, so a killed split leaves no half-copied model.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np

from rlbackdoors.folder import manifest_problems
from rlbackdoors.io import TEMP_SUFFIX, LinkError, atomic_write_text, find_links, remove_tree
from rlbackdoors.validate import ConfigError
from rlbackdoors.zoo.index import LEAD_COLUMNS, ModelState, csv_text, metadata_rows, scan
from rlbackdoors.zoo.plan import Zoo
from rlbackdoors.zoo.spec import ZooError

# Not part of a dataset entry: the lock (pid and host), resume state, and the job's log (host
# names, paths of the building machine); nothing of the building machine goes into a dataset.
SKIP = (".lock", "checkpoint.pt", "replay", "failed.json", "train.log")


def assign(states: list[ModelState], train: float, test: float, seed: int) -> tuple[list[ModelState], list[ModelState]]:
    """(train, test) converged models, disjoint by trigger string."""
    if not (0 < train < 1 and 0 < test < 1) or train + test > 1 + 1e-9:
        raise ConfigError(f"--train {train:g} and --test {test:g} must each be in (0, 1) and add up to at most 1")
    models = [s for s in states if s.converged]
    groups: dict[str, list[ModelState]] = {}
    for s in models:
        groups.setdefault(_trigger(s), []).append(s)
    if len(groups) < 2:
        raise ConfigError(
            f"the zoo has {len(models)} converged models and {len(groups)} distinct trigger(s); a split by trigger needs at least 2 "
            "(draw triggers from a range or a kind, or wait for more models)"
        )
    order = sorted(groups)
    rng = np.random.default_rng(seed)
    rng.shuffle(order)
    total = len(models)
    targets = {"train": train * total, "test": test * total}
    dealt: dict[str, list[ModelState]] = {"train": [], "test": []}
    skipped = 0
    for trigger in order:
        group = groups[trigger]
        fill = {k: len(v) / targets[k] for k, v in dealt.items()}
        side = min(fill, key=lambda k: (fill[k], k))
        if train + test < 1 - 1e-9 and all(len(dealt[k]) + len(group) > targets[k] + 0.5 for k in dealt):
            skipped += len(group)  # shares below 1: the rest of the zoo stays out
            continue
        dealt[side].extend(group)
    if not dealt["train"] or not dealt["test"]:
        raise ConfigError(f"the split left {'train' if not dealt['train'] else 'test'} empty; give it a larger share or build more models")
    return sorted(dealt["train"], key=lambda s: s.model.id), sorted(dealt["test"], key=lambda s: s.model.id)


def _attack_names(state: ModelState) -> set[str]:
    """What ``--hold-out-attack`` may name a model's attack by: its cell's label and the attack's registry name."""
    choice = state.model.group.cell.attack
    return {choice.name, choice.attack}


def assign_held_out(states: list[ModelState], hold_out: list[str]) -> tuple[list[ModelState], list[ModelState], int]:
    """(train, test, left out): every converged model of a cell poisoned by an attack in ``hold_out``
    (clean and poisoned) is tested, the others train, minus those whose trigger occurs in the test
    set (still disjoint by trigger: a detector is tested on an attack and triggers it never saw)."""
    models = [s for s in states if s.converged]
    known = set().union(*(_attack_names(s) for s in states)) if states else set()
    for name in hold_out:
        if name not in known:
            raise ConfigError(f"--hold-out-attack {name!r} is not an attack of this zoo (allowed: {', '.join(sorted(known)) or 'none'})")
    test = [s for s in models if _attack_names(s) & set(hold_out)]
    triggers = {_trigger(s) for s in test}
    rest = [s for s in models if not _attack_names(s) & set(hold_out)]
    train = [s for s in rest if _trigger(s) not in triggers]
    if not train or not test:
        raise ConfigError(
            f"holding out {', '.join(hold_out)} left {'train' if not train else 'test'} empty (converged models: {len(models)}; draw triggers so that attacks do not share them)"
        )
    return train, test, len(rest) - len(train)


def _copy_model(source: Path, target: Path, link: bool) -> None:
    tmp = target.with_name(f".{target.name}.{os.getpid()}{TEMP_SUFFIX}")
    remove_tree(tmp)

    def ignore(folder: str, names: list[str]) -> list[str]:
        return [n for n in names if n in SKIP or n.endswith(TEMP_SUFFIX)] if Path(folder) == source else [n for n in names if n.endswith(TEMP_SUFFIX)]

    copy = os.link if link else shutil.copy2
    try:
        shutil.copytree(source, tmp, ignore=ignore, copy_function=copy, symlinks=True)
        problems = manifest_problems(tmp)  # what landed is what the manifest says, or nothing lands
        if problems:
            raise ZooError(f"model {source.name}: {problems[0]} (it changed while being copied); run zoo split again")
        os.replace(tmp, target)
    except BaseException:
        remove_tree(tmp)
        raise


def write_split(zoo: Zoo, name: str, states: list[ModelState], out: Path, link: bool, info: dict) -> None:
    """split.json first (what this folder is to hold, so a re-run recognises a cut-short split),
    then the model folders, then METADATA.csv."""
    triggers = sorted({_trigger(s) for s in states})
    payload = {**info, "split": name, "models": [s.model.name for s in states], "triggers": triggers}
    atomic_write_text(out / "split.json", json.dumps(payload, indent=2, sort_keys=True) + "\n")
    models = out / "models"
    models.mkdir(parents=True, exist_ok=True)
    for stale in models.glob(f".*{TEMP_SUFFIX}"):  # a copy a killed split left
        remove_tree(stale)
    for s in states:
        target = models / s.model.name
        if not target.is_dir():
            _copy_model(s.folder, target, link)
    atomic_write_text(out / "METADATA.csv", csv_text(metadata_rows(states), LEAD_COLUMNS))


def _trigger(state: ModelState) -> str:
    return str((state.config or {}).get("poison", {}).get("trigger"))


def split(
    path: str | Path,
    train: float,
    test: float,
    out_train: str | Path,
    out_test: str | Path,
    seed: int = 0,
    link: bool = False,
    skip: dict[str, str] | None = None,
    hold_out_attacks: list[str] | None = None,
) -> dict:
    """Write the two datasets; returns their sizes and triggers. Re-running with the same
    arguments completes a split that was cut short and changes nothing else. ``skip``: models
    that failed zoo verify (name -> why), left out (``skipped`` in split.json names them).
    ``hold_out_attacks``: test on these attacks' cells, train on the rest (:func:`assign_held_out`;
    the shares are not used).

    Only finished, verified entries go in: each copy is checked against its manifest."""
    zoo = Zoo.open(path)
    out_train, out_test = Path(out_train), Path(out_test)
    if out_train.resolve() == out_test.resolve():
        raise ConfigError("--out-train and --out-test must be different folders")
    for out in (out_train, out_test):
        where = out.resolve()
        if where == zoo.path.resolve() or zoo.models_dir.resolve() in (where, *where.parents):
            raise ConfigError(f"{str(out)!r} is the zoo or inside its models folder; write the splits elsewhere")
    # the zoo by its folder's name, never a path of the building machine (datasets are shared)
    info: dict = {"zoo": zoo.path.resolve().name, "seed": seed, "shares": {"train": train, "test": test}, "skipped": dict(sorted((skip or {}).items()))}
    if hold_out_attacks:
        train_states, test_states, overlap = assign_held_out(scan(zoo, probe=False, skip=skip), list(hold_out_attacks))
        info.update(shares=None, hold_out_attacks=sorted(hold_out_attacks), left_out_for_shared_trigger=overlap)
    else:
        train_states, test_states = assign(scan(zoo, probe=False, skip=skip), train, test, seed)
    for out, name, states in ((out_train, "train", train_states), (out_test, "test", test_states)):
        meta = out / "split.json"
        links = find_links(out) if out.is_dir() else []
        if links:
            raise LinkError(f"{str(links[0])!r} in the split folder {str(out)!r} is a symbolic link; links are never followed (remove it)")
        if out.exists() and any(out.iterdir()):
            old = json.loads(meta.read_text()) if meta.is_file() else None
            same_zoo = isinstance(old, dict) and old.get("zoo") in (info["zoo"], str(zoo.path.resolve()))  # older splits kept the whole path
            if not same_zoo or not isinstance(old, dict) or old.get("models") != [s.model.name for s in states]:
                raise ZooError(f"{str(out)!r} is not empty and holds another split; give a new or empty folder")
    for out, name, states in ((out_train, "train", train_states), (out_test, "test", test_states)):
        write_split(zoo, name, states, out, link, info)
    return {
        "train": {"models": len(train_states), "poisoned": sum(s.model.group.poisoned for s in train_states)},
        "test": {"models": len(test_states), "poisoned": sum(s.model.group.poisoned for s in test_states)},
    }
