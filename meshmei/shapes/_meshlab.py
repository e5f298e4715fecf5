"""pymeshlab, imported in the main thread where meshmei is.

A process whose first pymeshlab import ran in a thread other than the main one has aborted at exit with a
corrupted heap ("malloc_consolidate(): unaligned fastbin chunk detected"): an ``optimize_mei`` in a
``threading.Thread`` (11 of 11 tries), a thread that only imported meshmei (1 of 1), and pytest-xdist's
controlling process, which imports the module of each warning class its workers report in a receiving
thread (3 of 3 in a small run; CI's run once, after every test had passed). None did with the import made
first in the main thread (pymeshlab 2025.7.post1, torch 2.13); the small run, with meshmei imported as below,
exits cleanly (10 of 10).

So meshmei imported in the main thread imports pymeshlab with it (about 0.1 s). meshmei imported in another
thread leaves pymeshlab out until the first use, which may never come (a class unpickled, a warning class
looked up), and warns at that use: only the caller can move the import to the main thread.
"""

from __future__ import annotations

import sys
import threading
import warnings

__all__ = ["pymeshlab"]


class _Deferred:
    """Stands for the pymeshlab module until its first attribute is asked for, then imports it."""

    def __getattr__(self, name):
        if "pymeshlab" not in sys.modules and threading.current_thread() is not threading.main_thread():
            warnings.warn(f"pymeshlab is first used in the thread {threading.current_thread().name!r}, not the main "
                          "thread: such processes have aborted at exit (a corrupted heap, 'malloc_consolidate'); "
                          "import meshmei at the top of your program, in the main thread", RuntimeWarning,
                          stacklevel=3)
        import pymeshlab as module

        return getattr(module, name)


if "pymeshlab" in sys.modules or threading.current_thread() is threading.main_thread():
    import pymeshlab
else:
    pymeshlab = _Deferred()
