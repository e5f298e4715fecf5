"""Reconstruction quality in float64, not differentiable: Chamfer-L2, F-score, normals, Hausdorff, by part.

Distances are exact point-to-triangle distances (libigl), so two identical surfaces score 0 up to round-off:
there is no sampling floor. The differentiable per-step side (sampling, Chamfer) is :mod:`meshmei.sampling`;
mesh health is :mod:`meshmei.quality`.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import igl
import numpy as np
import scipy.sparse as sp
import torch
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from ._checks import check_positive
from .errors import MeshError
from .mesh import as_faces, numpy_mesh
from .operators import doublearea, face_normals
from .quality import count_degenerate_faces, count_self_intersections, edge_use, triangle_quality
from .sampling import sample_points

__all__ = [
    "EVAL_SAMPLES",
    "SurfaceMetrics",
    "surface_metrics",
    "face_components",
    "error_by_part",
    "hidden_surface",
]

# The project's reported metrics sample each surface this many times (area-uniform).
EVAL_SAMPLES = 100_000


def _normals_np(V, F):
    """Unit normals ``(m, 3)`` (zero for zero-area faces) and double areas ``(m,)`` of a numpy mesh, as numpy."""
    Vt, Ft = torch.from_numpy(V), torch.from_numpy(F)
    return face_normals(Vt, Ft, eps=0.0).numpy(), doublearea(Vt, Ft).numpy()


@dataclass(frozen=True)
class SurfaceMetrics:
    """Reconstruction quality of a mesh against a target surface (see :func:`surface_metrics`).

    Attributes
    ----------
    chamfer_l2 : float
        ``accuracy + completeness``.
    accuracy : float
        Mean squared distance from samples on the mesh to the target surface.
    completeness : float
        Mean squared distance from samples on the target to the mesh surface.
    fscore, precision, recall : float
        At ``threshold``: precision is the fraction of mesh samples within it of the target, recall the
        fraction of target samples within it of the mesh; ``fscore = 2 P R / (P + R)``.
    threshold : float
        Absolute F-score distance (the given fraction of the bounding-box diagonal of the vertices the
        target's faces use).
    normal_consistency : float
        Mean absolute cosine between the normal at each sample and the normal of the face it is closest
        to on the other surface, averaged over both directions (1 is perfect).
    hausdorff : float
        Largest sample-to-surface distance in either direction (a lower bound on the exact Hausdorff
        distance, tight to the sample spacing).
    area_ratio : float
        The mesh's surface area over the target's. Accuracy is a mean over the mesh's area, so surface
        added where it costs little (folds and wrinkles lying on the target) lowers it; a ratio well
        above 1 flags a score bought that way (docs/reconstruction.md, *Why the teapot stops*).
    self_intersections, degenerate_faces : int or None
        Health of the mesh (see :class:`meshmei.quality.MeshHealth`).
    inverted_faces : int
        Mesh faces whose normal points against the target normal at the target point closest to the
        face's centroid (folds, or an orientation opposite to the target's): reconstruction's flipped
        faces, since a remeshed run has no rest pose to compare a face with.
    min_quality : float
        Smallest triangle quality ``4 sqrt(3) A / sum(l^2)`` of the mesh (:func:`~meshmei.quality.triangle_quality`;
        1 for equilateral, 0 for degenerate).
    boundary_edges, nonmanifold_edges : int
        Edges used by one face, and by more than two (:func:`~meshmei.quality.edge_use`).
    watertight : bool
        Closed and edge-manifold: no edge of either kind.
    n_samples, seed : int
    """

    chamfer_l2: float
    accuracy: float
    completeness: float
    fscore: float
    precision: float
    recall: float
    threshold: float
    normal_consistency: float
    hausdorff: float
    area_ratio: float
    self_intersections: int | None
    degenerate_faces: int
    inverted_faces: int
    min_quality: float
    boundary_edges: int
    nonmanifold_edges: int
    watertight: bool
    n_samples: int
    seed: int

    def as_dict(self) -> dict:
        return asdict(self)


def _sample_np(V, F, n, seed):
    P, N, _ = sample_points(torch.from_numpy(V), torch.from_numpy(F), n, generator=seed,
                            return_normals=True, return_faces=True)
    return P.numpy(), N.numpy()


def surface_metrics(V, F, Vt, Ft, *, n_samples: int = EVAL_SAMPLES, seed: int = 0, fscore_threshold: float = 0.01,
                    health: bool = True) -> SurfaceMetrics:
    """Chamfer-L2, F-score, normal consistency, Hausdorff and health of ``(V, F)`` against ``(Vt, Ft)``.

    ``n_samples`` area-uniform points are drawn on each surface (fixed ``seed``), and their distances
    to the other surface are exact point-to-triangle distances (``igl.point_mesh_squared_distance``), so
    two identical surfaces score 0 up to round-off: there is no sampling floor. Chamfer-L2 is the sum over
    both directions of the mean squared distance. No normalisation is applied: normalise both meshes
    (e.g. unit bounding-box diagonal) beforehand to compare across shapes.

    Parameters
    ----------
    V : (n, 3) float tensor or array, F : (m, 3) integer tensor or array
        The mesh to evaluate.
    Vt : (nt, 3) float tensor or array, Ft : (mt, 3) integer tensor or array
        The target.
    n_samples : int
        Samples per surface.
    seed : int
        Seed of the sampling (the same seed gives the same numbers).
    fscore_threshold : float
        F-score distance as a fraction of the target's bounding-box diagonal (default 1 %; the box of the
        target's surface: vertices no face uses do not count).
    health : bool
        Also count self-intersections of ``(V, F)`` (costs about 0.2 s on a 50k-face mesh).

    Returns
    -------
    SurfaceMetrics

    Raises
    ------
    MeshError
        Either mesh is invalid or has zero area.

    Examples
    --------
    >>> V, F = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]), torch.tensor([[0, 1, 2]])
    >>> m = surface_metrics(V, F, V, F, n_samples=1000)
    >>> m.chamfer_l2 < 1e-20, m.fscore, m.self_intersections, m.degenerate_faces
    (True, 1.0, 0, 0)
    """
    if isinstance(n_samples, bool) or int(n_samples) != n_samples or n_samples < 1:
        raise ValueError(f"n_samples must be a positive integer, got {n_samples!r}")
    if not fscore_threshold > 0:
        raise ValueError(f"fscore_threshold must be positive, got {fscore_threshold!r}")
    V, F = numpy_mesh(V, F)
    Vt, Ft = numpy_mesh(Vt, Ft)
    P, NP = _sample_np(V, F, int(n_samples), seed)
    Q, NQ = _sample_np(Vt, Ft, int(n_samples), seed + 1)
    d_pq, f_pq, _ = igl.point_mesh_squared_distance(P, Vt, Ft)
    d_qp, f_qp, _ = igl.point_mesh_squared_distance(Q, V, F)
    Nt, dbl_t = _normals_np(Vt, Ft)
    Ns, dbl = _normals_np(V, F)
    nc = 0.5 * (np.abs((NP * Nt[f_pq]).sum(1)).mean() + np.abs((NQ * Ns[f_qp]).sum(1)).mean())
    surface = Vt[np.unique(Ft)]  # an unused vertex is no part of the target and must not widen the box
    tau = fscore_threshold * float(np.linalg.norm(surface.max(0) - surface.min(0)))
    precision = float(np.mean(d_pq <= tau * tau))
    recall = float(np.mean(d_qp <= tau * tau))
    fscore = 0.0 if precision + recall == 0 else 2 * precision * recall / (precision + recall)
    _, f_c, _ = igl.point_mesh_squared_distance(V[F].mean(1), Vt, Ft)
    inverted = int(np.sum(((Ns * Nt[f_c]).sum(1) < 0) & (dbl > 0)))
    boundary, nonmanifold = edge_use(F)
    return SurfaceMetrics(
        chamfer_l2=float(d_pq.mean() + d_qp.mean()),
        accuracy=float(d_pq.mean()),
        completeness=float(d_qp.mean()),
        fscore=float(fscore),
        precision=precision,
        recall=recall,
        threshold=tau,
        normal_consistency=float(nc),
        hausdorff=float(np.sqrt(max(d_pq.max(), d_qp.max()))),
        area_ratio=float(dbl.sum() / dbl_t.sum()),
        self_intersections=count_self_intersections(V, F) if health else None,
        degenerate_faces=count_degenerate_faces(V, F),
        inverted_faces=inverted,
        min_quality=float(triangle_quality(torch.from_numpy(V), torch.from_numpy(F)).min()),
        boundary_edges=boundary,
        nonmanifold_edges=nonmanifold,
        watertight=boundary == 0 and nonmanifold == 0,
        n_samples=int(n_samples),
        seed=int(seed),
    )


def face_components(F, n_vertices: int) -> np.ndarray:
    """Label each face with its piece: faces that share a vertex, directly or through other faces, are in
    the same piece. Returns an ``(m,)`` int array of labels ``0 .. pieces - 1``."""
    check_positive("n_vertices", n_vertices, integer=True)
    F = as_faces(F).cpu().numpy()  # float, bool and quad faces were read as triangles of indices
    if int(F.max()) >= n_vertices:
        raise MeshError(f"F holds vertex index {int(F.max())}, but n_vertices is {n_vertices}")
    i = F[:, [0, 1, 2]].ravel()
    j = F[:, [1, 2, 0]].ravel()
    graph = sp.coo_matrix((np.ones(len(i)), (i, j)), shape=(int(n_vertices), int(n_vertices)))
    _, vertex_label = connected_components(graph, directed=False)
    _, label = np.unique(vertex_label[F[:, 0]], return_inverse=True)
    return label.ravel()


def error_by_part(V, F, Vt, Ft, *, n_samples: int = EVAL_SAMPLES, seed: int = 0) -> list[dict]:
    """Where the Chamfer error of ``(V, F)`` sits on a target made of several pieces.

    The target's faces are split into connected components (pieces sharing no vertex: the teapot's body,
    handle, spout and lid). The samples are those of :func:`surface_metrics` with the same ``seed``; each
    mesh sample is charged to the piece that holds its closest target point, and each target sample to its
    own piece, so the ``accuracy`` and ``completeness`` entries of all pieces add up to the totals that
    :func:`surface_metrics` reports.

    Returns
    -------
    list of dict, one per piece in order of decreasing area: ``faces``, ``area_share`` (of the target's
    area), ``accuracy`` and ``completeness`` (contributions to the means, same units as Chamfer-L2),
    ``bbox_min`` and ``bbox_max`` (of the piece's vertices).
    """
    V, F = numpy_mesh(V, F)
    Vt, Ft = numpy_mesh(Vt, Ft)
    P, _ = _sample_np(V, F, int(n_samples), seed)
    Q, fq = sample_points(torch.from_numpy(Vt), torch.from_numpy(Ft), int(n_samples), generator=seed + 1,
                          return_faces=True)
    Q, fq = Q.numpy(), fq.numpy()
    d_pq, f_pq, _ = igl.point_mesh_squared_distance(P, Vt, Ft)
    d_qp, _, _ = igl.point_mesh_squared_distance(Q, V, F)
    face_label = face_components(Ft, len(Vt))
    _, area = _normals_np(Vt, Ft)
    out = []
    for c in np.unique(face_label):
        faces = face_label == c
        verts = Vt[np.unique(Ft[faces])]
        out.append({
            "faces": int(faces.sum()),
            "area_share": float(area[faces].sum() / area.sum()),
            "accuracy": float(d_pq[faces[f_pq]].sum() / len(P)),
            "completeness": float(d_qp[faces[fq]].sum() / len(Q)),
            "bbox_min": verts.min(0).tolist(),
            "bbox_max": verts.max(0).tolist(),
        })
    return sorted(out, key=lambda r: -r["area_share"])


def hidden_surface(V, F, *, n_samples: int = EVAL_SAMPLES, seed: int = 0, offset: float = 1e-4) -> dict:
    """The part of a surface buried inside its own solid, which no surface around the solid can touch.

    A sample is *hidden* when the generalised winding number (``igl.fast_winding_number``) exceeds 0.5
    at both points ``offset`` (times the bounding-box diagonal) off the surface along its normal: it is
    inside the solid on both sides, like a spout's base that passes into the body of a teapot, or the
    patch of body wall that the spout's base encloses. The samples are the target samples of
    :func:`surface_metrics` (same ``seed``).

    Returns
    -------
    dict with ``fraction`` (share of the area that is hidden) and ``completeness`` (the completeness
    term of Chamfer-L2 that a surface covering exactly the visible part scores: the mean over all
    samples of the squared distance from each hidden sample to the nearest visible sample), and
    ``hidden`` (boolean mask over the samples) with ``points`` ``(n_samples, 3)``.
    """
    check_positive("offset", offset)  # 0 or inf gave a meaningless fraction without a word
    if offset >= 0.1:
        raise ValueError(f"offset must be below 0.1 of the bounding-box diagonal, got {offset!r}")
    V, F = numpy_mesh(V, F)
    Q, N = _sample_np(V, F, int(n_samples), seed + 1)
    h = offset * float(np.linalg.norm(V.max(0) - V.min(0)))
    w_out = igl.fast_winding_number(V, F, Q + h * N)
    w_in = igl.fast_winding_number(V, F, Q - h * N)
    hidden = (np.abs(w_out) > 0.5) & (np.abs(w_in) > 0.5)
    completeness = 0.0
    if hidden.any() and not hidden.all():
        d, _ = cKDTree(Q[~hidden]).query(Q[hidden])
        completeness = float((d**2).sum() / len(Q))
    return {"fraction": float(hidden.mean()), "completeness": completeness, "hidden": hidden, "points": Q}
