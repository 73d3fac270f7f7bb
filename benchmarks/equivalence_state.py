"""Carry ``gpu_checks.sh OUT equivalence``'s group runs from one GPU lease to the next.

    python benchmarks/equivalence_state.py pack SCRATCH OUT/equivalence_state.tar.gz
    python benchmarks/equivalence_state.py unpack STATE.tar.gz SCRATCH

A lease is 15 minutes on a bare machine, and 20 seeds of a world in one CUDA group may need more
than one (LavaWorld FC: 2.05 M frames a seed to converge alone, 41 M for 20). ``pack`` keeps what
the next lease needs to go on: every finished run's ``metrics.json``, ``config.json`` and
``log.csv`` (the report reads them), and every unfinished run's checkpoint, world by world while
the archive stays under ``--limit-mib`` (a lease returns files of at most 16 MiB). A world whose
checkpoints do not fit (Randomized LavaWorld's CNN: 3.7 MB each) keeps its finished runs and
starts the others again. ``unpack`` restores them (data only: no links, no paths outside
SCRATCH), and both print per world what is there, with each checkpoint's frames and the wall
seconds it carries across resumes, so the log shows that a run went on rather than restarted.
"""

from __future__ import annotations

import argparse
import sys
import tarfile
from pathlib import Path

KEEP_FINISHED = ("metrics.json", "config.json", "log.csv")
KEEP_STARTED = ("config.json", "log.csv", "checkpoint.pt")


def runs(scratch: Path) -> dict[str, tuple[list[Path], list[Path]]]:
    """WORLD -> its group runs' folders (``WORLD/group/sN``, in seed order): the finished ones
    (a ``metrics.json``) and the started ones (a checkpoint, no ``metrics.json``)."""
    found: dict[str, tuple[list[Path], list[Path]]] = {}
    for run in sorted(scratch.glob("*/group/s*"), key=lambda p: (p.parts[-3], int(p.name[1:]) if p.name[1:].isdigit() else -1)):
        finished, started = found.setdefault(run.parts[-3], ([], []))
        if (run / "metrics.json").is_file():
            finished.append(run)
        elif (run / "checkpoint.pt").is_file():
            started.append(run)
    return found


def checkpoint_state(path: Path) -> tuple[int, float]:
    """A checkpoint's frames and the wall seconds it carries (read as data: ``weights_only``)."""
    import torch

    state = torch.load(path, map_location="cpu", weights_only=True)
    return int(state["frames"]), float(state["elapsed"])


def describe(scratch: Path) -> list[str]:
    lines = []
    for world, (finished, started) in runs(scratch).items():
        text = ", ".join(f"{f.name} at {frames:,} frames ({wall:.0f} wall-s)" for f in started for frames, wall in [checkpoint_state(f / "checkpoint.pt")])
        lines.append(f"{world}: {len(finished)} finished, {len(started)} with checkpoints{': ' + text if text else ''}")
    return lines


def pack(scratch: Path, archive: Path, limit_mib: float) -> list[str]:
    """Write ARCHIVE (tar.gz) from SCRATCH; the lines say what it holds and what was left out."""
    limit = int(limit_mib * 2**20)
    members: list[tuple[Path, str]] = []
    left_out = []
    for world, (finished, started) in runs(scratch).items():
        members += [(f / n, f"{world}/group/{f.name}/{n}") for f in finished for n in KEEP_FINISHED if (f / n).is_file()]
        extra = [(f / n, f"{world}/group/{f.name}/{n}") for f in started for n in KEEP_STARTED if (f / n).is_file()]
        if extra and _size(members + extra) > limit:  # (compressed weights are not much smaller: counted raw)
            left_out.append(f"{world}: {len(started)} checkpoints left out ({_size(extra) / 2**20:.1f} MiB; over {limit_mib} MiB): they start again")
        else:
            members += extra
    archive.parent.mkdir(parents=True, exist_ok=True)
    part = archive.with_name(archive.name + ".part")
    with tarfile.open(part, "w:gz") as tar:
        for path, name in members:
            tar.add(path, arcname=name, recursive=False)
    part.replace(archive)
    return [*left_out, f"packed {len(members)} files into {archive.name} ({archive.stat().st_size / 2**20:.1f} MiB)"]


def _size(members: list[tuple[Path, str]]) -> int:
    return sum(path.stat().st_size for path, _ in members)


def unpack(archive: Path, scratch: Path) -> None:
    """Restore ARCHIVE into SCRATCH: regular files under WORLD/group/sN/ with the names pack keeps."""
    allowed = set(KEEP_FINISHED) | set(KEEP_STARTED)
    with tarfile.open(archive, "r:gz") as tar:
        members = tar.getmembers()
        for member in members:  # all checked before anything is written
            parts = Path(member.name).parts
            if not (member.isfile() and len(parts) == 4 and parts[1] == "group" and parts[2][:1] == "s" and parts[3] in allowed and ".." not in parts):
                raise SystemExit(
                    f"equivalence_state: error: {archive}: unexpected member {member.name!r} (allowed: WORLD/group/sN/{{{','.join(sorted(allowed))}}})"
                )
        for member in members:
            target = scratch.joinpath(*Path(member.name).parts)
            target.parent.mkdir(parents=True, exist_ok=True)
            source = tar.extractfile(member)
            assert source is not None
            target.write_bytes(source.read())


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="verb", required=True)
    p = sub.add_parser("pack", help="SCRATCH -> ARCHIVE")
    p.add_argument("scratch", type=Path)
    p.add_argument("archive", type=Path)
    p.add_argument("--limit-mib", type=float, default=15.0)
    u = sub.add_parser("unpack", help="ARCHIVE -> SCRATCH")
    u.add_argument("archive", type=Path)
    u.add_argument("scratch", type=Path)
    args = parser.parse_args(argv)
    if args.verb == "pack":
        lines = pack(args.scratch, args.archive, args.limit_mib)
        print("\n".join(f"state: {line}" for line in [*describe(args.scratch), *lines]), flush=True)
    else:
        if not args.archive.is_file():
            print(f"equivalence_state: error: EQ_STATE {args.archive} is not a file", file=sys.stderr)
            return 2
        unpack(args.archive, args.scratch)
        print("\n".join(f"resumed: {line}" for line in describe(args.scratch)), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
