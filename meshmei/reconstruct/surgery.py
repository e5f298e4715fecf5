"""Topology surgery between the stages of a reconstruction: the one way a fit changes its start's topology.

A deformation keeps the start's topology. A torus whose hole is not where the target's is (the centred torus
on the teapot) ends as the target's surface with two defects the guard's clean steps cannot remove:

- a **sheet** of its own solid spanning the target's opening (the teapot's handle), far from every target
  point, where it costs Chamfer accuracy no deformation removes (the membrane floor,
  :func:`meshmei.benchmarks.reconstruct.membrane_floor`);
- its own hole, which had nowhere to go, pressed shut into **thin passages**, the body around it a shell of
  two layers held apart by the contact barrier, each off the target by half that gap.

:func:`adapt_topology` mends both once the fit is close elsewhere: :func:`perforate` cuts a hole through each
sheet (the faces of both sides over the off-target part taken out, the two holes joined by a short tube: a
handle added), and :func:`seal` rebuilds the solid from voxels with its thin passages closed (and holes
plugged where the target has surface) and the cavities they close filled, carving out a sheet the mesh
could not be cut through, or closing a passage a cut left (the start's hole pressed shut inside a solid that
fills the target, where a seal adds no volume). Each result is closed, manifold and free of intersecting
pairs, or the mesh is left as it was. The target is used only to decide: which faces are off it, whether it
has an opening where a sheet is, whether it encloses what a seal fills, and where it has surface across a
hole.
"""

from __future__ import annotations

import time

import igl
import numpy as np
import scipy.ndimage as ndi
import scipy.sparse as sp
import torch
from scipy.sparse.csgraph import connected_components
from scipy.spatial import ConvexHull, QhullError, cKDTree

from ..metrics import face_components
from ..quality import edge_use, self_intersecting_pairs, signed_volume, topology
from .openings import spans_opening

__all__ = ["FAR_FROM_TARGET", "FIT_QUANTILE", "FIT_GATE", "CUT_REACH", "SHEET_THICKNESS", "SEAL_VOXELS",
           "SEAL_GAIN", "SEAL_REACH", "SEAL_PROBES", "SEAL_SMALL", "SEAL_REFUSED", "adapt_topology", "perforate",
           "seal", "sheet_patches", "surgery_lines"]

# A face is off the target when its centroid is farther than this share of the target's bounding-box
# diagonal from it: the F-score's threshold, where a sample counts as wrong
FAR_FROM_TARGET = 0.01
# Surgery is tried only once the fit is close elsewhere: this quantile of the faces' distances under FIT_GATE
# of the diagonal. On the centred teapot's default run at 2.5k: 0.025, 0.011 and 0.004 after the 151-, 625-
# and first 2,500-vertex stages; at 10k 0.035, 0.013, 0.0064 and 0.0067 after the 144-, 557- and the two
# 2,500-vertex stages. With 0.01 the 2.5k runs of 30 and 100 s were mended only before their last stage,
# too late to fit again (1.7e-5 and 1.6e-5); with 0.02 the 30 s run is mended after its 625-vertex stage
# (1.7e-6 at 30 s)
FIT_QUANTILE = 0.9
FIT_GATE = 0.02
# Two off-target patches form a sheet when each lies behind the other (against its outward normal) within
# this many of the mesh's mean edge lengths
SHEET_THICKNESS = 2.0
# seal's voxels: this many along the mesh's bounding-box diagonal (0.9 million on the centred torus's teapot
# fits, a seal 0.45 to 0.6 s with its checks)
SEAL_VOXELS = 160
# seal keeps its result only where closing the passages encloses at least this many times the solid's volume
# (tried only where the convex hull could hold that much)
SEAL_GAIN = 2.0
# ... counting as part of the solid the target's own surface within this many voxels of it
SEAL_REACH = 8
# ... and only where the target encloses most of what it would add (the winding number at this many points)
SEAL_PROBES = 2000
# ... unless it adds less than this share of the solid's volume
SEAL_SMALL = 0.1
# Why a seal was refused, as adapt_topology records it (record["seal"])
SEAL_REFUSED = {"gain": "it would add too little", "outside": "it would fill space the target does not enclose",
                "empty": "nothing was left after erosion", "extraction": "its surface intersects itself or is open",
                "passage": "it closes no passage a cut left, or fills a sheet"}


