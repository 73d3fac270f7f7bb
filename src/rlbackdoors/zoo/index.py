"""What a zoo holds, read from its folders: each model's state, METADATA.csv and the status table.

Everything here is derived from the model folders (config.json, metrics.json, failed.json,
reduced-config.json, the folder lock), so it can be rebuilt at any time and never disagrees
with the files.

A model is ``converged`` when its thresholds hold on its FINAL evaluation
(``metrics.json: converged``), not on a noisy mid-training one; the dataset holds
converged models only.
"""

from __future__ import annotations

import csv
import io
import json
import math
from collections.abc import Collection
from dataclasses import dataclass
from pathlib import Path

from rlbackdoors.io import atomic_write_text
from rlbackdoors.zoo.job import COMPLETE_MARK, FAILED, is_locked
from rlbackdoors.zoo.plan import PlannedModel, Zoo
from rlbackdoors.zoo.spec import Group, flatten

# status of a model: done (complete dataset entry), failed (recorded, retried only on request),
# running (a live process holds its folder), pending (not finished: new, started or finishing),
# unverified (failed zoo verify and left out on request: never read)
STATUSES = ("done", "failed", "running", "pending", "unverified")
LEAD_COLUMNS = ("model_name", "cell", "world", "arch", "trigger_family", "attack", "poisoned", "attempt", "status", "converged", "nonconverged_reason")


@dataclass
class ModelState:
    model: PlannedModel
    folder: Path
    status: str
    config: dict | None = None
    metrics: dict | None = None
    failure: dict | None = None

    @property
    def converged(self) -> bool:
        return self.status == "done" and bool(self.metrics and self.metrics.get("converged"))

    @property
    def reason(self) -> str:
        """Why the model is outside the dataset ("" for converged or unfinished ones)."""
        if self.status in ("failed", "unverified"):
            return f"{self.status}: {(self.failure or {}).get('error', 'unknown error')}"
        if self.status != "done" or self.converged:
            return ""
        return nonconverged_reason(self.metrics or {}, self.config or {})


def read_json(path: Path) -> dict | None:
    try:
        data = json.loads(path.read_bytes().decode("utf-8"))
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def nonconverged_reason(metrics: dict, config: dict) -> str:
    """E.g. ``clean_sr 0.930 < 0.98``: the thresholds the final evaluation missed."""
    train = config.get("train", {}) if isinstance(config.get("train"), dict) else {}
    poisoned = bool(config.get("poison", {}).get("poisoned", metrics.get("poisoned")))
    parts = []
    for key, threshold, applies in (
        ("clean_sr", train.get("clean_threshold"), True),
        ("poisoned_sr", train.get("poisoned_threshold"), poisoned),
    ):
        value = metrics.get(key)
        if applies and isinstance(threshold, (int, float)) and not (isinstance(value, (int, float)) and value >= threshold):
            parts.append(f"{key} {value:.3f} < {threshold:g}" if isinstance(value, (int, float)) else f"{key} missing")
    if not parts and metrics.get("curriculum_switch_frames", 0) is None:
        parts.append("the curriculum never switched to the full world")
    return "; ".join(parts) or "final evaluation below its thresholds"


def model_state(zoo: Zoo, model: PlannedModel, probe: bool = True) -> ModelState:
    folder = zoo.folder(model)
    config = read_json(folder / "config.json")
    metrics_path = folder / "metrics.json"
    if metrics_path.is_file() and (folder / COMPLETE_MARK).is_file():
        return ModelState(model, folder, "done", config, read_json(metrics_path))
    if (folder / FAILED).is_file():
        return ModelState(model, folder, "failed", config, read_json(metrics_path), read_json(folder / FAILED))
    if probe and is_locked(folder):
        return ModelState(model, folder, "running", config)
    return ModelState(model, folder, "pending", config)


def scan(zoo: Zoo, probe: bool = True, skip: dict[str, str] | None = None) -> list[ModelState]:
    """Every planned model's state, by id; ``skip`` (name -> why, from zoo verify): models left
    out as ``unverified``, their folders not read."""
    skip = skip or {}
    return [
        ModelState(m, zoo.folder(m), "unverified", failure={"error": skip[m.name]}) if m.name in skip else model_state(zoo, m, probe) for m in zoo.all_planned()
    ]


def _cell_fields(group: Group) -> dict:
    cell = group.cell
    return {"cell": cell.key, "world": cell.world, "arch": cell.arch_label, "trigger_family": cell.trigger.name, "attack": cell.attack.attack}


