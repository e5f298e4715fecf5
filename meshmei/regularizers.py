"""Geometric regularizers that keep an optimised mesh well formed (paper appendix B, plus true ARAP).

All take vertex positions ``V`` of shape ``(n, 3)`` (returning a scalar) or a batch ``(B, n, 3)``
sharing the face array ``F`` (returning ``(B,)``). Rest poses ``V0`` may be ``(n, 3)`` or ``(B, n, 3)``.
They are differentiable, work in float32 and float64, and stay finite on degenerate meshes.

On CPU float tensors the uniform Laplacian, edge and area losses run as compiled kernels
(``meshmei/_regularizers.c``, :mod:`meshmei.native`): each loss with its gradient in one float64 pass, handed
to autograd as the guard's and contact barriers are (the backward only scales the gradient, so they take no
second derivative). Their torch code is the reference and the fallback (no compiler, CUDA, half precision,
:func:`meshmei.native.torch_reference`, squared lengths beyond float64's range); the two agree to rounding
(float32 inputs: the compiled value is the float64 one, rounded once). :func:`regularizer_values` evaluates
several losses as an optimisation step does, those three in one pass.

=====================  ==========================================================================
``laplacian_loss``     uniform: ``mean_i |v_i - mean_{j in N(i)} v_j|^2`` over non-isolated vertices;
                       cotangent: ``sum_i |(L V)_i|^2 / M_i  /  sum_i M_i`` over interior vertices
                       (area-weighted mean of the squared mean-curvature normal ``|2 H n|^2``, a
                       discrete Willmore density)
``edge_loss``          ``mean_e (|e| - mean |e|)^2`` over unique edges
``area_loss``          ``mean_t (A_t - mean A)^2`` over faces
``arap_direction_loss`` ``mean_e |e - (e . d_e) d_e|^2`` with ``d_e = e0 / |e0|`` the rest direction
``arap_loss``          Sorkine-Alexa spokes energy ``sum_i sum_{j in N(i)} w_ij |e'_ij - R_i e_ij|^2``
                       with rest cotangent weights ``w_ij`` (``igl.cotmatrix`` entries) and best-fit
                       rotations ``R_i`` held fixed in the gradient (exact at the fit)
=====================  ==========================================================================

:data:`REGULARIZERS` names each of them, as ``loss(V, V0, F)``, for settings that pick regularizers by name.
"""

from __future__ import annotations

import numbers

import torch

from . import native
from .errors import MeshError
from .mesh import as_faces, check_mesh, check_rest_pose
from .operators import (
    EPS,
    corners,
    cot_laplacian_from_cot,
    doublearea_from_corners,
    face_terms,
    gather,
    index_add,
    massmatrix_from_terms,
    resolve_eps,
    safe_norm,
    sum_xyz,
    uniform_laplacian_from_topology,
)
from .topology import mesh_topology

__all__ = [
    "albedo_roughness",
    "texture_roughness",
    "laplacian_loss",
    "edge_loss",
    "area_loss",
    "arap_direction_loss",
    "arap_loss",
    "best_fit_rotations",
    "REGULARIZERS",
    "REGULARIZER_LABELS",
    "regularizer_values",
    "RESOLUTION_POWERS",
    "scale_weights",
]


def _check_rest(V, V0, F):
    V, F = check_mesh(V, F, batched=None)
    return V, check_rest_pose(V0, V, F).to(V.dtype), F


def _pow2_extent(V):
    """A power of two near the extent of each mesh in ``V``, ``(..., 1, 1)``, without gradient (1 if flat)."""
    X = V.detach()
    ext = (X.amax(-2) - X.amin(-2)).amax(-1)
    _, e = torch.frexp(torch.where(ext > 0, ext, torch.ones_like(ext)))
    return torch.ldexp(torch.ones_like(ext), e - 1)[..., None, None]


# the losses _regularizers.c computes, by name, with the bit that asks for each (its values come in this order)
_COMPILED = {"laplacian": 1, "edge": 2, "area": 4}