def adapt_topology(V: np.ndarray, F: np.ndarray, Vt: np.ndarray, Ft: np.ndarray):
    """``(V, F)`` with its sheets perforated and its thin passages sealed where the fit to ``(Vt, Ft)`` is
    close elsewhere (:data:`FIT_QUANTILE`): ``(V2, F2, record)``, the arrays given back unchanged where
    nothing was done. ``record``: ``fit`` (the :data:`FIT_QUANTILE` quantile of the faces' distances to the
    target, in target diagonals), ``checked`` (whether that was close enough to try), ``perforated`` (holes
    cut in the mesh), ``sealed``, ``carved`` (sheets the mesh could not be cut through, cut in seal's voxels
    instead) and ``seconds``; where a seal was tried, ``seal``: "kept", or why it was refused (a value of
    :data:`SEAL_REFUSED`; a refused seal costs about as much as a kept one, 0.45 to 0.6 s on the teapot)."""
    t0 = time.perf_counter()
    far = FAR_FROM_TARGET * float(np.linalg.norm(Vt.max(0) - Vt.min(0)))
    d = np.sqrt(igl.point_mesh_squared_distance(V[F].mean(1), Vt, Ft)[0])
    fit = float(np.quantile(d, FIT_QUANTILE)) / (far / FAR_FROM_TARGET)  # in target diagonals
    record = {"fit": round(fit, 5), "checked": fit < FIT_GATE, "perforated": 0, "sealed": False,
              "carved": 0}
    if record["checked"]:
        thickness = SHEET_THICKNESS * float(np.linalg.norm(V[F[:, 0]] - V[F[:, 1]], axis=1).mean())
        pairs = sheet_patches(V, F, Vt, Ft, d > far, thickness=thickness)
        cut = _perforated(V, F, pairs, thickness)
        # the sheets as points, for seal to carve out of the solid where it rebuilds the mesh
        sheets = [_surface_points(V, G, thickness / 4.0) for G in (F[np.concatenate(p)] for p in pairs)]
        spacing = float(np.linalg.norm(V.max(0) - V.min(0))) / SEAL_VOXELS
        sealed, carve = None, sheets
        if cut is None and (sheets or _may_seal(V, F, Vt, Ft)):
            # sheets the mesh could not be cut through (the tube between their holes crossed the mesh) are
            # carved by a seal whatever the cavities; without sheets the seal must fill one
            sealed, record["seal"] = _sealed(V, F, Vt, Ft, spacing=spacing, min_gain=0.0 if sheets else SEAL_GAIN,
                                             carve=sheets, reach=thickness, far=far)
        elif cut is not None and _may_seal(*cut[:2], Vt, Ft):
            V, F, record["perforated"] = cut
            sealed, record["seal"] = _sealed(V, F, Vt, Ft, spacing=spacing, min_gain=SEAL_GAIN, carve=[],
                                             reach=thickness, far=far)
            carve = []
        elif cut is not None:
            # a cut may leave a passage: the start's own hole pressed shut inside a solid that fills the target,
            # where a seal adds too little to pass _may_seal (the centred teapot at 2.5k: 3 of 12 30 s runs cut
            # the handle's sheet and kept that passage, ending near 1e-5 where the others, sealed, reach 2e-6).
            # Where the uncut mesh has a handle (a passage is one), a seal of the cut mesh, or failing that one
            # that carves the sheets instead, is kept where it closes a passage and leaves every sheet open
            U, G, record["perforated"] = cut
            if _handles(F):
                C = V[F].mean(1)
                gate = (topology(G)["euler"], topology(F)["euler"],
                        np.array([0.5 * (C[a].mean(0) + C[b].mean(0)) for a, b in pairs]))
                for W, H, made, carve in ((U, G, record["perforated"], []), (V, F, 0, sheets)):
                    sealed, record["seal"] = _sealed(W, H, Vt, Ft, spacing=spacing, min_gain=0.0, carve=carve,
                                                     reach=thickness, far=far, after_cut=gate)
                    if sealed is not None:
                        record["perforated"] = made
                        break
            V, F = U, G
        if sealed is not None:
            (V, F), record["sealed"], record["carved"] = sealed, True, len(carve)
    record["seconds"] = round(time.perf_counter() - t0, 4)
    return V, F, record


