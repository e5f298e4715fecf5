"""A population's folder: its configuration and hash, one run folder per finished neuron, the table.

Layout of ``OUT``::

    population.json          what the population was run with, and the configuration hash
    neurons/neuron_00007/    a complete 3D-MEI run (meshmei.mei.save_run), written atomically; its
                             summary.json records the configuration hash and the pixel MEI's response
    population.csv           one row per finished neuron, rebuilt from the run folders
    population.png           3D-MEI against pixel-MEI responses

A neuron is finished when its run folder exists: the folder is renamed into place only when complete, so
an interrupted run (SIGINT, SIGTERM, kill -9) leaves finished neurons whole and nothing else that counts.
The hash covers everything that shapes a result (encoder, settings, start, pixel-MEI settings) and not
which neurons are asked for, so a population can grow; a folder made with another hash is an error,
never mixed in.
"""

from __future__ import annotations

import csv
import hashlib
import json
import math
import numbers
import os
import re
import uuid
import warnings
from pathlib import Path

from .._checks import is_finite_real, is_int
from .._files import check_creatable
from ..errors import MEIError
from ..mei.runs import RUN_FILES, is_complete_summary

__all__ = ["CONFIG_FORMAT", "COLUMNS", "config_hash", "neuron_dir", "prepare_folder", "read_summary",
           "finished_neurons",
           "table_row", "write_table", "read_table", "parse_neurons"]

CONFIG_FORMAT = 1
COLUMNS = ("neuron", "mei_response", "pixel_mei_response", "ratio", "fraction_of_bound", "seed",
           "self_intersections", "flipped_faces", "min_quality", "watertight", "manifold", "seconds")


