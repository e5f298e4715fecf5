"""Shared helpers for benchmark scripts: timing, peak memory, and writing a section of docs/benchmarks.md."""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import platform
import re
import tempfile
import time
from pathlib import Path

import torch

from meshmei._checks import positive_int  # re-exported: the benchmarks' argparse type

__all__ = ["docs_dir", "write_section", "machine_line", "median", "step_intervals", "timeit", "timings",
           "markdown_table", "benchmark_parser", "add_restart", "int_list", "positive_int", "keep_docs_for_full_runs",
           "HEALTH_COLUMNS", "HEALTH_LEGEND", "health_cells", "SURFACE_HEALTH_COLUMNS", "SURFACE_HEALTH_LEGEND",
           "surface_health", "FinishedRows", "source_hash"]

_HEADER = "# Benchmarks\n\nEach section is written by the script named in it; re-run the script to refresh it.\n"


def docs_dir() -> Path:
    """The repository's ``docs/`` folder (``MESHMEI_DOCS`` overrides, e.g. for a dry run)."""
    env = os.environ.get("MESHMEI_DOCS")
    if env:
        return Path(env)
    return Path(__file__).resolve().parents[2] / "docs"


def benchmark_parser(file: str, doc: str) -> argparse.ArgumentParser:
    """The parser of the benchmark module at ``file``: ``python -m meshmei.benchmarks.NAME`` as its name, the
    docstring's first paragraph as its description (its first line alone was cut mid-sentence)."""
    name = Path(file).stem
    return argparse.ArgumentParser(prog=f"python -m meshmei.benchmarks.{name}",
                                   description=" ".join(doc.split("\n\n")[0].split()),
                                   epilog="A full run writes its section of docs/benchmarks.md.")


def add_restart(parser: argparse.ArgumentParser) -> None:
    """The ``--restart`` flag of a benchmark that keeps its finished results in :class:`FinishedRows`."""
    parser.add_argument("--restart", action="store_true",
                        help="compute again the results an interrupted run of the same source left in "
                             "docs/.SECTION.partial.json (by default they are taken as they are)")