def _may_seal(V: np.ndarray, F: np.ndarray, Vt: np.ndarray, Ft: np.ndarray) -> bool:
    """Whether a seal could keep its result: of :data:`SEAL_PROBES` points spread over the mesh's bounding box
    (a fixed draw), the target encloses at least :data:`SEAL_GAIN` times as many as the mesh does (a seal
    fills only space the target encloses, and must fill that much); a few milliseconds, where a seal that
    fails takes seconds (the cup's thin shell: 7.6 s over three stages, for nothing)."""
    if _hull_volume(V) < SEAL_GAIN * abs(signed_volume(V, F)):
        return False
    P = V.min(0) + np.random.default_rng(0).random((SEAL_PROBES, 3)) * (V.max(0) - V.min(0))
    in_target = int((np.abs(igl.fast_winding_number(Vt, Ft, P)) > 0.5).sum())
    in_mesh = int((np.abs(igl.fast_winding_number(V, F, P)) > 0.5).sum())
    return in_target >= SEAL_GAIN * max(in_mesh, 1)


def _handles(F: np.ndarray) -> int:
    """The handles (genus, summed over the pieces) of the closed mesh with faces ``F``."""
    pieces = int(face_components(F, int(F.max()) + 1).max()) + 1
    return (2 * pieces - topology(F)["euler"]) // 2