def metadata_rows(states: list[ModelState]) -> list[dict]:
    rows = []
    for s in states:
        row = {
            "model_name": s.model.name,
            **_cell_fields(s.model.group),
            "poisoned": s.model.group.poisoned,
            "attempt": s.model.attempt,
            "status": s.status,
            "converged": s.converged,
            "nonconverged_reason": s.reason,
        }
        row.update(flatten(s.config or {}))
        row.update({f"metrics.{k}": v for k, v in flatten(s.metrics or {}).items()})
        rows.append(row)
    return rows


def _cell(value) -> str:
    if value is None:
        return ""
    if isinstance(value, float) and math.isnan(value):
        return "nan"
    if isinstance(value, (list, tuple, dict)):
        return json.dumps(value, sort_keys=True)
    return str(value)


def csv_text(rows: list[dict], lead: tuple[str, ...] = ()) -> str:
    """Rows as CSV; columns: ``lead`` first, then config columns, then metrics.* (each sorted)."""
    keys = dict.fromkeys(k for row in rows for k in row)
    rest = sorted(k for k in keys if k not in lead)
    columns = [k for k in lead if k in keys or not rows] + [k for k in rest if not k.startswith("metrics.")] + [k for k in rest if k.startswith("metrics.")]
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(columns)
    for row in rows:
        writer.writerow([_cell(row.get(k)) for k in columns])
    return buf.getvalue()


def write_metadata(zoo: Zoo, states: list[ModelState] | None = None, path: Path | None = None) -> Path:
    """``ZOO/METADATA.csv``: one row per planned model (converged or not), TrojAI style."""
    states = scan(zoo, probe=False) if states is None else states
    return atomic_write_text(path or zoo.path / "METADATA.csv", csv_text(metadata_rows(states), LEAD_COLUMNS))


def read_metadata(path: str | Path) -> list[dict[str, str]]:
    """METADATA.csv's rows; ValueError naming the file if it is not UTF-8 CSV."""
    try:
        return list(csv.DictReader(io.StringIO(Path(path).read_bytes().decode("utf-8"), newline="")))
    except (UnicodeDecodeError, csv.Error) as err:
        raise ValueError(f"{str(path)!r} is not a METADATA.csv of UTF-8 text ({err})") from None


@dataclass
class GroupCounts:
    group: Group
    planned: int = 0
    converged: int = 0
    not_converged: int = 0
    failed: int = 0
    running: int = 0
    pending: int = 0
    unverified: int = 0

    @property
    def finished(self) -> bool:
        """Nothing more will be trained: enough converged, or every attempt used and finished."""
        return self.converged >= self.group.wanted or (self.planned >= self.group.max_attempts and self.pending == 0 and self.running == 0)


def group_counts(zoo: Zoo, states: list[ModelState], running: Collection[int] = ()) -> list[GroupCounts]:
    """Per group; ``running`` adds ids the caller is training itself."""
    counts = {g.index: GroupCounts(g) for g in zoo.spec.groups}
    for s in states:
        c = counts[s.model.group.index]
        c.planned += 1
        if s.status == "done":
            if s.converged:
                c.converged += 1
            else:
                c.not_converged += 1
        elif s.status == "failed":
            c.failed += 1
        elif s.status == "unverified":
            c.unverified += 1
        elif s.status == "running" or s.model.id in running:
            c.running += 1
        else:
            c.pending += 1
    return list(counts.values())


def status_table(zoo: Zoo, states: list[ModelState]) -> str:
    """The table ``rlbackdoors zoo status`` prints: per cell and label."""
    head = ("cell", "label", "wanted", "converged", "not conv.", "failed", "running", "left", "attempts", "state")
    rows = []
    total = [0] * 6
    for c in group_counts(zoo, states):
        state = "complete" if c.converged >= c.group.wanted else ("unverified" if c.unverified else "short" if c.finished else "open")
        numbers = (c.group.wanted, c.converged, c.not_converged, c.failed, c.running, c.pending)
        total = [t + n for t, n in zip(total, numbers)]
        rows.append((c.group.cell.key, c.group.label, *map(str, numbers), f"{c.planned}/{c.group.max_attempts}", state))
    rows.append(("total", "", *map(str, total), "", ""))
    widths = [max(len(str(r[i])) for r in [head, *rows]) for i in range(len(head))]
    lines = ["  ".join(str(v).ljust(w) if i < 2 else str(v).rjust(w) for i, (v, w) in enumerate(zip(r, widths))) for r in [head, *rows]]
    lines.insert(1, "  ".join("-" * w for w in widths))
    lines.insert(len(lines) - 1, "  ".join("-" * w for w in widths))
    return "\n".join(lines)
