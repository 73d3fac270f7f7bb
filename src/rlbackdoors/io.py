"""Files as a zoo needs them: atomic writes, identical bytes for identical contents, loads that
never run code, and one lock per folder.

* Atomic: a crash mid-write leaves the old file (or none), never half of a new one. The temp
  file is ``.NAME.PID.rlbtmp`` beside the target: recognisable, so a later start of the same
  folder removes what a killed writer left (:func:`remove_stale_temp_files`).
* Same contents, same bytes: ``torch.save`` names its zip archive after the file it writes,
  so saving through a temp file put the temp file's random name inside ``model.pt``. We
  serialise to memory first (archive name ``archive``) and write those bytes.
* Loading is data only: ``torch.load(weights_only=True)``; a file that needs the unpickler
  to build objects is refused with :class:`UnsafeFileError`, whatever it holds.
* Links are never followed inside a zoo or a model folder (:func:`refuse_links`,
  :func:`find_links`, :func:`open_beneath`): a dataset is unpacked from archives people pass
  around, and a planted link must not make us read, write or delete outside it. Temp files
  are created with ``O_EXCL | O_NOFOLLOW``, so a link planted under a temp file's name is
  never written through.
* :class:`FolderLock`: an ``flock`` on ``.lock`` in the folder. The kernel drops it when the
  holder dies, however it dies, so a crashed holder never leaves a folder stuck; a live
  holder is named (pid, host, start time) in the refusal.
"""

from __future__ import annotations

import collections
import errno
import fcntl
import io
import json
import os
import pickle
import warnings
import shutil
import socket
import stat
import time
from pathlib import Path
from typing import Callable

TEMP_SUFFIX = ".rlbtmp"
LOCK_NAME = ".lock"


class UnsafeFileError(ValueError):
    """A file that is not plain data (tensors, arrays, numbers, strings) was refused unread."""


class LockedError(RuntimeError):
    """Another live process holds the folder's lock."""


class LinkError(ValueError):
    """A path inside a zoo or a model folder is a symbolic link: it is refused, never followed."""


def refuse_links(root: str | Path, path: str | Path, what: str = "zoo") -> Path:
    """``path`` itself and every folder between ``root`` and it, refused if one is a symbolic link
    (``root`` is the user's own argument and may be one). Returns ``path``."""
    root, path = Path(root), Path(path)
    try:
        parts = path.relative_to(root).parts
    except ValueError:
        raise LinkError(f"{str(path)!r} is not inside the {what} {str(root)!r}") from None
    here = root
    for part in parts:
        here = here / part
        if part in ("..", ".") or here.is_symlink():
            raise LinkError(f"{str(here)!r} inside the {what} {str(root)!r} is a symbolic link; links are never followed in a {what} (remove it)")
    return path


def find_links(root: str | Path) -> list[Path]:
    """Every symbolic link below ``root``, found without following any (sorted)."""
    found: list[Path] = []
    for top, dirs, files in os.walk(root, followlinks=False):
        for name in dirs + files:
            path = Path(top) / name
            if path.is_symlink():
                found.append(path)
    return sorted(found)