def _hull_volume(V: np.ndarray) -> float:
    """The convex hull's volume; 0 for points in a plane or on a line (qhull refuses them)."""
    try:
        return float(ConvexHull(V).volume)
    except QhullError:
        return 0.0


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
    loops = _boundary_loops(F)
    return loops is not None and len(loops) == 1


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
    there: the point between the two centres is open both ways along the sheet's normal (the sides' mean
    normal, or failing that either side's own) and surrounded by the target in the sheet's plane
    (:func:`~meshmei.reconstruct.openings.spans_opening`; a thin part of the mesh that is off the target but
    lies over it is no sheet to cut). Each patch is used once, the nearest pairs first.
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
        # the sheet's normal: the two sides' mean, or where the sides tilt apart either side's own (on the
        # centred teapot's 600-vertex fits the handle's sheet was open along one side's normal and not along
        # the mean, 20 degrees off it, in 7 of 12 30 s runs; those waited for the next stage's check)
        middle = np.array([0.5 * (centre[i] + centre[j]) for _, i, j in pairs])
        ok = np.zeros(len(pairs), dtype=bool)
        for axis in ([normal[i] - normal[j] for _, i, j in pairs], [normal[i] for _, i, _ in pairs],
                     [normal[j] for _, _, j in pairs]):
            ok[~ok] = spans_opening(Vt, Ft, middle[~ok], np.array(axis)[~ok])
            if ok.all():  # (each call builds a ray tree of the target)
                break
        pairs = [p for p, o in zip(pairs, ok) if o]
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
    cut, no intersecting pair).

    A sheet is cut through two disks facing each other across it: for each of :data:`CUT_REACH` in turn,
    the faces of each side over the off-target faces of either side (:func:`_facing_disks`); failing both,
    the two off-target patches themselves (whose holes may not face each other, so that the tube between
    them may cross the sheet). Each sheet is cut alone first, by the first of these that passes; those that
    pass are cut together, or, if that fails the checks, only the first of them. Returns ``(V2, F2, cuts)``,
    ``cuts`` the number of holes cut; the vertices inside the removed faces are dropped."""
    return _perforated(V, F, sheet_patches(V, F, Vt, Ft, off, thickness=thickness), thickness)


def _perforated(V: np.ndarray, F: np.ndarray, pairs: list, thickness: float):
    """:func:`perforate` of the sheets ``pairs`` (:func:`sheet_patches`), found already."""
    if not pairs:
        return None
    euler = topology(F)["euler"]
    tt = igl.triangle_triangle_adjacency(F)[0]
    edge = float(np.linalg.norm(V[F[:, 0]] - V[F[:, 1]], axis=1).mean())
    C = V[F].mean(1)
    N = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    N /= np.maximum(np.linalg.norm(N, axis=1, keepdims=True), 1e-300)
    passing, alone = [], []  # each sheet's first cut that passes, and its result
    for A, B in pairs:
        for cut in [*_facing_disks(A, B, F, C, N, tt, thickness, edge), (A, B)]:
            got = _cut(V, F, [cut], euler)
            if got is not None:
                passing.append(cut)
                alone.append(got)
                break
    if not passing:
        return None
    if len(passing) > 1:
        got = _cut(V, F, passing, euler)
        if got is not None:
            return (*got, len(passing))
    return (*alone[0], 1)


# perforate's cut: on each side of a sheet, the faces within this many mean edge lengths (across the sheet's
# plane) of the off-target faces of either side, wider first
CUT_REACH = (1.0, 0.5)


def _facing_disks(A, B, F, C, N, tt, thickness: float, edge: float):
    """Pairs of disks ``(A', B')`` that cover the same part of the sheet whose sides are the patches ``A`` and
    ``B``, one per reach of :data:`CUT_REACH`: on each side, the faces reached across edges from the patch,
    facing that side's way (against the other side's), within ``thickness`` of the sheet's middle plane and,
    across it, within the reach of a face of ``A`` or ``B``. The two off-target patches need not lie over each
    other, and a tube between holes that do not face each other crosses the sheet."""
    nA, nB = N[A].sum(0), N[B].sum(0)
    axis = nA / np.linalg.norm(nA) - nB / np.linalg.norm(nB)
    axis /= np.linalg.norm(axis)
    middle = 0.5 * (C[A].mean(0) + C[B].mean(0))
    height = (C - middle) @ axis
    flat = C - height[:, None] * axis  # centroids moved onto the middle plane
    tree = cKDTree(flat[np.concatenate([A, B])])
    for reach in CUT_REACH:
        near = np.isfinite(tree.query(flat, distance_upper_bound=reach * edge)[0]) & (np.abs(height) <= thickness)
        sides = []
        for patch, sign in ((A, 1.0), (B, -1.0)):
            ok = near & (sign * (N @ axis) > 0)
            ok[patch] = True
            disk = _grown(int(patch[0]), ok, tt)
            if not _is_disk(F[disk]):
                break
            sides.append(disk)
        if len(sides) == 2:
            yield sides[0], sides[1]


def _grown(seed: int, ok: np.ndarray, tt: np.ndarray) -> np.ndarray:
    """The faces with ``ok`` reached from ``seed`` across edges (``tt``: libigl's face adjacency)."""
    seen, todo = {seed}, [seed]
    while todo:
        f = todo.pop()
        for g in tt[f]:
            if g >= 0 and ok[g] and g not in seen:
                seen.add(int(g))
                todo.append(int(g))
    return np.array(sorted(seen), dtype=np.int64)


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
    return edge_use(torch.from_numpy(np.ascontiguousarray(F))) == (0, 0)


def seal(V: np.ndarray, F: np.ndarray, Vt: np.ndarray, Ft: np.ndarray, *, spacing: float,
         min_gain: float = SEAL_GAIN, carve=(), reach: float = 0.0, far: float = 0.0):
    """The solid of ``(V, F)`` with its thin passages sealed and the cavities they close filled, as a new mesh,
    or None where that adds less than ``min_gain - 1`` times the solid's own volume, or fills space that the
    target ``(Vt, Ft)`` does not enclose (winding number under one half at most of
    :data:`SEAL_PROBES` points of what it adds).

    The solid is voxelised at ``spacing`` (inside by winding number, and the voxels the surface passes
    through with their neighbours, so that a wall thinner than a voxel stays whole and tight). The target's
    own surface voxels within :data:`SEAL_REACH` voxels of it are added (they plug a hole the mesh has where
    the target has surface, as the teapot's lid, through which the torus's hole leaves), the whole closed by
    one voxel (a passage at most two voxels wide is sealed), its enclosed cavities filled and a voxel eroded
    away again; the largest piece's boundary is extracted by marching cubes on the lightly smoothed
    occupancy (None where that has an intersecting pair or an open edge)."""
    return _sealed(V, F, Vt, Ft, spacing=spacing, min_gain=min_gain, carve=carve, reach=reach, far=far)[0]


def _sealed(V, F, Vt, Ft, *, spacing: float, min_gain: float, carve, reach: float, far: float, after_cut=None):
    """:func:`seal`'s mesh (or None) and "kept" or the :data:`SEAL_REFUSED` reason for None. With
    ``after_cut``, ``(cut, uncut, middles)``, the Euler characteristics of a mesh with its sheets cut and
    without, and the sheets' middles: kept only where the result's Euler characteristic lies above ``cut``
    and at most ``uncut`` (it closes a passage) and every middle lies outside it (no sheet stays)."""
    lo, n, G, wall = _grid(V, F, spacing)
    inside = abs(signed_volume(V, F)) / spacing ** 3  # the solid's own volume, in voxels
    ball = ndi.generate_binary_structure(3, 1)
    solid = wall | _inside(V, F, G, wall, lo, spacing)
    before = int(solid.sum())
    # the target's surface where it passes within SEAL_REACH voxels of the solid: it plugs a hole the mesh has
    # where the target has surface (the teapot's lid, through which the torus's hole left)
    plug = ndi.binary_dilation(_voxels(_surface_points(Vt, Ft, spacing / 3.0), lo, spacing, n), ball)
    plug &= ndi.distance_transform_edt(~solid) <= SEAL_REACH
    filled = ndi.binary_fill_holes(ndi.binary_closing(solid | plug, ball))
    # what the seal adds, against the solid's own volume (not its voxels with the thickened walls, mostly wall
    # in a thin shell: measured so, seals that filled the teapot counted as adding too little)
    if filled.sum() - before < (min_gain - 1.0) * inside:
        return None, SEAL_REFUSED["gain"]
    added = np.flatnonzero((filled & ~solid).reshape(-1))
    if len(added) > SEAL_SMALL * before:  # (a rebuild for carving alone may add a little, and that unchecked)
        probes = G.reshape(-1, 3)[added[np.linspace(0, len(added) - 1, min(SEAL_PROBES, len(added))).astype(int)]]
        if np.mean(np.abs(igl.fast_winding_number(Vt, Ft, probes)) > 0.5) < 0.5:
            return None, SEAL_REFUSED["outside"]
    for P in carve:
        grown = ndi.binary_dilation(_voxels(P, lo, spacing, n), ball, iterations=int(np.ceil(reach / spacing)) + 1)
        cand = np.flatnonzero((grown & filled).reshape(-1))
        Q = G.reshape(-1, 3)[cand]
        clear = np.sqrt(igl.point_mesh_squared_distance(Q, Vt, Ft)[0]) > far
        clear &= np.abs(igl.fast_winding_number(Vt, Ft, Q)) < 0.5  # outside the target's solid (not a handle's core)
        filled.reshape(-1)[cand[clear]] = False
    filled = ndi.binary_erosion(filled, ball)
    label, count = ndi.label(filled)
    if count == 0:
        return None, SEAL_REFUSED["empty"]
    filled = label == 1 + int(np.argmax(ndi.sum(filled, label, range(1, count + 1))))
    S = ndi.gaussian_filter(filled.astype(float), 1.0)
    # libigl's grid order: x fastest, then y, then z
    Vm, Fm, _ = igl.marching_cubes(S.transpose(2, 1, 0).reshape(-1), G.transpose(2, 1, 0, 3).reshape(-1, 3),
                                   int(n[0]), int(n[1]), int(n[2]), 0.5)
    Fm = np.asarray(Fm, dtype=np.int64)
    if signed_volume(Vm, Fm) < 0:  # outward normals, as the meshes of a reconstruction have
        Fm = Fm[:, ::-1].copy()
    if len(self_intersecting_pairs(Vm, Fm)) or not _closed(Fm):
        return None, SEAL_REFUSED["extraction"]
    if after_cut is not None:
        cut, uncut, middles = after_cut
        if not (cut < topology(Fm)["euler"] <= uncut
                and (np.abs(igl.fast_winding_number(Vm, Fm, middles)) < 0.5).all()):
            return None, SEAL_REFUSED["passage"]
    return (Vm, Fm), "kept"


def _grid(V, F, spacing: float):
    """:func:`seal`'s voxels for ``(V, F)`` at ``spacing``: ``(lo, n, G, wall)``, the grid's corner, shape and
    centres ``(*n, 3)`` (the mesh's box and four voxels around it), and the wall: the voxels of points of every
    face a third of a voxel apart, with their neighbours (walls two voxels thick: no leak between)."""
    lo = V.min(0) - 4 * spacing
    n = np.ceil((V.max(0) + 4 * spacing - lo) / spacing).astype(int) + 1
    G = lo + spacing * np.stack(np.meshgrid(*[np.arange(k) for k in n], indexing="ij"), -1)
    P = _surface_points(V, F, spacing / 3.0)
    return lo, n, G, ndi.binary_dilation(_voxels(P, lo, spacing, n), ndi.generate_binary_structure(3, 1))


# _inside: a wall whose points leave no point of the surface farther than this many voxels (under one half:
# then the surface cannot pass between two neighbouring voxels outside the wall), and the winding number at
# up to PIECE_PROBES voxels of each piece of the grid outside it
COVER = 0.45
PIECE_PROBES = 16


def _inside(V, F, G, wall, lo, spacing: float) -> np.ndarray:
    """The voxels of the grid ``G`` (centres, ``(*n, 3)``; corner ``lo``) inside the closed mesh ``(V, F)`` by
    winding number, outside ``wall`` (the voxels of the surface's points, with their neighbours).

    The surface crosses no segment between two neighbouring voxels that a tight wall leaves out, so each
    6-connected piece of the rest of the grid lies on one side of it, and its winding number is taken at
    :data:`PIECE_PROBES` of its voxels. The wall is made tight by points added on the faces that its own
    lattice leaves too coarse (:data:`COVER`), and those points' voxels are tested one by one: by the exact
    winding number the result is that of every voxel, and on the centred torus's teapot fits libigl's fast
    one gave the same seals bit for bit (285 to 716 points for about 900,000: 0.04-0.06 s for 1.0). Every voxel
    is tested where a face would need more than 64 subdivisions, or a piece's probes disagree."""
    n = wall.shape
    Q, tight = _cover_points(V, F, spacing / 3.0, COVER * spacing)
    if tight:
        ball = ndi.generate_binary_structure(3, 1)
        extra = ndi.binary_dilation(_voxels(Q, lo, spacing, n), ball) & ~wall if len(Q) else np.zeros(n, bool)
        label, count = ndi.label(~(wall | extra))
        flat = label.reshape(-1)
        order = np.argsort(flat, kind="stable")
        bounds = np.searchsorted(flat[order], np.arange(1, count + 2))  # each piece's run in ``order``
        size = np.diff(bounds)
        k = np.minimum(size, PIECE_PROBES)
        piece = np.repeat(np.arange(count), k)
        at = bounds[piece] + (np.arange(k.sum()) - np.repeat(np.cumsum(k) - k, k)) * (size[piece] // k[piece])
        tested = np.concatenate([order[at], np.flatnonzero(extra.reshape(-1))])
        w = np.abs(igl.fast_winding_number(V, F, G.reshape(-1, 3)[tested])) > 0.5
        votes = np.bincount(piece, weights=w[:len(piece)], minlength=count)
        if np.all((votes == 0) | (votes == k)):
            out = np.concatenate([[False], votes > 0])[label]
            out.reshape(-1)[tested[len(piece):]] = w[len(piece):]
            return out
    return (np.abs(igl.fast_winding_number(V, F, G.reshape(-1, 3)).reshape(n)) > 0.5) & ~wall


def _voxels(P, lo, spacing: float, n) -> np.ndarray:
    """The voxels of a grid (corner ``lo``, ``spacing``, shape ``n``) that hold a point of ``P``."""
    idx = np.floor((P - lo) / spacing + 0.5).astype(int)
    idx = idx[((idx >= 0) & (idx < n)).all(1)]
    out = np.zeros(n, dtype=bool)
    out[tuple(idx.T)] = True
    return out


def _surface_points(V, F, spacing):
    """Points on every face of ``(V, F)``, about ``spacing`` apart (barycentric lattice per face)."""
    return _lattice(V, F, _subdivisions(V, F, spacing))


def _subdivisions(V, F, spacing) -> np.ndarray:
    """:func:`_surface_points`' subdivisions of each face's edges: 1 to 64."""
    return np.clip(np.ceil(np.sqrt(igl.doublearea(V, F).ravel()) / spacing).astype(int), 1, 64)


def _cover_points(V, F, spacing, cover):
    """``(points, tight)``: points on the faces of ``(V, F)`` whose :func:`_surface_points` lattice at
    ``spacing`` is too coarse to leave no point of the face farther than ``cover`` from a lattice point (long
    thin faces), on a lattice fine enough: each of a lattice's triangles is its face shrunk, and no point of a
    triangle is farther than its longest edge over the square root of 3 from a corner. ``tight``: no face
    needed more than 64 subdivisions for that."""
    longest = np.linalg.norm(V[F] - V[np.roll(F, 1, axis=1)], axis=2).max(1)
    k = np.maximum(np.ceil(longest / (np.sqrt(3.0) * cover)).astype(int), 1)
    coarse = k > _subdivisions(V, F, spacing)
    tight = bool(k.max(initial=1) <= 64)
    return _lattice(V, F[coarse], np.minimum(k[coarse], 64)), tight


def _lattice(V, F, k) -> np.ndarray:
    """The points of each face ``F[i]`` at barycentric coordinates in steps of ``1 / k[i]``."""
    out = [np.zeros((0, 3), dtype=V.dtype)]
    for m in np.unique(k):
        faces = F[k == m]
        i, j = np.meshgrid(np.arange(m + 1), np.arange(m + 1), indexing="ij")
        keep = i + j <= m
        b = np.stack([i[keep], j[keep], m - i[keep] - j[keep]], 1) / m  # (p, 3) barycentric
        out.append(np.einsum("pk,fkd->fpd", b, V[faces]).reshape(-1, 3))
    return np.concatenate(out)


def surgery_lines(stages) -> list[str]:
    """One line for each stage of a run's ``info["stages"]`` whose start topology surgery changed (none for a
    run without it, or where it changed nothing): what was done and what it took."""
    lines = []
    for k, stage in enumerate(stages):
        s = stage.get("surgery") or {}
        done = [what for what, n in (("a sheet cut", s.get("perforated", 0)),
                                     ("a sheet carved", s.get("carved", 0))) for _ in range(n)]
        if s.get("sealed"):
            done.append("the solid rebuilt with its thin passages sealed")
        if not done:
            continue
        dropped = f" (dropped: {s['dropped']})" if s.get("dropped") else ""
        lines.append(f"topology surgery before stage {k}: {', '.join(done)} ({s['seconds']:.1f} s){dropped}")
    return lines
