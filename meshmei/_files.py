"""Writing result directories atomically, so an interrupted write is never taken for a finished one."""

from __future__ import annotations

import os
import shutil
import uuid
from pathlib import Path
from typing import Callable

__all__ = ["atomic_directory"]


def atomic_directory(directory, write: Callable[[Path], None], *, overwrite: bool = False,
                     error: type[Exception] = ValueError) -> Path:
    """Build ``directory`` by calling ``write(tmp)`` on a hidden temporary sibling, then rename it into place.

    Until ``write`` returns, only ``.NAME.partial-XXXXXXXX`` exists (and is removed if ``write`` raises);
    an existing ``directory`` is replaced only with ``overwrite``, after the new one is complete. Without
    ``overwrite`` it is never replaced, also when another process put it there while ``write`` ran (the
    rename onto it fails, and the new folder is removed).

    Raises
    ------
    error
        ``directory`` exists and ``overwrite`` is False, before ``write`` or after it (the caller's
        exception type).
    """
    directory = Path(directory)
    exists = error(f"{directory} exists; pass overwrite=True (CLI: --overwrite) to replace it")
    if directory.exists() and not overwrite:
        raise exists
    directory.parent.mkdir(parents=True, exist_ok=True)
    tmp = directory.parent / f".{directory.name}.partial-{uuid.uuid4().hex[:8]}"
    tmp.mkdir()
    try:
        write(tmp)
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
                    raise exists from None
                raise
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return directory