def _compiled(V: torch.Tensor, F: torch.Tensor, names) -> torch.Tensor | None:
    """The losses ``names`` (keys of ``_COMPILED``, in its order) of the checked mesh ``V`` ((n, 3) or (B, n, 3))
    and ``F`` by ``_regularizers.c``, in one pass, each with its gradient (:func:`~meshmei.native.with_gradient`):
    ``(k,)`` or ``(k, B)``. None where the kernels do not apply (not built, within
    :func:`~meshmei.native.torch_reference`, not a CPU float32/float64 tensor) or leave the losses to the torch
    code (a nonzero length at unit size beyond float64's normal range)."""
    if not native.available(V):
        return None
    F = F.contiguous()
    Xd, value, grad = native.kernel_buffers(V, len(names))  # (B, n, 3): one mesh as a batch of one
    topo = mesh_topology(F, Xd.shape[1])
    which = sum(_COMPILED[k] for k in names)
    rc = native.library().reg_losses(Xd.shape[0], Xd.shape[1], F.shape[0], topo.n_edges, Xd.ctypes.data, F.data_ptr(),
                                     topo.edges.data_ptr(), topo.nbr_ptr.data_ptr(), topo.nbr_idx.data_ptr(), which,
                                     value.ctypes.data, None if grad is None else grad.ctypes.data)
    if rc != 0:
        return None
    return native.with_gradient(V, value, grad)


def regularizer_values(V, V0, F, names) -> dict:
    """``{name: REGULARIZERS[name](V, V0, F)}`` for ``names``, each () or (B,): the uniform Laplacian, edge and
    area losses among them in one compiled pass with one autograd node (:mod:`meshmei.native`), the others (or
    all of them, where the kernels do not apply) one by one. What an optimisation step evaluates."""
    names = [names] if isinstance(names, str) else list(names)  # "laplacian" was read letter by letter
    unknown = [k for k in names if k not in REGULARIZERS]
    if unknown:
        raise ValueError(f"unknown regularizers {unknown}; known: {', '.join(REGULARIZERS)}")
    together = [k for k in _COMPILED if k in names]
    values = {}
    if len(together) > 1:
        X, G = check_mesh(V, F, batched=None)
        out = _compiled(X, G, together)
        if out is not None:
            values = dict(zip(together, out.unbind(0)))
    return {k: values[k] if k in values else REGULARIZERS[k](V, V0, F) for k in names}


def laplacian_loss(V, F, *, method: str = "uniform", eps: float | None = EPS) -> torch.Tensor:
    """Laplacian smoothness.

    Parameters
    ----------
    V : (n, 3) or (B, n, 3) float tensor
    F : (m, 3) int64 tensor
    method : {"uniform", "cotangent"}
        ``uniform`` is the paper's loss. ``cotangent`` uses the cotangent Laplacian and Voronoi mass
        of the current ``V``; it is insensitive to the mesh's sampling and equals ``4 H^2`` averaged over
        the area on smooth surfaces (``4 / r^2`` on a sphere of radius ``r``). Boundary vertices are left
        out of it: there ``L V`` measures the in-plane curvature of the boundary curve, not bending, so a
        flat sheet scores 0, and so does a mesh without interior mass (every vertex on the boundary, or
        zero area), with a zero gradient.
    eps : float, optional
        Guard on the cotangent weights (see :func:`meshmei.operators.cot_weights`) and on the mass:
        ``M_i`` is held above ``eps`` times the mean vertex mass. Default: from the dtype
        (:func:`meshmei.operators.resolve_eps`).

    Returns
    -------
    () or (B,) float tensor
    """
    V, F = check_mesh(V, F, batched=None)
    topo = mesh_topology(F, V.shape[-2])
    if method == "uniform":
        fast = _compiled(V, F, ["laplacian"])
        if fast is not None:
            return fast[0]
        d = uniform_laplacian_from_topology(V, topo)
        live = topo.degree > 0
        return (sum_xyz(d * d) * live).sum(-1) / live.sum().clamp_min(1)
    if method == "cotangent":
        # The loss has units of 1 / length^2 and its terms of length^2 / area: at a far-from-unit scale their
        # squares leave the float32 range (at 1e-9, NaN gradients). Dividing V by a power of two near its
        # extent is exact, so the loss is computed at unit scale and brought back, with identical values.
        s = _pow2_extent(V)
        V = V / s
        terms = face_terms(corners(V, F), eps)  # shared by L and M
        LV = cot_laplacian_from_cot(V, F, terms.cot)
        M = massmatrix_from_terms(F, V.shape[-2], terms)
        interior = ~topo.boundary_vertex
        total = (M * interior).sum(-1, keepdim=True)
        mean_mass = M.sum(-1, keepdim=True) / M.shape[-1]
        # A mesh of zero area has no mass to weigh bending by: a floor of 1 keeps the quotients (and their
        # gradients) finite there, and the loss is 0 anyway, since no interior vertex has mass.
        floor = torch.where(mean_mass > 0, resolve_eps(eps, V.dtype) * mean_mass, torch.ones_like(mean_mass))
        floor = floor.clamp_min(torch.finfo(V.dtype).tiny)
        # where, not a product with the mask: a huge term at a boundary vertex times 0 would be NaN
        e = torch.where(interior, (LV * LV).sum(-1) / torch.maximum(M, floor), 0.0).sum(-1, keepdim=True)
        some = total > 0  # no interior mass (all boundary, or zero area): the loss is 0, with zero gradient
        loss = torch.where(some, e / torch.where(some, total, torch.ones_like(total)), 0.0).squeeze(-1)
        return loss / s.reshape(loss.shape) ** 2
    raise ValueError(f"method must be 'uniform' or 'cotangent', got {method!r}")


