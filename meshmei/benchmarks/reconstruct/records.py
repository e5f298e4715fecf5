"""The benchmark's records under typed keys, and their form in ``docs/reconstruction_benchmark.json``."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import NamedTuple

from .problems import PROBLEMS, VARIANTS

__all__ = ["Case", "RunKey", "key_text", "Records", "ordered"]


class Case(NamedTuple):
    """A problem at a final vertex count: what a decimation floor and a starting mesh belong to."""

    problem: str
    n_vertices: int

    @classmethod
    def from_text(cls, text: str) -> "Case":
        """Read ``"problem|n"`` (the JSON's key)."""
        problem, n = text.split("|")
        return cls(problem, int(n))


class RunKey(NamedTuple):
    """One configuration of the benchmark: a problem, a final vertex count and a variant."""

    problem: str
    n_vertices: int
    variant: str

    @property
    def case(self) -> Case:
        return Case(self.problem, self.n_vertices)

    @classmethod
    def from_text(cls, text: str) -> "RunKey":
        """Read ``"problem|n|variant"`` (the JSON's key)."""
        problem, n, variant = text.split("|")
        return cls(problem, int(n), variant)


def key_text(key, sep: str = "|") -> str:
    """A :class:`Case` or :class:`RunKey` as text, its fields joined by ``sep`` (``"|"``: the JSON's key)."""
    return sep.join(str(part) for part in key)


@dataclass
class Records:
    """Everything the benchmark measured, kept across runs (``--merge``).

    Attributes
    ----------
    results : dict RunKey -> dict
        Per configuration: ``budgets`` (str(seconds) -> final metrics of that run), ``curve`` [(t, Chamfer-L2)],
        ``metrics`` (the longest run's evaluations), ``settings``, ``run`` (when it was measured).
    floors : dict Case -> dict
        The target decimated to the result's face count, and its metrics.
    membrane : dict target name -> dict
        :class:`~meshmei.benchmarks.reconstruct.membrane.MembraneFloor` numbers.
    """

    results: dict = field(default_factory=dict)
    floors: dict = field(default_factory=dict)
    membrane: dict = field(default_factory=dict)

    @classmethod
    def from_json(cls, raw: dict) -> "Records":
        """From the JSON file's content (``membrane`` may be missing in older files)."""
        return cls(results={RunKey.from_text(k): v for k, v in raw["results"].items()},
                   floors={Case.from_text(k): v for k, v in raw["floors"].items()},
                   membrane=dict(raw.get("membrane") or {}))

    def to_json(self) -> dict:
        """The JSON file's content: keys as text, in the order the records were made."""
        return {"results": {key_text(k): v for k, v in self.results.items()},
                "floors": {key_text(k): v for k, v in self.floors.items()}, "membrane": self.membrane}

    @classmethod
    def load(cls, path) -> "Records":
        return cls.from_json(json.loads(path.read_text()))

    def save(self, path) -> dict:
        """Write the JSON file; return its content."""
        raw = self.to_json()
        path.write_text(json.dumps(raw, indent=1, default=float))
        return raw


def ordered(results: dict) -> list:
    """``[(RunKey, entry)]`` sorted by problem, resolution and variant, in the order the benchmark defines them
    (unknown problems and variants last)."""
    probs, names = list(PROBLEMS), list(VARIANTS)

    def rank(key):
        return (probs.index(key.problem) if key.problem in probs else 99, key.n_vertices,
                names.index(key.variant) if key.variant in names else 99)

    return sorted(results.items(), key=lambda item: rank(item[0]))