def int_list(text: str) -> list:
    """``"0,1,3"`` as ``[0, 1, 3]``: an argparse type (a bad entry is argparse's one-line error)."""
    try:
        return [int(x) for x in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers, got {text!r}") from None


def keep_docs_for_full_runs(quick: bool) -> None:
    """A quick (smoke) run writes into a fresh temporary folder, never over the published ``docs/``
    (unless ``MESHMEI_DOCS`` names a folder already); it says where."""
    if quick and not os.environ.get("MESHMEI_DOCS"):
        os.environ["MESHMEI_DOCS"] = tempfile.mkdtemp(prefix="meshmei-quick-")
        print(f"--quick: writing to {os.environ['MESHMEI_DOCS']}, not docs/")


def machine_line() -> str:
    """Processor, cores, torch version and threads, and today's date: the line under each section's title."""
    return (f"{platform.processor() or platform.machine()}, {os.cpu_count()} logical cores, "
            f"torch {torch.__version__}, {torch.get_num_threads()} threads, {time.strftime('%Y-%m-%d')}")


def write_section(name: str, body: str) -> Path:
    """Replace (or append) the section ``name`` of ``docs/benchmarks.md`` with ``body`` (markdown)."""
    path = docs_dir() / "benchmarks.md"
    path.parent.mkdir(parents=True, exist_ok=True)
    text = path.read_text() if path.exists() else _HEADER
    begin, end = f"<!-- BEGIN {name} -->", f"<!-- END {name} -->"
    block = f"{begin}\n{body.strip()}\n{end}"
    pattern = re.compile(re.escape(begin) + r".*?" + re.escape(end), re.S)
    text = pattern.sub(lambda _: block, text) if pattern.search(text) else text.rstrip() + "\n\n" + block + "\n"
    path.write_text(text)
    return path


def source_hash() -> str:
    """A hash of meshmei's source (every ``.py`` and ``.c`` file under the package, paths and contents)."""
    root = Path(__file__).resolve().parents[1]
    h = hashlib.sha256()
    for path in sorted(p for p in root.rglob("*") if p.suffix in (".py", ".c") and p.is_file()):
        h.update(str(path.relative_to(root)).encode() + b"\0" + path.read_bytes() + b"\0")
    return h.hexdigest()[:16]


def _plain(x):
    """NumPy and torch scalars as Python's (an int stays an int), for JSON."""
    return x.item() if hasattr(x, "item") else float(x)


class FinishedRows:
    """The finished results of one part of a benchmark, saved as each finishes, so that an interrupted run
    loses none of them.

    ``get(key, compute)`` returns the result saved under ``key`` or computes, saves and returns it, in its
    JSON form either way (a resumed table is the table a whole run writes). The file is
    ``docs/.NAME.partial.json``; the same command run again takes its results instead of recomputing them,
    unless meshmei's source has changed since (:func:`source_hash`) or ``restart`` is set, and says which.
    :meth:`close`, once the part's section is written, removes the file. ``name`` None keeps nothing on disk.
    """

    def __init__(self, name: str | None, restart: bool = False):
        self.path = None if name is None else docs_dir() / f".{name}.partial.json"
        self.source = None if self.path is None else source_hash()  # nothing on disk: nothing to match
        self.rows, self.resumed = {}, 0
        self.started = time.strftime("%Y-%m-%d %H:%M")
        old = self._read()
        if old is None:
            return
        if restart:
            print(f"{self.path}: --restart: dropping the {len(old['rows'])} finished results of an earlier run")
        elif old.get("source") != self.source:
            print(f"{self.path}: dropping the {len(old['rows'])} finished results of an earlier run: meshmei's "
                  "source has changed since")
        else:
            self.rows, self.started = old["rows"], str(old.get("started", "at a time not recorded"))
            print(f"{self.path}: taking the {len(self.rows)} finished results of an earlier run (started "
                  f"{self.started}); --restart computes them again")

    def _read(self) -> dict | None:
        if self.path is None or not self.path.exists():
            return None
        try:
            old = json.loads(self.path.read_text())
            return old if isinstance(old, dict) and isinstance(old.get("rows"), dict) else None
        except (OSError, ValueError):  # a file cut short is a run to redo, not an error
            return None

    def get(self, key: str, compute):
        if key in self.rows:
            self.resumed += 1
            return self.rows[key]
        value = json.loads(json.dumps(compute(), default=_plain))
        self.rows[key] = value
        if self.path is not None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            tmp = self.path.with_name(self.path.name + ".tmp")
            tmp.write_text(json.dumps({"source": self.source, "started": self.started, "rows": self.rows}))
            os.replace(tmp, self.path)  # whole or not at all, should the run be killed mid-write
        return value

    def note(self) -> str:
        """A sentence for the section when results were taken from an earlier run ("" otherwise)."""
        if not self.resumed:
            return ""
        return (f" {self.resumed} of its results were finished by an interrupted run of the same source that "
                f"started {self.started}; the machine line, load and total time are this run's.")

    def close(self) -> None:
        if self.path is not None:
            self.path.unlink(missing_ok=True)


def median(xs) -> float:
    """The upper median of ``xs`` (an element of it: ``sorted(xs)[len(xs) // 2]``)."""
    return sorted(xs)[len(xs) // 2]


def step_intervals(times, skip: int) -> list:
    """The durations of the steps of a run from its cumulative ``times`` (a ``time_history``), the first
    ``skip`` left out (warm-up)."""
    return [b - a for a, b in zip(times[:-1], times[1:])][skip:]


def timings(fn, *, repeat: int = 5, warmup: int = 1) -> tuple[float, float]:
    """Median and best wall time of ``fn()`` in seconds, after ``warmup`` calls.

    The best is the time least disturbed by other jobs on a shared machine; report both.
    """
    for _ in range(warmup):
        fn()
    ts = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return median(ts), min(ts)


def timeit(fn, *, repeat: int = 5, warmup: int = 1) -> float:
    """Median wall time of ``fn()`` in seconds."""
    return timings(fn, repeat=repeat, warmup=warmup)[0]


def markdown_table(header: list[str], rows: list[list]) -> str:
    """A markdown table: ``header`` (k,) strings, ``rows`` lists of k cells (written with ``str``)."""
    out = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    out += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return "\n".join(out)


HEALTH_COLUMNS = ["SI", "flipped", "q", "watertight", "manifold"]
HEALTH_LEGEND = ("SI = self-intersecting face pairs, flipped = faces flipped against the start (summed over the "
                 "results of a row), q = the smallest triangle quality, watertight and manifold = how many of the "
                 "row's results are (the sheet is open by design)")


def health_cells(reports: list) -> list:
    """The :data:`HEALTH_COLUMNS` of a table row from the :func:`meshmei.quality.health_report` of each of its
    results (one, or a set's members)."""
    n = len(reports)
    return [sum(h["self_intersections"] for h in reports), sum(h["flipped_faces"] for h in reports),
            f"{min(h['min_quality'] for h in reports):.3f}", f"{sum(bool(h['watertight']) for h in reports)}/{n}",
            f"{sum(h['nonmanifold_edges'] == 0 for h in reports)}/{n}"]


SURFACE_HEALTH_COLUMNS = ["SI", "inverted", "q", "watertight", "manifold"]
SURFACE_HEALTH_LEGEND = ("SI = self-intersecting face pairs, inverted = faces whose normal points against the "
                         "target's at the nearest target point (a remeshed result has no start to be flipped "
                         "against; summed over the results of a row), q = the smallest triangle quality, "
                         "watertight and manifold = how many of the row's results are")


def surface_health(metrics) -> dict:
    """A reconstruction result's health from its :class:`~meshmei.metrics.SurfaceMetrics` (or their
    ``as_dict()``), in the keys :func:`health_cells` reads; its flipped faces are the faces against the
    target (``inverted_faces``): with :func:`health_cells`, the :data:`SURFACE_HEALTH_COLUMNS`."""
    m = metrics if isinstance(metrics, dict) else metrics.as_dict()
    return {"self_intersections": m["self_intersections"], "flipped_faces": m["inverted_faces"],
            "min_quality": m["min_quality"], "watertight": m["watertight"],
            "nonmanifold_edges": m["nonmanifold_edges"]}
