"""Topology surgery between the stages of a reconstruction: the one way a fit changes its start's topology.

A deformation keeps the start's topology. A torus whose hole is not where the target's is (the centred torus
on the teapot) ends as the target's surface with two defects the guard's clean steps cannot remove:

- a **sheet** of its own solid spanning the target's opening (the teapot's handle), far from every target
  point, where it costs Chamfer accuracy no deformation removes (the membrane floor,
  :func:`meshmei.benchmarks.reconstruct.membrane_floor`);
- its own hole, which had nowhere to go, pressed shut into **thin passages**, the body around it a shell of
  two layers held apart by the contact barrier, each off the target by half that gap.

:func:`adapt_topology` mends both once the fit is close elsewhere: :func:`perforate` cuts a hole through each
sheet (the faces of both sides that are off the target taken out, the two holes joined by a short tube: a
handle added), and :func:`seal` rebuilds the solid with its thin passages closed and the cavities they close
filled. Each result is closed, manifold and free of intersecting pairs, or the mesh is left as it was.
"""

from __future__ import annotations

import time

import igl
import numpy as np
import scipy.ndimage as ndi
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from scipy.spatial import ConvexHull

from ..quality import self_intersecting_pairs, topology
from .openings import spans_opening

__all__ = ["FAR_FROM_TARGET", "FIT_QUANTILE", "SHEET_THICKNESS", "SEAL_VOXELS", "SEAL_GAIN", "SEAL_PROBES",
           "adapt_topology",
           "perforate", "seal", "sheet_patches"]

# A face is off the target when its centroid is farther than this share of the target's bounding-box
# diagonal from it: the F-score's threshold, where a sample counts as wrong
FAR_FROM_TARGET = 0.01
# Surgery is tried only once the fit is close elsewhere: this quantile of the faces' distances under
# FAR_FROM_TARGET (on the centred teapot's default run at 2.5k: 0.025, 0.011 and 0.004 of the diagonal after the
# 151-, 625- and first 2,500-vertex stages; at 10k 0.035, 0.013, 0.0064 and 0.0067 after the 144-, 557- and
# the two 2,500-vertex stages)
FIT_QUANTILE = 0.9
# Two off-target patches form a sheet when each lies behind the other (against its outward normal) within
# this many of the mesh's mean edge lengths
SHEET_THICKNESS = 2.0
# seal's voxels: this many along the mesh's bounding-box diagonal (about a second at 2.5k vertices)
SEAL_VOXELS = 160
# seal keeps its result only where closing the passages encloses at least this many times the solid's volume
# (tried only where the convex hull could hold that much)
SEAL_GAIN = 2.0
# ... and only where the target encloses most of what it would add (the winding number at this many points)
SEAL_PROBES = 2000


def adapt_topology(V: np.ndarray, F: np.ndarray, Vt: np.ndarray, Ft: np.ndarray):
    """``(V, F)`` with its sheets perforated and its thin passages sealed where the fit to ``(Vt, Ft)`` is
    close elsewhere (:data:`FIT_QUANTILE`): ``(V2, F2, record)``, the arrays given back unchanged where
    nothing was done. ``record``: ``fit`` (the :data:`FIT_QUANTILE` quantile of the faces' distances to the
    target, in target diagonals), ``checked`` (whether that was close enough to try), ``perforated`` (holes
    cut), ``sealed`` and ``seconds``."""
    t0 = time.perf_counter()
    far = FAR_FROM_TARGET * float(np.linalg.norm(Vt.max(0) - Vt.min(0)))
    d = np.sqrt(igl.point_mesh_squared_distance(V[F].mean(1), Vt, Ft)[0])
    fit = float(np.quantile(d, FIT_QUANTILE)) / (far / FAR_FROM_TARGET)  # in target diagonals
    record = {"fit": round(fit, 5), "checked": fit < FAR_FROM_TARGET, "perforated": 0, "sealed": False}
    if record["checked"]:
        edge = float(np.linalg.norm(V[F[:, 0]] - V[F[:, 1]], axis=1).mean())
        cut = perforate(V, F, Vt, Ft, d > far, thickness=SHEET_THICKNESS * edge)
        if cut is not None:
            V, F, record["perforated"] = cut
        if _hull_volume(V) >= SEAL_GAIN * abs(_signed_volume(V, F)):
            sealed = seal(V, F, Vt, Ft, spacing=float(np.linalg.norm(V.max(0) - V.min(0))) / SEAL_VOXELS)
            if sealed is not None:
                (V, F), record["sealed"] = sealed, True
    record["seconds"] = round(time.perf_counter() - t0, 4)
    return V, F, record


