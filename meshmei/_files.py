"""Writing result directories atomically, so an interrupted write is never taken for a finished one."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import tempfile
import threading
import time
import uuid
from pathlib import Path
from typing import Callable

__all__ = ["atomic_directory", "check_apart", "check_creatable", "check_output", "check_replaceable", "RESULT_MARKERS"]

# One of these files is in every folder meshmei writes (a 3D-MEI run, a diverse set, a sweep, a
# reconstruction), with the keys listed: a folder that holds none of them (and is not empty) is not meshmei's
# to replace. The names alone are common (a training script's history.json): the keys are checked too.
RESULT_MARKERS = {"summary.json": ("format", "complete", "neuron", "activation"),
                  "diversity.json": ("responses", "dissimilarity"),
                  "sweep.json": ("format", "complete", "kind", "axes"),
                  "history.json": ("settings", "final", "history", "metrics")}


def atomic_directory(directory, write: Callable[[Path], None], *, overwrite: bool = False,
                     error: type[Exception] = ValueError, kinds=None) -> Path:
    """Build ``directory`` by calling ``write(tmp)`` on a hidden temporary sibling, then rename it into place.

    Until ``write`` returns, only ``.NAME.partial-XXXXXXXX`` exists (and is removed if ``write`` raises);
    an existing ``directory`` is replaced only with ``overwrite``, after the new one is complete. Without
    ``overwrite`` it is never replaced, also when another process put it there while ``write`` ran (the
    rename onto it fails, and the new folder is removed).

    ``overwrite`` replaces only what meshmei wrote: an empty folder, or one holding one of
    :data:`RESULT_MARKERS` with meshmei's keys in it (of ``kinds``, when given: the markers the caller
    writes). A folder of other files (``--out ~/data --overwrite`` by mistake) or a file in the way is never
    removed.

    Raises
    ------
    error
        ``directory`` exists and ``overwrite`` is False, before ``write`` or after it; or ``directory`` is
        a file, or a folder of files meshmei did not write (the caller's exception type).
    """
    directory = Path(directory)
    check_output(directory, overwrite=overwrite, error=error, kinds=kinds)
    directory.parent.mkdir(parents=True, exist_ok=True)
    tmp = directory.parent / f".{directory.name}.partial-{uuid.uuid4().hex[:8]}"
    tmp.mkdir()
    try:
        write(tmp)
        _sync_tree(tmp)  # on disk before the rename makes it a finished result (a node that loses power)
        if directory.exists() and overwrite:
            trash = directory.parent / f".{directory.name}.old-{uuid.uuid4().hex[:8]}"
            os.replace(directory, trash)
            os.replace(tmp, directory)
            shutil.rmtree(trash, ignore_errors=True)
        else:
            try:
                os.rename(tmp, directory)  # onto a folder that landed meanwhile: fails (it is not empty)
            except OSError:
                if directory.exists():
                    raise error(_exists(directory, _API)) from None
                raise
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    _sync(directory.parent)
    _remove_stale(directory)
    return directory


# a temporary sibling untouched this long was left by a process killed while it wrote (SIGKILL, power):
# writing takes seconds (the results are computed before), so no live writer's folder is this old
STALE_SECONDS = 3600.0


# the hidden temporary folders in each parent, listed once per process: a population writes thousands of
# neuron folders into one parent, and a listing at every write would make its saves quadratic in their count
_LEFT_OVER: dict[Path, set[str]] = {}


def _remove_stale(directory: Path) -> None:
    """Remove the temporary siblings of ``directory`` (``.NAME.partial-*``, ``.NAME.old-*``) that a killed
    process left, once ``directory`` has been written whole: they were never removed before."""
    parent = directory.parent.resolve()
    if parent not in _LEFT_OVER:
        try:
            with os.scandir(parent) as entries:
                _LEFT_OVER[parent] = {e.name for e in entries
                                      if e.name.startswith(".") and (".partial-" in e.name or ".old-" in e.name)}
        except OSError:
            _LEFT_OVER[parent] = set()
    left = _LEFT_OVER[parent]
    prefixes = tuple(f".{directory.name}.{kind}-" for kind in ("partial", "old"))
    now = time.time()
    for name in [n for n in left if n.startswith(prefixes)]:
        left.discard(name)  # looked at once: a recent one is a live writer's, and stays
        stale = parent / name
        try:
            if stale.is_dir() and not stale.is_symlink() and now - stale.stat().st_mtime > STALE_SECONDS:
                shutil.rmtree(stale, ignore_errors=True)
        except OSError:  # gone meanwhile, or not ours to read: left as it is
            continue


def _sync(path: Path) -> None:
    """fsync a file or a folder (its entries); where the system cannot (a folder on Windows), nothing."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _sync_tree(root: Path) -> None:
    """fsync every file under ``root`` and the folders that hold them: a result renamed into place after a
    crash is whole, not files of zero length (a review emptied state.pt by hand, and the resume took the neuron
    for finished)."""
    for folder, _, files in os.walk(root):
        for name in files:
            _sync(Path(folder) / name)
        _sync(Path(folder))


_API = "overwrite=True (CLI: --overwrite)"


def _exists(directory, how: str) -> str:
    return f"{directory} exists; pass {how} to replace it"


def check_output(directory, *, overwrite: bool, error, how: str = _API, kinds=None) -> None:
    """Raise ``error`` unless ``directory`` may be written: it does not exist, or ``overwrite`` is given and
    it is an empty folder or a meshmei result (:func:`check_replaceable`). Commands call it before their
    work (``how="--overwrite"``), so that a refused output costs no run; :func:`atomic_directory` again."""
    directory = Path(directory)
    if directory.exists() and not overwrite:
        raise error(_exists(directory, how))
    here = Path.cwd()
    if directory.exists() and (directory.resolve() == here or directory.resolve() in here.parents):
        # its replacement was refused by the system (errno 16) after the run
        raise error(f"{directory} is the current folder or holds it; it cannot be replaced: choose another "
                    "output folder")
    if directory.exists() or directory.is_symlink():
        check_replaceable(directory, error, kinds)
    check_creatable(directory, error)


def check_creatable(directory, error) -> None:
    """Raise ``error`` unless the nearest existing folder above ``directory`` is a folder this process can make
    a folder in, by making and removing one (``--out afile/sub`` failed with errno 17 or 20, after the run)."""
    directory = Path(directory)
    above = next((p for p in directory.absolute().parents if p.exists()), None)
    if above is not None and not above.is_dir():
        raise error(f"cannot make {directory}: {above} is a file, not a folder; choose another output path")
    if above is not None:  # the system's word: no permission, a read-only disk, /proc (which passed os.access)
        try:
            os.rmdir(tempfile.mkdtemp(prefix=".meshmei-probe-", dir=above))
        except OSError as err:
            raise error(f"cannot make {directory}: {above} takes no new folder ({err.strerror}); choose another "
                        "output path") from None


def check_apart(out, source, error, what: str = "the input") -> None:
    """Raise ``error`` when the output folder ``out`` is ``source`` or holds it: replacing it would delete
    ``source`` (``meshmei tune --out RUN --overwrite`` replaced the run it swept)."""
    out, source = Path(out).resolve(), Path(source).resolve()
    if out == source or out in source.parents:
        raise error(f"the output folder {out} is {what} ({source}) or holds it; replacing it would delete it: "
                    "choose another output folder")


def check_replaceable(directory, error, kinds=None) -> None:
    """Raise ``error`` unless ``directory`` is an empty folder or one that meshmei wrote; with ``kinds`` (names
    in :data:`RESULT_MARKERS`), one holding a result of those kinds (``meshmei tune --out RUN/member_1
    --overwrite`` replaced a 3D-MEI run with a sweep)."""
    directory = Path(directory)
    if directory.is_symlink() or not directory.is_dir():
        raise error(f"{directory} is {'a link' if directory.is_symlink() else 'a file'}, not a result folder; "
                    "it is not replaced, even with overwrite: choose another output path")
    found = [name for name, keys in RESULT_MARKERS.items() if _is_marker(directory / name, keys)]
    if any(directory.iterdir()) and not found:
        lookalike = [name for name in RESULT_MARKERS if (directory / name).exists()]  # named so, not meshmei's
        why = f"; its {', '.join(lookalike)} is not one meshmei wrote" if lookalike else ""
        raise error(f"{directory} holds files meshmei did not write (no result file of meshmei's: "
                    f"{', '.join(RESULT_MARKERS)}{why}); it is not replaced, even with overwrite: choose another "
                    "output folder, or empty it yourself")
    if kinds is not None and found and not set(found) & set(kinds):  # a sweep's --out naming a 3D-MEI run
        raise error(f"{directory} holds another kind of meshmei result ({', '.join(found)}, where this command "
                    f"writes {' or '.join(kinds)}); it is not replaced, even with overwrite: choose another output "
                    "folder")


def _is_marker(path: Path, keys) -> bool:
    """Whether ``path`` is a JSON object with all of ``keys``: a result file meshmei wrote."""
    if not path.is_file():
        return False
    try:
        with open(path) as fh:
            data = json.load(fh)
    except (OSError, UnicodeDecodeError, ValueError):
        return False
    return isinstance(data, dict) and all(k in data for k in keys)


@contextlib.contextmanager
def terminate_as_interrupt():
    """SIGTERM (a scheduler cancelling the job, ``kill``) raises KeyboardInterrupt for the block, so that it
    ends a run as Ctrl-C does: what finished is kept, what was being written is written whole or not at all.
    Outside the main thread, where Python takes no signal handler, nothing changes."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, frame):
        raise KeyboardInterrupt(f"signal {signum}")

    old = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old)