def edge_loss(V, F) -> torch.Tensor:
    """Edge-length uniformity: ``mean_e (|e| - mean |e|)^2`` over unique edges. Returns () or (B,)."""
    V, F = check_mesh(V, F, batched=None)
    E = mesh_topology(F, V.shape[-2]).edges
    if E.shape[0] == 0:
        return V.sum((-1, -2)) * 0.0
    fast = _compiled(V, F, ["edge"])
    if fast is not None:
        return fast[0]
    ln = safe_norm(gather(V, E[:, 1]) - gather(V, E[:, 0]))  # (..., E)
    return ((ln - ln.mean(-1, keepdim=True)) ** 2).mean(-1)


def area_loss(V, F) -> torch.Tensor:
    """Triangle-area uniformity: ``mean_t (A_t - mean A)^2``. Returns () or (B,)."""
    V, F = check_mesh(V, F, batched=None)
    fast = _compiled(V, F, ["area"])
    if fast is not None:
        return fast[0]
    # at unit scale and back (exact, as the cotangent Laplacian): the squared cross products of a mesh 1e-155
    # across underflowed, and its gradient was NaN
    s = _pow2_extent(V)
    A = 0.5 * doublearea_from_corners(corners(V / s, F))
    loss = ((A - A.mean(-1, keepdim=True)) ** 2).mean(-1)
    return loss * s.reshape(loss.shape) ** 4


def arap_direction_loss(V, V0, F, *, eps: float | None = EPS) -> torch.Tensor:
    """Direction-preserving ARAP term of the paper: ``mean_e |e - (e . d_e) d_e|^2``.

    ``d_e`` is the unit rest direction of edge ``e`` in ``V0``. It is zero under translation and uniform
    scaling of the rest pose, and positive under rotation. A rest edge shorter than ``eps`` times the mean
    rest edge length has no direction: ``d_e = 0`` there, so the term becomes ``|e|^2`` and keeps it short.

    Returns () or (B,).
    """
    V, V0, F = _check_rest(V, V0, F)
    E = mesh_topology(F, V.shape[-2]).edges
    if E.shape[0] == 0:
        return V.sum((-1, -2)) * 0.0
    e = gather(V, E[:, 1]) - gather(V, E[:, 0])
    e0 = gather(V0, E[:, 1]) - gather(V0, E[:, 0])
    l0 = safe_norm(e0)
    short = l0 <= resolve_eps(eps, V.dtype) * l0.mean(-1, keepdim=True)
    d = torch.where(short.unsqueeze(-1), torch.zeros_like(e0), e0 / l0.clamp_min(torch.finfo(V.dtype).tiny).unsqueeze(-1))
    r = e - (e * d).sum(-1, keepdim=True) * d
    return (r * r).sum(-1).mean(-1)


def _spokes(V, V0, F, C0):
    """The directed spokes ``i -> j`` of every face corner pair, with their rest cotangent weights.

    Returns ``i`` (6m,), ``w`` (..., 6m) (each pair weighs ``0.5 cot`` of the corner opposite it, so a
    spoke's two faces add up to the ``igl.cotmatrix`` entry) and the rest and current spoke vectors
    ``e0``, ``e`` (..., 6m, 3).
    """
    i = F[:, [1, 2, 0, 2, 0, 1]].reshape(-1)  # (6m,)
    j = F[:, [2, 0, 1, 1, 2, 0]].reshape(-1)
    k = torch.arange(3, device=F.device).repeat(2)  # which corner's cotangent weighs the pair
    w = 0.5 * C0[..., :, k].reshape(*C0.shape[:-2], -1)  # (..., 6m)
    e0 = gather(V0, j) - gather(V0, i)
    e = gather(V, j) - gather(V, i)
    return i, w, e0, e


