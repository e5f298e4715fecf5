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
    an existing ``directory`` is replaced only with ``overwrite``, after the new one is complete.

    Raises
    ------
    error
        ``directory`` exists and ``overwrite`` is False (the caller's exception type).
    """
    directory = Path(directory)
    if directory.exists() and not overwrite:
        raise error(f"{directory} exists; pass overwrite=True (CLI: --overwrite) to replace it")
    directory.parent.mkdir(parents=True, exist_ok=True)
    tmp = directory.parent / f".{directory.name}.partial-{uuid.uuid4().hex[:8]}"
    tmp.mkdir()
    try:
        write(tmp)
        if directory.exists():
            trash = directory.parent / f".{directory.name}.old-{uuid.uuid4().hex[:8]}"
            os.replace(directory, trash)
            os.replace(tmp, directory)
            shutil.rmtree(trash, ignore_errors=True)
        else:
            os.replace(tmp, directory)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return directory