def _hull_volume(V: np.ndarray) -> float:
    return float(ConvexHull(V).volume)


def _face_components(F: np.ndarray, chosen: np.ndarray) -> list[np.ndarray]:
    """The faces ``chosen`` (indices) grouped by shared edges, largest first."""
    if len(chosen) == 0:
        return []
    tt = igl.triangle_triangle_adjacency(F)[0][chosen]  # (k, 3) neighbour faces, -1 at a boundary
    pos = -np.ones(len(F), dtype=np.int64)
    pos[chosen] = np.arange(len(chosen))
    nb = np.where(tt >= 0, pos[np.maximum(tt, 0)], -1)
    rows = np.repeat(np.arange(len(chosen)), 3)
    keep = nb.reshape(-1) >= 0
    A = sp.coo_matrix((np.ones(keep.sum()), (rows[keep], nb.reshape(-1)[keep])), shape=(len(chosen),) * 2)
    _, label = connected_components(A, directed=False)
    groups = [chosen[label == k] for k in range(label.max() + 1)]
    return sorted(groups, key=len, reverse=True)


def _is_disk(F: np.ndarray) -> bool:
    """Whether the faces ``F`` form one disk: Euler characteristic 1 and one boundary loop."""
    nv = len(np.unique(F))
    E = igl.edges(F)
    if nv - len(E) + len(F) != 1:
        return False
    return len(_boundary_loops(F)) == 1


def _boundary_loops(F: np.ndarray) -> list[list[int]] | None:
    """The boundary loops of ``F`` as vertex lists in the direction of their faces' half-edges (None where a
    vertex has two boundary half-edges leaving it, a pinch no loop is drawn through)."""
    he = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    key = {(int(a), int(b)) for a, b in he}
    nxt = {}
    for a, b in key:
        if (b, a) not in key:
            if a in nxt:
                return None
            nxt[a] = b
    loops, seen = [], set()
    for start in nxt:
        if start in seen:
            continue
        loop, v = [], start
        while v not in seen:
            seen.add(v)
            loop.append(v)
            v = nxt[v]
        if v != start:
            return None
        loops.append(loop)
    return loops


def sheet_patches(V: np.ndarray, F: np.ndarray, Vt: np.ndarray, Ft: np.ndarray, off: np.ndarray, *,
                  thickness: float) -> list:
    """Pairs of face patches ``(A, B)`` (face index arrays) of ``(V, F)``, the two sides of one sheet that spans
    an opening of the target ``(Vt, Ft)``.

    A patch is a disk of faces that are off the target (``off``, a bool per face). Two
    patches are the sides of a sheet when their mean normals point apart (cosine below -0.5) and each one's
    centre lies behind the other, against its normal, within ``thickness``, and the target has an opening
    there: the point between the two centres is open both ways along the sheet's normal and surrounded by
    the target in the sheet's plane (:func:`~meshmei.reconstruct.openings.spans_opening`; a thin part of the
    mesh that is off the target but lies over it is no sheet to cut). Each patch is used once, the nearest
    pairs first.
    """
    C = V[F].mean(1)
    patches = [p for p in _face_components(F, np.flatnonzero(off)) if _is_disk(F[p])]
    if len(patches) < 2:
        return []
    N = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])  # area-weighted normals
    centre = np.array([C[p].mean(0) for p in patches])
    normal = np.array([N[p].sum(0) for p in patches])
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-300)
    pairs = []
    for i in range(len(patches)):
        for j in range(i + 1, len(patches)):
            gap = centre[j] - centre[i]
            dist = float(np.linalg.norm(gap))
            if (dist <= thickness and normal[i] @ normal[j] < -0.5 and gap @ normal[i] < 0
                    and -gap @ normal[j] < 0):
                pairs.append((dist, i, j))
    pairs.sort()
    if pairs:
        middle = np.array([0.5 * (centre[i] + centre[j]) for _, i, j in pairs])
        axis = np.array([normal[i] - normal[j] for _, i, j in pairs])
        pairs = [p for p, ok in zip(pairs, spans_opening(Vt, Ft, middle, axis)) if ok]
    used, out = set(), []
    for _, i, j in pairs:
        if i not in used and j not in used:
            used |= {i, j}
            out.append((patches[i], patches[j]))
    return out