def best_fit_rotations(V, V0, F, *, eps: float | None = EPS) -> torch.Tensor:
    """Per-vertex rotations ``R_i`` minimising the ARAP spokes energy for fixed ``V`` (local step).

    ``R_i = argmin_R sum_j w_ij |e'_ij - R e_ij|^2`` from the SVD of ``S_i = sum_j w_ij e_ij e'_ij^T``,
    with the reflection case fixed by flipping the axis of the smallest singular value. Computed without
    gradient. Returns ``(..., n, 3, 3)``.
    """
    V, V0, F = _check_rest(V, V0, F)
    with torch.no_grad():
        return _rotations(V.detach(), V0, F, face_terms(corners(V0, F), eps).cot)


def _rotations(V, V0, F, C0):
    i, w, e0, e = _spokes(V, V0, F, C0)
    if e0.ndim < e.ndim:
        e0 = e0.expand_as(e)
        w = w.expand(e.shape[:-1])
    S = (w[..., None, None] * e0.unsqueeze(-1) * e.unsqueeze(-2))  # (..., 6m, 3, 3)
    S = index_add(torch.zeros(*e.shape[:-2], V.shape[-2], 3, 3, dtype=V.dtype, device=V.device), -3, i, S)
    # torch's SVD and determinant take float32 and float64 only: a half-precision mesh fits its rotations in
    # float32 (they are then rounded to its dtype)
    wide = S.dtype in (torch.float16, torch.bfloat16)
    U, _, Vh = torch.linalg.svd(S.float() if wide else S)
    R = Vh.transpose(-1, -2) @ U.transpose(-1, -2)
    flip = torch.linalg.det(R) < 0
    if bool(flip.any()):
        D = torch.ones(*R.shape[:-1], dtype=R.dtype, device=V.device)
        D[..., 2] = torch.where(flip, -1.0, 1.0).to(R.dtype)
        R = (Vh.transpose(-1, -2) * D.unsqueeze(-2)) @ U.transpose(-1, -2)
    return R.to(V.dtype) if wide else R


def arap_loss(V, V0, F, *, eps: float | None = EPS) -> torch.Tensor:
    """As-rigid-as-possible energy of Sorkine & Alexa (2007), spokes form, cotangent weights.

    ``E = sum_i sum_{j in N(i)} w_ij |(v_j - v_i) - R_i (v0_j - v0_i)|^2`` where ``w_ij`` are the
    entries of ``igl.cotmatrix(V0, F)`` (``0.5 (cot a_ij + cot b_ij)``, each undirected edge visited
    from both ends) and ``R_i`` the best-fit rotations (:func:`best_fit_rotations`). The rotations are
    treated as constants in the gradient: they minimise ``E`` for the current ``V``, so this is the exact
    gradient of the energy after the local step. Zero for any rigid motion of ``V0``; units of length^2.

    Returns () or (B,).
    """
    V, V0, F = _check_rest(V, V0, F)
    C0 = face_terms(corners(V0, F), eps).cot
    with torch.no_grad():
        R = _rotations(V.detach(), V0.detach(), F, C0.detach())
    i, w, e0, e = _spokes(V, V0, F, C0)
    r = e - (gather(R, i, dim=-3) @ e0.unsqueeze(-1)).squeeze(-1)
    return (w * (r * r).sum(-1)).sum(-1)


# name -> loss(V, V0, F); the paper's four first, then the two variants beyond it
def albedo_roughness(a, F) -> torch.Tensor:
    """Roughness of a per-vertex scalar field ``a`` (n,) or (B, n) such as an albedo: ``mean_i (a_i - mean of a
    over i's 1-ring)^2`` over vertices with neighbours. Returns () or (B,)."""
    _check_field("a", a, 1, "(n,) or (B, n)")
    F = as_faces(F)  # float faces were truncated to indices
    if int(F.max()) >= a.shape[-1]:
        raise MeshError(f"F holds vertex index {int(F.max())}, but a has values for {a.shape[-1]} vertices")
    topo = mesh_topology(F.to(a.device), a.shape[-1])
    d = uniform_laplacian_from_topology(a.unsqueeze(-1), topo).squeeze(-1)
    live = topo.degree > 0
    return ((d * d) * live).sum(-1) / live.sum().clamp_min(1)