def config_hash(config: dict) -> str:
    """A short stable hash of a JSON-able configuration (sorted keys)."""
    text = json.dumps(config, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def neuron_dir(out: Path, neuron: int) -> Path:
    return Path(out) / "neurons" / f"neuron_{neuron:05d}"


def _write_atomic(path: Path, text: str) -> None:
    tmp = path.parent / f".{path.name}.{uuid.uuid4().hex[:8]}.tmp"
    tmp.write_text(text)
    os.replace(tmp, path)


def prepare_folder(out, config: dict) -> str:
    """Create ``out`` with its ``population.json``, or check that an existing one holds the same configuration.

    Returns the configuration hash. Raises :class:`MEIError` when ``out`` was made with another one.
    """
    out = Path(out)
    digest = config_hash(config)
    meta = out / "population.json"
    if meta.is_file():
        try:
            old = json.loads(meta.read_text())
        except (OSError, json.JSONDecodeError, UnicodeDecodeError) as err:
            if not _neurons_made_with(out, digest):
                raise MEIError(f"{meta} is unreadable ({err}); choose another --out") from None
            # every finished neuron says it was made with these settings: the description is rewritten, and
            # they are resumed (before, "choose another --out" left them behind)
            warnings.warn(f"{meta} was unreadable ({err}); rewritten with this run's settings, which every finished "
                          "neuron there was made with", UserWarning, stacklevel=2)
            _describe(meta, digest, config)
            return digest
        if not isinstance(old, dict) or not isinstance(old.get("config", {}), dict):
            what = (f"it holds a {type(old).__name__}" if not isinstance(old, dict)
                    else f"its config is a {type(old['config']).__name__}")
            raise MEIError(f"{meta} is not a population description ({what}); choose another --out")
        if old.get("config_hash") != digest:
            changed = sorted(k for k in set(config) | set(old.get("config", {}))
                             if config.get(k) != old.get("config", {}).get(k))
            if not changed and old.get("format") == CONFIG_FORMAT:  # the same settings, another recorded hash
                changed = ["none of the settings; its recorded hash does not match them (was the file edited?)"]
            raise MEIError(f"{out} holds a population run with other settings (config {old.get('config_hash')}, "
                           f"this run {digest}; differing: {', '.join(changed) or 'format'}); use another --out "
                           "or the same settings to resume")
        return digest
    if out.exists() and (not out.is_dir() or any(not p.name.startswith(".") for p in out.iterdir())):
        if not meta.exists() and _neurons_made_with(out, digest):  # deleted: as when unreadable (above)
            warnings.warn(f"{meta} was missing; written again with this run's settings, which every finished "
                          "neuron there was made with", UserWarning, stacklevel=2)
            _describe(meta, digest, config)
            return digest
        raise MEIError(f"{out} exists and is not a population folder; choose another --out")
    check_creatable(out, MEIError)
    out.mkdir(parents=True, exist_ok=True)
    # the description first, then the neurons folder: jobs of one SLURM array may start at once
    _describe(meta, digest, config)
    (out / "neurons").mkdir(exist_ok=True)
    return digest


def _describe(meta: Path, digest: str, config: dict) -> None:
    _write_atomic(meta, json.dumps({"format": CONFIG_FORMAT, "config_hash": digest, "config": config}, indent=1,
                                   default=str))


def _neurons_made_with(out: Path, digest: str) -> bool:
    """Whether ``out`` holds finished neuron folders and every readable summary there names ``digest``."""
    found = False
    for summary in sorted((out / "neurons").glob("neuron_*/summary.json")):
        try:
            made = json.loads(summary.read_text()).get("config_hash")
        except (OSError, ValueError, AttributeError):  # a damaged summary: resumed, it is named then
            continue
        if made != digest:
            return False
        found = True
    return found


# the quality fields table_row reads, each with the test its value must pass when present (a damaged "x"
# failed in the CLI's min())
# (a finite real: NaN and Inf in a damaged summary had made the table's responses nan)
_QUALITY_FIELDS = {"self_intersections": is_int, "flipped_faces": is_int, "nonmanifold_edges": is_int,
                   "min_quality": is_finite_real, "watertight": lambda x: isinstance(x, bool)}


def _good_quality(q) -> bool:
    return isinstance(q, dict) and all(q.get(k) is None or ok(q[k]) for k, ok in _QUALITY_FIELDS.items())


def _well_formed(summary, name: str) -> bool:
    """Whether a parsed ``summary.json`` holds what load_run and table_row read, as the types they read it
    as, for the neuron that its folder ``name`` is named after."""
    if not is_complete_summary(summary):
        return False
    n, pix = summary.get("neuron"), summary.get("pixel_mei_activation")
    return (is_int(n) and name == f"neuron_{n:05d}"
            and is_finite_real(summary.get("activation")) and _good_quality(summary.get("quality", {}))
            and (pix is None or is_finite_real(pix)))


class IncompleteFolder(MEIError):
    """A neuron folder with a file missing, empty or damaged: removed and resumed, not reused."""


def read_summary(d: Path, digest: str) -> dict:
    """The summary of the finished neuron folder ``d`` made with configuration ``digest``; MEIError when a
    file is missing or damaged, the summary names another neuron, or the folder was made with other settings."""
    d = Path(d)
    incomplete = IncompleteFolder(f"{d} is not a complete run folder; remove it and resume")
    if any(not (d / name).is_file() or (d / name).stat().st_size == 0 for name in RUN_FILES):
        raise incomplete  # an empty state.pt or mesh.obj counted as finished, and failed in a later tune
    with open(d / "state.pt", "rb") as fh:  # torch.save's zip archive; other bytes counted as finished too
        if fh.read(4) != b"PK\x03\x04":
            raise incomplete
    try:
        summary = json.loads((d / "summary.json").read_text())
    except (OSError, json.JSONDecodeError, UnicodeDecodeError):
        raise incomplete from None
    if not _well_formed(summary, d.name):
        raise incomplete
    if summary.get("config_hash") != digest:
        raise MEIError(f"{d} was made with other settings (config {summary.get('config_hash')}, this run "
                       f"{digest}); it would mix results of different settings: use another --out")
    return summary


def finished_neurons(out, digest: str) -> dict[int, dict]:
    """``{neuron: summary}`` of the complete run folders (:func:`read_summary`); a damaged folder or one made
    with another configuration raises."""
    root = Path(out) / "neurons"
    if not root.is_dir():
        return {}
    summaries, damaged = {}, []
    for d in sorted(root.glob("neuron_*")):
        try:
            s = read_summary(d, digest)
        except IncompleteFolder as err:  # collected (another configuration's MEIError is raised at once, as before)
            damaged.append((d, err))
            continue
        summaries[s["neuron"]] = s
    if len(damaged) == 1:
        raise damaged[0][1]
    if damaged:  # all at once: one per rerun before
        more = f" and {len(damaged) - 10} more" if len(damaged) > 10 else ""
        names = ", ".join(d.name for d, _ in damaged[:10]) + more
        raise MEIError(f"{len(damaged)} folders in {root} are not complete run folders ({names}); remove them and "
                       "resume")
    return summaries


def table_row(summary: dict) -> dict:
    """One table row from a run folder's ``summary.json``."""
    q = summary.get("quality", {})
    mei, pix = summary["activation"], summary.get("pixel_mei_activation")
    ratio = mei / pix if pix is not None and pix > 0 else None  # no ratio to a pixel MEI that does not excite
    return {"neuron": summary["neuron"], "mei_response": mei, "pixel_mei_response": pix, "ratio": ratio,
            "fraction_of_bound": summary.get("fraction_of_bound"), "seed": summary.get("seed"),
            "self_intersections": q.get("self_intersections"), "flipped_faces": q.get("flipped_faces"),
            "min_quality": q.get("min_quality"), "watertight": q.get("watertight"),
            "manifold": None if q.get("nonmanifold_edges") is None else q["nonmanifold_edges"] == 0,
            "seconds": summary.get("population_seconds", summary.get("wall_time_s"))}


def write_table(out, summaries: dict[int, dict]) -> Path:
    """Write ``population.csv`` (one row per neuron, by neuron) atomically.

    Pass every finished neuron (:func:`finished_neurons`): jobs that share a folder (a SLURM array) each
    rewrite the table from the folders, so the last writer's table holds them all.
    """
    path = Path(out) / "population.csv"
    tmp = path.parent / f".{path.name}.{uuid.uuid4().hex[:8]}.tmp"
    with open(tmp, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=COLUMNS)
        w.writeheader()
        for n in sorted(summaries):
            w.writerow({k: ("" if v is None else v) for k, v in table_row(summaries[n]).items()})
    os.replace(tmp, path)
    return path


_INTEGER_COLUMNS = ("neuron", "seed", "self_intersections", "flipped_faces")
_BOOLEAN_COLUMNS = ("watertight", "manifold")
_DECIMAL = re.compile(r"[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?", re.ASCII)


def read_table(out) -> list[dict]:
    """``population.csv`` of the population folder ``out`` as a list of dicts, one per neuron: the columns of
    :data:`COLUMNS`, integers, finite numbers and booleans parsed, empty cells None. A table of other columns
    or cells is one MEIError naming its line (short rows, NaN and other scripts' digits were read as
    they were, or ended in a TypeError); a byte-order mark is skipped."""
    path = Path(out) / "population.csv"
    try:
        with open(path, newline="", encoding="utf-8-sig") as fh:  # a BOM (a spreadsheet's save) is skipped
            lines = list(csv.reader(fh))
    except FileNotFoundError:
        raise MEIError(f"no population table at {path}") from None
    except (OSError, UnicodeDecodeError, csv.Error) as err:
        raise MEIError(f"{path} is unreadable: {err}") from None
    if not lines or tuple(lines[0]) != COLUMNS:
        raise MEIError(f"{path} is not a population table: its header is {lines[0] if lines else 'missing'}, "
                       f"not {list(COLUMNS)}")
    return [_table_row(cells, path, i) for i, cells in enumerate(lines[1:], start=2)]


def _table_row(cells: list, path: Path, line: int) -> dict:
    if len(cells) != len(COLUMNS):
        raise MEIError(f"{path}, line {line}: {len(cells)} cells, not {len(COLUMNS)}")
    row = {}
    for key, v in zip(COLUMNS, cells):
        if v == "":
            row[key] = None
        elif key in _BOOLEAN_COLUMNS and v in ("True", "False"):
            row[key] = v == "True"
        elif key in _INTEGER_COLUMNS and v.isascii() and v.isdigit():
            row[key] = int(v)
        elif key not in _INTEGER_COLUMNS + _BOOLEAN_COLUMNS and _DECIMAL.fullmatch(v) and math.isfinite(float(v)):
            row[key] = float(v)
        else:
            raise MEIError(f"{path}, line {line}: {key} holds {v!r:.40}")
    return row


MAX_NEURONS = 1_000_000  # indices one neuron list may name (without the encoder's count to bound them)


def parse_neurons(text: str, n_neurons: int | None = None) -> list[int]:
    """``"0-99"``, ``"3,7,12"``, ``"0-9,20,30-32"``: neuron indices in the order given, without repeats.
    With ``n_neurons``, an index beyond the encoder's count is refused before any range is expanded; without
    it, more than :data:`MAX_NEURONS` indices are (0-99999999999 ran out of memory)."""
    if n_neurons is not None and not (isinstance(n_neurons, numbers.Integral) and not isinstance(n_neurons, bool)
                                      and n_neurons > 0):
        raise MEIError(f"n_neurons must be a positive integer, got {n_neurons!r}")
    out: list[int] = []
    for part in str(text).replace(" ", "").split(","):
        if not part:
            continue
        lo, sep, hi = part.partition("-")
        # ASCII digits only: int() also reads '+1', '1_0' (as 10) and other scripts' digits
        if not all(x.isascii() and x.isdigit() and len(x) <= 18 for x in ((lo, hi) if sep else (lo,))):
            raise MEIError(f"neurons must be ranges and lists such as 0-99 or 3,7,12; got {text!r:.80}")
        a = int(lo)
        b = int(hi) if sep else a
        if a < 0 or b < a:
            raise MEIError(f"neuron range {part!r} is empty or negative")
        if n_neurons is not None and b >= n_neurons:
            raise MEIError(f"neuron index out of range for {n_neurons} neurons: got {b} (in {part!r})")
        if len(out) + (b - a + 1) > MAX_NEURONS:
            raise MEIError(f"{text!r:.80} names more than {MAX_NEURONS:,} neurons")
        out.extend(range(a, b + 1))
    if not out:
        raise MEIError(f"no neurons in {text!r}")
    return list(dict.fromkeys(out))