def _zip(a: list[int], b: list[int], V: np.ndarray) -> list[tuple[int, int, int]]:
    """Triangles of a tube between loop ``a`` (in its faces' direction) and loop ``b`` (against its faces'
    direction, so running beside ``a``), starting at ``b``'s vertex nearest ``a[0]`` and stepping along
    whichever loop gives the shorter new edge."""
    s = int(np.argmin(np.linalg.norm(V[b] - V[a[0]], axis=1)))
    b = b[s:] + b[:s]
    n, m = len(a), len(b)
    i = j = 0
    tris = []
    while i < n or j < m:
        ai, ai1, bj, bj1 = a[i % n], a[(i + 1) % n], b[j % m], b[(j + 1) % m]
        step_a = j >= m or (i < n and np.linalg.norm(V[ai1] - V[bj]) <= np.linalg.norm(V[bj1] - V[ai]))
        if step_a:
            tris.append((ai1, ai, bj))
            i += 1
        else:
            tris.append((bj, bj1, ai))
            j += 1
    return tris


def perforate(V: np.ndarray, F: np.ndarray, Vt: np.ndarray, Ft: np.ndarray, off: np.ndarray, *, thickness: float):
    """``(V, F)`` with a hole cut through each sheet that :func:`sheet_patches` finds, or None where it finds
    none or no cut passes the checks (closed, edge-manifold, the Euler characteristic two lower for each
    cut, no intersecting pair). Each sheet is cut alone first; those that pass are cut together, or, if
    that fails the checks, only the first of them. Returns ``(V2, F2, cuts)``, ``cuts`` the number of holes
    cut; the vertices inside the removed patches are dropped."""
    pairs = sheet_patches(V, F, Vt, Ft, off, thickness=thickness)
    euler = topology(F)["euler"]
    passing = [p for p in pairs if _cut(V, F, [p], euler) is not None]
    for chosen in ([passing, passing[:1]] if len(passing) > 1 else [passing] if passing else []):
        got = _cut(V, F, chosen, euler)
        if got is not None:
            return (*got, len(chosen))
    return None


def _cut(V: np.ndarray, F: np.ndarray, pairs, euler: int):
    """``(V, F)`` with each pair of patches in ``pairs`` taken out and joined by a tube, or None where the
    result fails :func:`perforate`'s checks."""
    drop = np.concatenate([np.concatenate(p) for p in pairs])
    keep = np.ones(len(F), dtype=bool)
    keep[drop] = False
    tube = []
    for A, B in pairs:
        la, lb = _boundary_loops(F[A]), _boundary_loops(F[B])
        # a patch's own loop runs against the hole's loop in the faces that stay
        tube += _zip(la[0][::-1], lb[0], V)
    F2 = np.concatenate([F[keep], np.asarray(tube, dtype=F.dtype).reshape(-1, 3)])
    used = np.unique(F2)
    remap = -np.ones(len(V), dtype=np.int64)
    remap[used] = np.arange(len(used))
    V2, F2 = V[used], remap[F2]
    got = topology(F2)
    if (got["euler"] == euler - 2 * len(pairs) and not got["nonmanifold_edges"] and not got["nonmanifold_vertices"]
            and _closed(F2) and len(self_intersecting_pairs(V2, F2)) == 0):
        return V2, F2
    return None


def _closed(F: np.ndarray) -> bool:
    """Every edge of ``F`` used by exactly two faces."""
    E = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
    _, count = np.unique(E, axis=0, return_counts=True)
    return bool((count == 2).all())


