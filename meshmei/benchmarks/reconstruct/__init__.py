"""Reconstruction benchmark: sphere -> bunny and torus -> teapot, each method, Chamfer-L2 / F-score / normal
consistency against wall time, at about 2.5k and 10k vertices, with the decimation floor.

Three problems: bunny (from a sphere), teapot (from the torus started with its hole through the teapot's
handle, what ``--init torus`` gives) and teapot-centred (from the centred torus, whose hole misses the
handle). Run ``python -m meshmei.benchmarks.reconstruct`` (about 55 minutes on a 2-core CPU;
``--problems``, ``--resolutions`` and ``--variants`` pick a subset, ``--merge`` keeps the rest); it writes
the section "reconstruction" of ``docs/benchmarks.md``, ``docs/reconstruction_<problem>.png`` and the raw
numbers in ``docs/reconstruction_benchmark.json``. ``--quick`` runs a few-second smoke version into a
temporary folder. Each (problem, resolution, method) is run separately at each time budget (10, 30, 100 s):
the schedule (coarse-to-fine stages, learning-rate decay) follows the budget, as a user would set it; the
100 s run is also evaluated at intermediate times for the curves. ``--extra-budgets 50,70`` adds runs
whose ends count only in the best-of-runs reading of the levels.

Modules: ``problems`` (what is run), ``records`` (typed keys and the JSON file), ``run`` (the command line and
the runs), ``curves`` (reading the Chamfer curves), ``report`` (the markdown section), ``figures`` (the
curves' figures), ``membrane`` (what blocking the teapot's opening costs), ``rbf_cost`` (the RBF map's cost).
"""

from .curves import CHECKPOINTS, best_of_runs, on_checkpoints, slower_levels, time_to_reach
from .figures import plot
from .membrane import MembraneFloor, membrane_floor
from .problems import BUDGETS, PROBLEMS, RESOLUTIONS, VARIANTS, Variant, variant_settings
from .rbf_cost import rbf_cost
from .records import Case, Records, RunKey
from .report import render, teapot_piece_names
from .run import decimation_floor, main, start_mesh, warm_up

__all__ = [
    "BUDGETS",
    "CHECKPOINTS",
    "Case",
    "MembraneFloor",
    "PROBLEMS",
    "RESOLUTIONS",
    "Records",
    "RunKey",
    "VARIANTS",
    "Variant",
    "best_of_runs",
    "decimation_floor",
    "main",
    "membrane_floor",
    "on_checkpoints",
    "plot",
    "rbf_cost",
    "render",
    "slower_levels",
    "start_mesh",
    "teapot_piece_names",
    "time_to_reach",
    "variant_settings",
    "warm_up",
]