def texture_roughness(T) -> torch.Tensor:
    """:func:`albedo_roughness` of a texture ``(H, W)`` or ``(B, H, W)`` over its grid: ``mean (t - mean of
    the 4 neighbours)^2`` over interior texels. Returns () or (B,)."""
    _check_field("T", T, 2, "(H, W) or (B, H, W)")  # an RGB (H, W, 3) would be read as a batch of H
    if min(T.shape[-2:]) < 3:
        raise ValueError(f"T must be at least 3 x 3 texels to have an interior, got {tuple(T.shape[-2:])}")
    d = T[..., 1:-1, 1:-1] - 0.25 * (T[..., :-2, 1:-1] + T[..., 2:, 1:-1] + T[..., 1:-1, :-2] + T[..., 1:-1, 2:])
    return (d * d).mean((-1, -2))


def _check_field(name: str, x, dims: int, shapes: str) -> None:
    """ValueError unless ``x`` is a real float tensor of ``dims`` or ``dims + 1`` (batched) dimensions."""
    if not isinstance(x, torch.Tensor) or not x.is_floating_point():
        got = f"dtype {x.dtype}" if isinstance(x, torch.Tensor) else f"a {type(x).__name__}"
        raise ValueError(f"{name} must be a float torch tensor, got {got}")
    if x.ndim not in (dims, dims + 1) or x.numel() == 0:
        raise ValueError(f"{name} must have shape {shapes}, got {tuple(x.shape)}")


REGULARIZERS = {
    "laplacian": lambda V, V0, F: laplacian_loss(V, F),
    "edge": lambda V, V0, F: edge_loss(V, F),
    "area": lambda V, V0, F: area_loss(V, F),
    "arap": lambda V, V0, F: arap_direction_loss(V, V0, F),
    "laplacian_cot": lambda V, V0, F: laplacian_loss(V, F, method="cotangent"),
    "arap_sorkine": lambda V, V0, F: arap_loss(V, V0, F),
}

# name in REGULARIZERS -> its label in tables, in the order tables list them
REGULARIZER_LABELS = {
    "laplacian": "laplacian (uniform)",
    "laplacian_cot": "laplacian (cotangent)",
    "edge": "edge",
    "area": "area",
    "arap": "arap (direction)",
    "arap_sorkine": "arap (Sorkine-Alexa)",
}

# name in REGULARIZERS -> p such that the loss of a given smooth shape falls like n^-p on an even mesh of n
# vertices (edge length h ~ n^-1/2): squared umbrella vectors and squared area deviations ~ h^4 (p = 2),
# squared edge-length deviations and squared orthogonal edge components ~ h^2 (p = 1). The two variants
# are not scaled (p = 0): the cotangent loss is weighted by Voronoi mass and the Sorkine-Alexa energy sums
# over every edge, so neither has the simple power law of the paper's four.
RESOLUTION_POWERS = {"laplacian": 2, "edge": 1, "area": 2, "arap": 1, "laplacian_cot": 0, "arap_sorkine": 0}


def scale_weights(weights: dict, n_vertices: int, ref_vertices: int | None) -> dict:
    """Weights stated for a mesh of ``ref_vertices`` vertices, moved to ``n_vertices``: each multiplied by
    ``(n_vertices / ref_vertices) ** RESOLUTION_POWERS[name]``, so that the same settings ask for the same
    smoothness at every resolution. ``ref_vertices=None`` returns the weights unchanged."""
    if ref_vertices is None:
        return dict(weights)
    for name, count in (("n_vertices", n_vertices), ("ref_vertices", ref_vertices)):
        if isinstance(count, bool) or not isinstance(count, numbers.Integral) or count < 1:
            raise ValueError(f"{name} must be a positive integer, got {count!r}")
    unknown = sorted(set(weights) - set(RESOLUTION_POWERS))
    if unknown:
        raise ValueError(f"unknown regularizers {unknown}; known: {', '.join(RESOLUTION_POWERS)}")
    ratio = n_vertices / ref_vertices
    return {k: w * ratio ** RESOLUTION_POWERS[k] for k, w in weights.items()}
