"""Write the normalised reconstruction targets and the initial meshes as OBJ files, with a JSON of their stats.

Usage::

    python data_gen/make_targets.py --out DIR [--teapot-resolutions 8 16 32] [--n-vertices 2500]

The library builds these meshes at run time (they take well under a second each); this script is for
looking at them and for the numbers quoted in docs/shapes.md. Nothing it writes is committed.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from meshmei.mesh import save_mesh  # noqa: E402
from meshmei.quality import count_self_intersections  # noqa: E402
from meshmei.shapes import INITIAL_KINDS, initial_mesh, target_mesh  # noqa: E402


def mesh_stats(V, F, seconds):
    import igl

    V = V.detach().double().cpu().numpy()
    F = F.cpu().numpy()
    E = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
    uniq, count = np.unique(E, axis=0, return_counts=True)
    L = np.linalg.norm(V[uniq[:, 0]] - V[uniq[:, 1]], axis=1)
    volume = float(np.einsum("ij,ij->i", V[F[:, 0]], np.cross(V[F[:, 1]], V[F[:, 2]])).sum() / 6.0)
    n_boundary = int(np.sum(count == 1))
    return {
        "vertices": int(len(V)),
        "faces": int(len(F)),
        "edges": int(len(uniq)),
        "edge_length_mean": float(L.mean()),
        "edge_length_std": float(L.std()),
        "edge_length_cv": float(L.std() / L.mean()),
        "euler_characteristic": int(len(V) - len(uniq) + len(F)),
        "boundary_edges": n_boundary,
        "watertight": n_boundary == 0 and bool(np.all(count == 2)),
        "edge_manifold": bool(igl.is_edge_manifold(F)[0]),
        "signed_volume": volume,
        "surface_area": float(igl.doublearea(V, F).sum() / 2),
        "bbox_min": V.min(axis=0).tolist(),
        "bbox_max": V.max(axis=0).tolist(),
        "self_intersecting_pairs": count_self_intersections(V, F),
        "build_seconds": seconds,
    }


def timed(fn, *args, **kwargs):
    t0 = time.perf_counter()
    out = fn(*args, **kwargs)
    return out, time.perf_counter() - t0


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True, help="output folder (created if missing)")
    parser.add_argument("--teapot-resolutions", type=int, nargs="+", default=[8, 16, 32])
    parser.add_argument("--n-vertices", type=int, nargs="+", default=[2500, 10000],
                        help="vertex counts of the initial meshes")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)

    jobs = [("bunny", lambda: target_mesh("bunny", dtype=torch.float64))]
    for r in args.teapot_resolutions:
        jobs.append((f"teapot_r{r}", lambda r=r: target_mesh("teapot", resolution=r, dtype=torch.float64)))
    for kind in INITIAL_KINDS:
        for n in args.n_vertices:
            jobs.append((f"{kind}_n{n}", lambda k=kind, n=n: initial_mesh(k, n_vertices=n, dtype=torch.float64)))

    stats = {}
    for name, make in jobs:
        (V, F), seconds = timed(make)
        save_mesh(args.out / f"{name}.obj", V, F)
        stats[name] = mesh_stats(V, F, seconds)
        s = stats[name]
        print(f"{name:14s} V={s['vertices']:6d} F={s['faces']:6d} cv={s['edge_length_cv']:.3f} "
              f"chi={s['euler_characteristic']} bnd={s['boundary_edges']} vol={s['signed_volume']:.4f} "
              f"selfint={s['self_intersecting_pairs']} t={seconds:.3f}s")
    versions = {"torch": torch.__version__}
    for mod in ("igl", "pymeshlab", "trimesh", "numpy"):
        try:
            versions[mod] = getattr(__import__(mod), "__version__", "unknown")
        except ImportError:
            versions[mod] = None
    (args.out / "stats.json").write_text(json.dumps({"versions": versions, "meshes": stats}, indent=2))
    print(f"wrote {len(stats)} meshes and stats.json to {args.out}")


if __name__ == "__main__":
    main()