def open_beneath(root: str | Path, path: str | Path, what: str = "zoo") -> int:
    """A file descriptor of the folder ``path`` under ``root``, each step opened with
    ``O_NOFOLLOW``: what is written through ``/proc/self/fd/N`` lands in that folder even if a
    link is swapped in at its path afterwards. The caller closes it."""
    root, path = Path(root), Path(path)
    refuse_links(root, path, what)
    flags = os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW | os.O_CLOEXEC
    fd = os.open(root, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
    try:
        for part in path.relative_to(root).parts:
            try:
                nxt = os.open(part, flags, dir_fd=fd)
            except OSError as err:
                if err.errno in (errno.ELOOP, errno.ENOTDIR):
                    raise LinkError(
                        f"{str(path)!r} inside the {what} {str(root)!r} is not a real folder (a link was swapped in); it is never followed"
                    ) from None
                raise
            os.close(fd)
            fd = nxt
    except BaseException:
        os.close(fd)
        raise
    return fd


def fd_path(fd: int, fallback: Path) -> Path:
    """The path that reaches the open folder ``fd`` whatever is renamed or linked meanwhile
    (Linux); ``fallback`` elsewhere."""
    path = Path(f"/proc/self/fd/{fd}")
    return path if path.is_dir() else fallback


def _temp_path(path: Path) -> Path:
    return path.with_name(f".{path.name}.{os.getpid()}{TEMP_SUFFIX}")


def atomic_write(path: str | Path, write: Callable[[str], None]) -> Path:
    """Call ``write(tmp_path)`` on a temp file in the same folder, then rename it onto ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _temp_path(path)
    try:
        _create_temp(tmp)
        write(str(tmp))
        os.chmod(tmp, 0o666 & ~_umask())  # zoo files are meant to be shared
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def _create_temp(tmp: Path) -> None:
    """Create the temp file anew, never through a link planted under its name."""
    for _ in range(2):
        try:
            os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC, 0o600))
            return
        except FileExistsError:
            tmp.unlink()  # a killed writer's of our pid, or a planted link: removed, not followed
    raise FileExistsError(errno.EEXIST, "temp file keeps reappearing", str(tmp))


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def atomic_write_bytes(path: str | Path, data: bytes) -> Path:
    def write(tmp: str) -> None:
        with open(os.open(tmp, os.O_WRONLY | os.O_TRUNC | os.O_NOFOLLOW | os.O_CLOEXEC), "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())

    return atomic_write(path, write)


def atomic_write_text(path: str | Path, text: str) -> Path:
    return atomic_write_bytes(path, text.encode())


def torch_bytes(obj) -> bytes:
    """``torch.save(obj)`` as bytes, with a fixed archive name: same contents, same bytes."""
    import torch

    buf = io.BytesIO()
    torch.save(obj, buf)
    return buf.getvalue()


def save_torch(path: str | Path, obj) -> Path:
    """Atomically write ``obj``, which must be plain data (tensors, numbers, strings, bytes,
    containers): checked here, so a file we write always loads with ``weights_only=True``."""
    check_plain(obj, Path(path).name)
    return atomic_write_bytes(path, torch_bytes(obj))


def check_plain(obj, where: str = "value") -> None:
    """Raise :class:`TypeError` naming the first part of ``obj`` that is not plain data."""
    import torch

    if obj is None or isinstance(obj, (bool, int, float, str, bytes, torch.Tensor)):
        if isinstance(obj, torch.Tensor) and type(obj) is not torch.Tensor and not isinstance(obj, torch.nn.Parameter):
            raise TypeError(f"{where}: {type(obj).__name__} is not a plain tensor")
        return
    if isinstance(obj, (list, tuple)) and type(obj) in (list, tuple):
        for i, value in enumerate(obj):
            check_plain(value, f"{where}[{i}]")
        return
    if type(obj) in (dict, collections.OrderedDict):
        for key, value in obj.items():
            if not isinstance(key, (str, int)):
                raise TypeError(f"{where}: key {key!r} is not a string or integer")
            check_plain(value, f"{where}.{key}")
        return
    raise TypeError(f"{where}: {type(obj).__module__}.{type(obj).__name__} is not plain data")


def load_torch(path: str | Path, what: str = "file"):
    """``torch.load`` of plain data only; anything that needs the unpickler is refused unread.

    ``what`` names the file in errors ("weights file", "checkpoint"). Raises
    :class:`FileNotFoundError`, :class:`UnsafeFileError` or :class:`ValueError` (unreadable).
    """
    import torch

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{what} {str(path)!r} does not exist")
    try:
        with warnings.catch_warnings():  # torch warns of a raw pickle's protocol, naming its own install path
            warnings.simplefilter("ignore", UserWarning)
            return torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as err:
        lines = [line.strip() for line in str(err).splitlines()]
        # "Unsupported global: ..." or "Trying to load unsupported GLOBAL posix.system ..." (torch 2.6+)
        detail = next((line for line in lines if "unsupported" in line.lower()), first_line(err))
        if "global" in detail.lower():  # it names a class or function to call: an object, maybe code
            raise UnsafeFileError(
                f"refused to load {what} {str(path)!r}: it holds Python objects, not plain tensors and numbers "
                "(loading it could run code; re-save it as a state dict)"
            ) from None
        raise ValueError(f"cannot read {what} {str(path)!r}: not a torch file of plain data ({detail.removeprefix('WeightsUnpickler error: ')})") from None
    except Exception as err:  # truncated zip, random bytes, wrong format
        raise ValueError(f"cannot read {what} {str(path)!r}: {first_line(err)}") from None


def first_line(err: BaseException) -> str:
    text = str(err).strip()
    return text.splitlines()[0] if text else type(err).__name__


def remove_tree(path: Path) -> None:
    """Remove a folder we own, or a symlink (or file) planted in its place, never what a link points to."""
    if path.is_symlink() or path.is_file():
        path.unlink(missing_ok=True)
    elif path.is_dir():
        shutil.rmtree(path, ignore_errors=True)


def remove_stale_temp_files(folder: str | Path) -> list[Path]:
    """Remove temp files that a killed writer left in ``folder`` (call it holding the folder's lock)."""
    folder = Path(folder)
    removed: list[Path] = []
    if not folder.is_dir():
        return removed
    for path in folder.rglob(f".*{TEMP_SUFFIX}"):
        try:
            path.unlink()
            removed.append(path)
        except FileNotFoundError:
            pass
    return removed


class FolderLock:
    """An exclusive, non-blocking ``flock`` on ``FOLDER/.lock``, held for a ``with`` block.

    The lock file stays (removing it would race with a new holder); it holds the last
    holder's pid, host and start time, for the message a refused process prints.
    """

    def __init__(self, folder: str | Path, what: str = "folder"):
        self.folder = Path(folder)
        self.path = self.folder / LOCK_NAME
        self.what = what
        self._fd: int | None = None

    def acquire(self) -> FolderLock:
        self.folder.mkdir(parents=True, exist_ok=True)
        # O_NOFOLLOW: a planted symlink must not make us overwrite the file it points to.
        flags = os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC
        try:
            fd = os.open(self.path, flags, 0o666 & ~_umask())
        except OSError as err:
            if err.errno == errno.ELOOP:
                raise LockedError(f"{self.what} {str(self.folder)!r}: {LOCK_NAME} is a symbolic link; remove it") from None
            raise
        try:
            if not stat.S_ISREG(os.fstat(fd).st_mode):
                raise LockedError(f"{self.what} {str(self.folder)!r}: {LOCK_NAME} is not a regular file; remove it")
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError as err:
                if err.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                    raise LockedError(f"{self.what} {str(self.folder)!r} is in use by {self.holder()}; wait for it or stop it first") from None
                raise
            # The file we locked must still be the one at the path: a failed start removes the
            # .lock it created, and a lock on that removed file would guard nothing.
            here = os.stat(self.path, follow_symlinks=False) if os.path.lexists(self.path) else None
            mine = os.fstat(fd)
            if here is None or (here.st_dev, here.st_ino) != (mine.st_dev, mine.st_ino):
                raise LockedError(f"{self.what} {str(self.folder)!r} was being set up by another process; try again")
            holder = {"pid": os.getpid(), "host": socket.gethostname(), "since": time.strftime("%Y-%m-%d %H:%M:%S")}
            os.ftruncate(fd, 0)
            os.pwrite(fd, (json.dumps(holder) + "\n").encode(), 0)
        except BaseException:
            os.close(fd)
            raise
        self._fd = fd
        return self

    def holder(self) -> str:
        try:
            info = json.loads(self.path.read_text() or "{}")
            return f"process {info['pid']} on {info['host']} (since {info['since']})"
        except (OSError, ValueError, KeyError, TypeError):
            return "another process"

    def release(self) -> None:
        if self._fd is not None:
            fcntl.flock(self._fd, fcntl.LOCK_UN)
            os.close(self._fd)
            self._fd = None

    @property
    def held(self) -> bool:
        return self._fd is not None

    def __enter__(self) -> FolderLock:
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()
