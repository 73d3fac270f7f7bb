"""The model folder, the unit of a zoo (TrojAI layout).

``model.pt`` (state dict), ``config.json`` (everything to rebuild and retrain),
``metrics.json`` (written last: its presence marks the folder complete),
``log.csv`` (one row per evaluation), ``ground_truth.csv`` (1 poisoned / 0 clean),
``training_curve.png``, and while training runs, ``checkpoint.pt`` for resuming.
"""

from __future__ import annotations

import csv
import io
import json
from pathlib import Path

import torch

from rlbackdoors.config import RunConfig
from rlbackdoors.io import atomic_write, atomic_write_text

FILES = ("model.pt", "config.json", "metrics.json", "log.csv", "ground_truth.csv", "training_curve.png", "checkpoint.pt")


class FolderError(RuntimeError):
    """The folder cannot be used as asked (already complete, or holds another run)."""


class ModelFolder:
    def __init__(self, path: str | Path):
        self.path = Path(path)
        if self.path.exists() and not self.path.is_dir():
            raise FolderError(f"{str(self.path)!r} exists and is not a folder")

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

    # --- writing -------------------------------------------------------------------------
    def begin(self, cfg, overwrite: bool = False) -> dict | None:
        """Open the folder for training ``cfg`` (a run config): refuse a finished model unless
        ``overwrite``; return the checkpoint of an interrupted run of the same config (None for
        a fresh start); refuse one of another config. Writes ``config.json``."""
        if overwrite:
            self.clear()
        elif self.complete:
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
        self.write_config(cfg)
        return checkpoint

    def write_config(self, cfg: RunConfig) -> None:
        atomic_write_text(self.file("config.json"), cfg.to_json())

    def write_json(self, name: str, data: dict) -> None:
        atomic_write_text(self.file(name), json.dumps(data, indent=2, sort_keys=True) + "\n")

    def write_log(self, rows: list[dict]) -> None:
        if not rows:
            return
        buf = io.StringIO()
        writer = csv.DictWriter(buf, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
        atomic_write_text(self.file("log.csv"), buf.getvalue())

    def write_ground_truth(self, poisoned: bool) -> None:
        atomic_write_text(self.file("ground_truth.csv"), f"{int(poisoned)}\n")

    def save_torch(self, name: str, obj) -> None:
        atomic_write(self.file(name), lambda tmp: torch.save(obj, tmp))

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
        try:
            return torch.load(self.file("checkpoint.pt"), map_location="cpu", weights_only=False)
        except Exception as err:
            raise FolderError(f"checkpoint in {str(self.path)!r} is unreadable ({err}); pass --overwrite to start over") from None


def _number_or_text(value: str):
    """log.csv cells are numbers except labels such as the curriculum phase."""
    try:
        return float(value)
    except ValueError:
        return value