def seal(V: np.ndarray, F: np.ndarray, Vt: np.ndarray, Ft: np.ndarray, *, spacing: float,
         min_gain: float = SEAL_GAIN):
    """The solid of ``(V, F)`` with its thin passages sealed and the cavities they close filled, as a new mesh,
    or None where that adds less than ``min_gain - 1`` times the solid's own volume, or fills space that the
    target ``(Vt, Ft)`` does not enclose (winding number under one half at most of
    :data:`SEAL_PROBES` points of what it adds).

    The solid is voxelised at ``spacing`` (inside by winding number, and the voxels the surface passes
    through with their neighbours, so a wall thinner than a voxel stays whole and tight), closed by one voxel (a passage at most two voxels
    wide is sealed), its enclosed cavities filled and the one-voxel thickening eroded away again; the largest
    piece's boundary is extracted by marching cubes on the lightly smoothed occupancy (None where that has an
    intersecting pair or an open edge)."""
    lo = V.min(0) - 4 * spacing
    n = np.ceil((V.max(0) + 4 * spacing - lo) / spacing).astype(int) + 1
    G = lo + spacing * np.stack(np.meshgrid(*[np.arange(k) for k in n], indexing="ij"), -1)
    solid = np.abs(igl.fast_winding_number(V, F, G.reshape(-1, 3)).reshape(n)) > 0.5
    # the surface's own voxels: points of every face at a third of a voxel apart
    area = 0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1)
    P = _surface_points(V, F, area, spacing / 3.0)
    surface = np.zeros(n, dtype=bool)
    surface[tuple(np.floor((P - lo) / spacing + 0.5).astype(int).T)] = True
    ball = ndi.generate_binary_structure(3, 1)
    solid |= ndi.binary_dilation(surface, ball)  # a wall at least two voxels thick: no leak between voxels
    before = int(solid.sum())
    filled = ndi.binary_fill_holes(ndi.binary_closing(solid, ball))
    if filled.sum() < min_gain * before:
        return None
    added = np.flatnonzero((filled & ~solid).reshape(-1))
    probes = G.reshape(-1, 3)[added[np.linspace(0, len(added) - 1, min(SEAL_PROBES, len(added))).astype(int)]]
    if np.mean(np.abs(igl.fast_winding_number(Vt, Ft, probes)) > 0.5) < 0.5:
        return None
    filled = ndi.binary_erosion(filled, ball)
    label, count = ndi.label(filled)
    if count == 0:
        return None
    filled = label == 1 + int(np.argmax(ndi.sum(filled, label, range(1, count + 1))))
    S = ndi.gaussian_filter(filled.astype(float), 1.0)
    # libigl's grid order: x fastest, then y, then z
    Vm, Fm, _ = igl.marching_cubes(S.transpose(2, 1, 0).reshape(-1), G.transpose(2, 1, 0, 3).reshape(-1, 3),
                                   int(n[0]), int(n[1]), int(n[2]), 0.5)
    Fm = np.asarray(Fm, dtype=np.int64)
    if _signed_volume(Vm, Fm) < 0:  # outward normals, as the meshes of a reconstruction have
        Fm = Fm[:, ::-1].copy()
    if len(self_intersecting_pairs(Vm, Fm)) or not _closed(Fm):
        return None
    return Vm, Fm


def _surface_points(V, F, area, spacing):
    """Points on every face of ``(V, F)``, about ``spacing`` apart (barycentric lattice per face)."""
    k = np.clip(np.ceil(np.sqrt(2.0 * area) / spacing).astype(int), 1, 64)
    out = []
    for m in np.unique(k):
        faces = F[k == m]
        i, j = np.meshgrid(np.arange(m + 1), np.arange(m + 1), indexing="ij")
        keep = i + j <= m
        b = np.stack([i[keep], j[keep], m - i[keep] - j[keep]], 1) / m  # (p, 3) barycentric
        out.append(np.einsum("pk,fkd->fpd", b, V[faces]).reshape(-1, 3))
    return np.concatenate(out)


def _signed_volume(V, F) -> float:
    return float(np.einsum("ij,ij->i", V[F[:, 0]], np.cross(V[F[:, 1]], V[F[:, 2]])).sum() / 6.0)
