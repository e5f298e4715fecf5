"""Valid steps: the rules a mesh must meet before an optimisation step that produced it is accepted.

A mesh is valid when it has no self-intersecting face pair that the last accepted mesh (at first, the start)
did not have (exact predicates, :func:`~meshmei.quality.self_intersecting_pairs`): from a clean start, none
at all; from a start that intersects itself, its pairs may go but no new one may come. No face is turned by more than
``max_turn_degrees`` against its reference orientation (the rest mesh, or the last accepted mesh), and no
triangle whose quality fell below a bound. :class:`StepGuard` holds the reference and the counts;
:func:`meshmei.optim.minimize` calls its :meth:`StepGuard.accept` after every step and halves the step
until it passes (or rejects the step).

What is guaranteed is discrete: every accepted iterate meets the rules. Between two accepted iterates a
face is not tracked; a step that carries a face through another and out of it again in one move would not
be seen. Steps are short against the features they could cross (a step moves a vertex by about the
learning rate, 1e-3 to 5e-2 of the unit-diagonal object, against edge lengths of 1e-2 and more), and the
turn bound rejects the inverted faces such a pass would leave behind.
"""

from __future__ import annotations

import math
import numbers
import time
from dataclasses import dataclass

import numpy as np
import torch

from . import native
from ._checks import all_finite, check_positive
from .certify import GraphCertificate, SeparationCertificate, StarCertificate
from .contact import log_barrier
from .errors import MeshError
from .mesh import array_as_tensor, check_mesh
from .operators import corners, cross_from_corners, resolve_eps, safe_norm, sq_edge_sum_from_corners, sum_xyz
from .quality import count_self_intersections, self_intersecting_pairs

__all__ = ["ValidityRules", "StepGuard", "face_frame", "SLIVER_QUALITY"]

SLIVER_QUALITY = 1e-4
"""Triangle quality below which a face's orientation is left to rounding: the turn rule leaves such faces
of the reference out (the quality floor still holds them; see :meth:`StepGuard._oriented`)."""


def face_frame(V: torch.Tensor, F: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Unit face normals ``(..., m, 3)`` and triangle qualities ``(..., m)`` from one pass over the corners
    (``V`` may hold a batch of meshes, ``(..., n, 3)``).

    The normals are those of :func:`~meshmei.operators.face_normals` (zero for a collapsed face), the
    qualities those of :func:`~meshmei.quality.triangle_quality`; ``V`` and ``F`` are not checked. The guard
    and its barrier need both every step, so they share the corners and cross products.
    """
    T = corners(V, F)  # (m, 3, 3)
    c = cross_from_corners(T)  # (m, 3), twice the area long
    l2 = sq_edge_sum_from_corners(T)
    dbl = safe_norm(c)
    den = torch.maximum(dbl, resolve_eps(None, V.dtype) * l2)
    ok = den > 0
    n = torch.where(ok[..., None], c / torch.where(ok, den, torch.ones_like(den))[..., None], torch.zeros_like(c))
    return n, 2.0 * math.sqrt(3.0) * dbl / l2.clamp_min(torch.finfo(dbl.dtype).tiny)


_FRAME_RULE: list = []  # [fused]: the probe's answer, once per process


def _frame_rule() -> int | None:
    """How the compiled frame must form cross products to equal :func:`face_frame` bit for bit here: 1 where
    torch's float64 cross product kernel fuses its first product into the subtraction (it does where it was
    built with fused multiply-add), 0 where it does not; None where neither reproduces the torch code (the
    torch code then runs). Probed once, on a random mesh of 64 vertices and 512 faces."""
    if not _FRAME_RULE:
        g = torch.Generator().manual_seed(0)
        V = torch.randn(64, 3, dtype=torch.float64, generator=g, device="cpu")
        F = torch.randint(0, 64, (512, 3), generator=g, device="cpu")
        n, q = face_frame(V, F)
        rule = None
        for fused in (1, 0):
            got = _kernel_frame(V, F, fused, None, 0.0, None)
            if got is not None and torch.equal(got[0], n) and torch.equal(got[1], q):
                rule = fused
                break
        _FRAME_RULE.append(rule)
    return _FRAME_RULE[0]


def _kernel_frame(Vd, F, fused, normals, cos_limit, turn_faces):
    """:func:`_compiled_frame` with the cross product rule ``fused``."""
    lib = native.library()
    Vd, F = Vd.contiguous(), F.contiguous()
    m = F.shape[0]
    f64 = dict(dtype=torch.float64, device="cpu")
    C, S, L2 = torch.empty(m, 3, **f64), torch.empty(m, **f64), torch.empty(m, **f64)
    rc = lib.guard_frame_parts(Vd.shape[0], m, Vd.data_ptr(), F.data_ptr(), fused, C.data_ptr(), S.data_ptr(),
                               L2.data_ptr())
    if rc:
        return "non-finite" if rc < 0 else None
    S.sqrt_()  # torch's square root: the torch code's rounding
    N, Q, stats = torch.empty(m, 3, **f64), torch.empty(m, **f64), torch.empty(2, **f64)
    R = None if normals is None else normals.to(torch.float64).contiguous()
    T = None if turn_faces is None else turn_faces.contiguous()
    lib.guard_frame_finish(m, C.data_ptr(), S.data_ptr(), L2.data_ptr(), resolve_eps(None, torch.float64),
                           2.0 * math.sqrt(3.0), None if R is None else R.data_ptr(), cos_limit,
                           None if T is None else T.data_ptr(), N.data_ptr(), Q.data_ptr(), stats.data_ptr())
    q, turned = stats.tolist()
    return N, Q, q, int(turned)


def _compiled_frame(Vd: torch.Tensor, F: torch.Tensor, normals, cos_limit: float, turn_faces):
    """The guard's check of float64 ``Vd`` by the compiled kernels (``meshmei/_guard.c``): ``(normals,
    qualities, smallest quality, turned faces)``, the first two :func:`face_frame`'s bit for bit (the probe
    :func:`_frame_rule` makes sure), the last the number of faces whose normal's cosine to its reference in
    ``normals`` lies below ``cos_limit``, both non-zero and the face in ``turn_faces`` (None: every face;
    ``normals`` None: no turn rule, 0). ``"non-finite"`` where a coordinate of ``Vd`` is not finite; None
    where the kernels do not apply (not built, within :func:`~meshmei.native.torch_reference`, not CPU
    float64, a squared cross product out of float64's normal range): the torch code runs instead. One pass
    in C, torch's square root, one more pass: the guard's check of a 3D-MEI step from the sheet (740 faces,
    with the graph certificate) 0.57-0.62 ms instead of 1.3-1.5 (wrapped timers)."""
    if not (native.available(Vd) and Vd.dtype == torch.float64 and F.device.type == "cpu"):
        return None
    fused = _frame_rule()
    return None if fused is None else _kernel_frame(Vd, F, fused, normals, cos_limit, turn_faces)


def _compiled_barrier(guard, V: torch.Tensor, q_band: float, band: float):
    """:meth:`StepGuard.barrier` of ``V`` ((n, 3) or (B, n, 3)) by ``_guard.c``'s ``guard_barrier`` (``band``
    0: no turn energy): the energy in float64 with its gradient from the same pass, which the backward only
    scales (:func:`~meshmei.native.with_gradient`); or None where the kernel does not apply (not built,
    within :func:`~meshmei.native.torch_reference`, not a CPU float tensor) or leaves the energy to the torch
    code (a non-finite coordinate, a face in a band whose squared cross product leaves float64's normal
    range)."""
    if not native.available(V):
        return None
    Xd, energy, grad = native.kernel_buffers(V)  # (B, n, 3): one mesh as a batch of one
    B, n = Xd.shape[:2]
    turn = band > 0.0
    F = guard.F.contiguous()  # int64 (check_mesh)
    R = guard.normals.to(torch.float64).contiguous() if turn else None
    T = guard.turn_faces if turn else None
    T = None if T is None else np.ascontiguousarray(T.numpy(), dtype=np.uint8)
    rc = native.library().guard_barrier(
        B, n, F.shape[0], Xd.ctypes.data, F.data_ptr(), None if R is None else R.data_ptr(),
        None if T is None else T.ctypes.data, guard.quality_floor, q_band, guard.cos_bound, band,
        resolve_eps(None, V.dtype), 2.0 * math.sqrt(3.0), float(torch.finfo(V.dtype).tiny), energy.ctypes.data,
        None if grad is None else grad.ctypes.data)
    if rc != 0:
        return None
    return native.with_gradient(V, energy, grad)


@dataclass(frozen=True)
class ValidityRules:
    """What an accepted mesh must meet.

    Attributes
    ----------
    self_intersections : bool
        No intersecting face pair that the last accepted mesh (at first the start) did not have: none from
        a clean start (every built-in one).
    max_turn_degrees : float
        Largest angle by which a face's normal may turn from its reference (in ``(0, 180]``; 180 turns the
        check off). 90 rejects every inverted (flipped) face.
    turn_from : {"rest", "step"}
        The reference: the rest mesh (no face may ever be flipped against its start, as a 3D-MEI's sheet
        or sphere) or the last accepted mesh (no face may turn over in one step; a reconstruction's faces
        may turn far from the sphere they started on, but only smoothly).
    min_quality : float
        Smallest triangle quality (``4 sqrt(3) A / sum l^2``, 1 for equilateral) an accepted mesh may have;
        a start that already has worse triangles lowers the bound to half its own minimum.
    max_halvings : int
        How often a rejected step is halved before it is given up (the parameters then stay where they
        were for this step).
    max_step : float or None
        Farthest any vertex may move from the last accepted mesh in one step (None: no bound). Refusing a
        long step by this rule costs no intersection test; the guarantee rests on that test, not on this
        bound. Reconstruction passes one mean edge, four contact-barrier reaches
        (:data:`meshmei.reconstruct.fit.MAX_STEP_REACHES`): a diverging learning rate is refused cheaply,
        and a step may still close a gap wider than the barrier's reach, which the exact test then checks.
    """

    self_intersections: bool = True
    max_turn_degrees: float = 90.0
    turn_from: str = "rest"
    min_quality: float = 0.02
    max_halvings: int = 6
    max_step: float | None = None

    def __post_init__(self):
        for name in ("max_turn_degrees", "min_quality"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, numbers.Real):
                raise ValueError(f"{name} must be a number, got {value!r}")
        if not 0 < self.max_turn_degrees <= 180:
            raise ValueError(f"max_turn_degrees must lie in (0, 180], got {self.max_turn_degrees!r}")
        if self.turn_from not in ("rest", "step"):
            raise ValueError(f"turn_from must be 'rest' or 'step', got {self.turn_from!r}")
        if not 0 <= self.min_quality < 1:
            raise ValueError(f"min_quality must lie in [0, 1), got {self.min_quality!r}")
        if (isinstance(self.max_halvings, bool) or not isinstance(self.max_halvings, numbers.Integral)
                or self.max_halvings < 0):
            raise ValueError(f"max_halvings must be a non-negative integer, got {self.max_halvings!r}")
        if self.max_step is not None:
            check_positive("max_step", self.max_step)


def _as_tensor(V) -> torch.Tensor:
    """Candidate vertices as a tensor: a NumPy array is taken as it is (it ended in an AttributeError)."""
    if not isinstance(V, (torch.Tensor, np.ndarray)):
        raise MeshError(f"candidate vertices must be a tensor or a NumPy array, got {type(V).__name__}")
    return array_as_tensor(V, "V")


class StepGuard:
    """Checks candidate meshes against :class:`ValidityRules`, from a valid start.

    Parameters
    ----------
    V0 : (n, 3) float tensor
        The start (and, with ``turn_from="rest"``, the reference orientation).
    F : (m, 3) int64 tensor
    rules : ValidityRules

    Attributes
    ----------
    allowed_pairs : int
        Intersecting pairs of the start.
    allowed : set of (int, int)
        The intersecting face pairs of the last accepted mesh (at first, the start's): a candidate may have
        these and no other (empty for a clean start).
    quality_floor : float
        The triangle-quality bound in force.
    checks, failures : int
        Candidates checked, and those that failed.
    reasons : dict of str -> int
        Failures by the rule they broke (``"step"``, ``"quality"``, ``"turn"``, ``"intersection"``,
        ``"non-finite"``).
    seconds : float
        Time spent checking.
    certificate : GraphCertificate, StarCertificate or None
        For a start that is a disc facing one way (the 3D-MEI's sheet) or closed and star-shaped about its
        centroid (its sphere), with no intersecting pair allowed: a candidate it proves to be a graph over a
        plane, or star-shaped, skips libigl's exact test, which it would pass (:mod:`meshmei.certify`); one
        it does not prove goes to the exact test.
    certified : int
        Candidates that passed the intersection rule by the certificate alone.
    separation : SeparationCertificate or None
        With :meth:`use_contact`: clears candidates of a clean start from the contact barrier's distances at
        the last accepted mesh and the step's length (:mod:`meshmei.certify`), leaving libigl the faces it
        cannot clear.
    separated : int
        Candidates that passed the intersection rule by the separation certificate (with libigl on at most
        the faces it could not clear).
    """

    def __init__(self, V0: torch.Tensor, F: torch.Tensor, rules: ValidityRules = ValidityRules()):
        V0, F = check_mesh(V0, F)
        V0, F = V0.detach().cpu(), F.cpu()  # the checks run on the CPU, whatever the run's device
        self.F, self.rules, self.n_vertices = F, rules, V0.shape[0]
        ref = V0.detach().double()
        self.normals, q = face_frame(ref, F)  # (m, 3) reference orientation
        # slivers of a user's start (quality below SLIVER_QUALITY) have a normal set by rounding, which flips
        # under any move: the turn rule leaves them out (the quality floor still holds them); None when every
        # face counts, as in every built-in start
        self.turn_faces = self._oriented(q)
        self.cos_bound = math.cos(math.radians(rules.max_turn_degrees))
        start_pairs = self_intersecting_pairs(ref, F) if rules.self_intersections else np.zeros((0, 2), np.int64)
        self.allowed = set(map(tuple, start_pairs.tolist()))
        self.allowed_pairs = len(self.allowed)
        self._candidate_pairs = None  # the pairs of the candidate just checked (a dirty start's)
        self.quality_floor = min(rules.min_quality, 0.5 * float(q.min()))
        # a disc start facing one way (the 3D-MEI's sheet) or a closed star-shaped one (its sphere): most
        # candidates are proven clean without libigl
        self.certificate = None
        if rules.self_intersections and self.allowed_pairs == 0:
            self.certificate = (GraphCertificate.for_start(ref, F, self.normals)
                                or StarCertificate.for_start(ref, F, self.normals))
        self.certified = 0
        self.separation, self._contact, self.separated = None, None, 0
        self.checks, self.failures, self.seconds = 0, 0, 0.0
        self.reasons = {"non-finite": 0, "step": 0, "quality": 0, "turn": 0, "intersection": 0}
        self.accepted = ref  # the last accepted vertices (float64): for max_step and the separation certificate
        # the float64 face frame of the last accepted candidate: the next objective's barrier screens its faces
        # with it (the same vertices) instead of computing the frame again
        self._accepted_frame = None

    def _oriented(self, quality: torch.Tensor):
        """The faces whose orientation the turn rule trusts, ``(m,)`` bool, or None for all: every face of
        quality at least :data:`SLIVER_QUALITY` (or ``min_quality``, if lower). Below it the corners' float32
        rounding (a relative 6e-8) can tilt the normal by about ``6e-8 / q`` radians and more, and a face made
        of an edge and its rounded midpoint turns over under any move; above it the normal is sound, and a
        thin face turning over is a real flip."""
        ok = quality >= min(self.rules.min_quality, SLIVER_QUALITY)
        return None if bool(ok.all()) else ok

    def _verdict(self, V: torch.Tensor, frame=None) -> tuple:
        """``(rule, message, frame)``: the rule ``V`` breaks (a key of :attr:`reasons`, None when it meets
        them all), what is wrong, and ``V``'s float64 :func:`face_frame` ``(normals, quality)`` when it was
        computed (cheapest checks first; always when ``V`` meets the rules).
        ``frame``: :func:`face_frame` of ``V`` in float64, when already computed (a batch's, at once)."""
        if V.ndim != 2 or V.shape[1] != 3 or V.shape[0] != self.n_vertices:
            raise MeshError(f"candidate vertices must have the start's shape ({self.n_vertices}, 3), got "
                            f"{tuple(V.shape)}")
        Vd = V.detach().to("cpu", torch.float64)
        turn = self.rules.max_turn_degrees < 180
        # the frame, the smallest quality and the turned faces in one compiled pass where it applies
        checked = None if frame is not None else _compiled_frame(
            Vd, self.F, self.normals if turn else None, self.cos_bound - 1e-12, self.turn_faces)
        if checked == "non-finite" or (checked is None and not all_finite(Vd)):
            return "non-finite", "non-finite vertices", None
        if self.rules.max_step is not None:
            moved = float((Vd - self.accepted).norm(dim=1).max())
            if moved > self.rules.max_step:
                return "step", f"a vertex moved {moved:.3g}, more than {self.rules.max_step:.3g}, in one step", None
        if checked is not None:
            n, quality, q, n_turned = checked
            frame = (n, quality)
        else:
            frame = face_frame(Vd, self.F) if frame is None else frame
            n, quality = frame
            q, n_turned = float(quality.min()), 0
            if turn:
                turned = sum_xyz(n * self.normals) < self.cos_bound - 1e-12
                # a zero-area face has no direction
                turned &= (sum_xyz(n.abs()) > 0) & (sum_xyz(self.normals.abs()) > 0)
                if self.turn_faces is not None:
                    turned &= self.turn_faces
                n_turned = int(turned.sum())
        if q < self.quality_floor:
            return "quality", f"triangle quality {q:.3g} below {self.quality_floor:.3g}", frame
        if n_turned:
            why = f"{n_turned} faces turned by more than {self.rules.max_turn_degrees:g} degrees"
            return "turn", why, frame
        if self.rules.self_intersections:
            if self.certificate is not None and self.certificate.holds(Vd, n):
                self.certified += 1  # proven a graph over a plane, or star-shaped: no pair can intersect
                return None, None, frame
            if not self.allowed:  # a clean start (every built-in one): any pair is new
                cleared = self._separated(Vd)
                if cleared is not None:
                    found, listed = cleared
                    if not found:
                        self.separated += 1  # the contact barrier's distances and the step's length cleared it
                        return None, None, frame
                    # libigl found pairs among the faces it could not clear: no need to count them all
                    return ("intersection", f"{found} self-intersecting face pairs among the {listed} faces the "
                            "separation certificate could not clear (start: 0)", frame)
                pairs = count_self_intersections(Vd, self.F)
                if pairs > 0:
                    return "intersection", f"{pairs} self-intersecting face pairs (start: 0)", frame
            else:
                found = set(map(tuple, self_intersecting_pairs(Vd, self.F).tolist()))
                new = found - self.allowed
                if new:
                    return ("intersection", f"{len(new)} new self-intersecting face pairs ({len(found)} in all; "
                            f"the last accepted mesh: {len(self.allowed)})", frame)
                self._candidate_pairs = found
        return None, None, frame

    def use_contact(self, barrier) -> None:
        """Let the contact ``barrier`` (a :class:`~meshmei.contact.ContactBarrier` with edge pairs, evaluated at
        each accepted mesh by the objective) clear candidates of the intersection test:
        :class:`~meshmei.certify.SeparationCertificate` proves most steps of a clean start clean from its
        distances and the step's length, and hands libigl only the faces it cannot clear. The verdicts are
        the exact test's (a candidate it cannot prove goes to libigl whole). None turns it off."""
        self._contact = barrier
        self.separation = None
        if barrier is not None and self.rules.self_intersections:
            self.separation = SeparationCertificate.for_mesh(self.F, self.n_vertices)

    def _separated(self, Vd: torch.Tensor) -> tuple[int, int] | None:
        """What the separation certificate, with libigl on the faces it could not clear, says of ``Vd``:
        ``(pairs, listed)``, the intersecting pairs libigl found among the ``listed`` faces it could not clear
        (0: ``Vd`` is proven clean; more: it is refused without a test of the whole mesh), or None when it
        proves nothing (the whole mesh goes to the exact test)."""
        if self.separation is None:
            return None
        handed_out = self._contact.separation(self.accepted)
        if handed_out is None:
            return None
        faces = self.separation.suspects(Vd, self.accepted, handed_out)
        if faces is None:
            return None
        return (count_self_intersections(Vd, self.F[torch.from_numpy(faces)]) if len(faces) else 0), len(faces)

    def why_not(self, V: torch.Tensor) -> str | None:
        """None when ``V`` meets the rules, else which rule it breaks (cheapest checks first). A question, not a
        check: it counts in neither :attr:`checks` nor :attr:`certified`."""
        certified, separated = self.certified, self.separated
        why = self._verdict(_as_tensor(V))[1]
        self.certified, self.separated = certified, separated
        return why

    def accept(self, V: torch.Tensor, frame=None) -> bool:
        """Whether ``V`` meets the rules; an accepted ``V`` becomes the reference under ``turn_from="step"``.
        ``frame``: :func:`face_frame` of ``V`` in float64, when already computed."""
        t0 = time.perf_counter()
        V = _as_tensor(V)
        self._candidate_pairs = None
        rule, _, frame = self._verdict(V, frame)
        self.checks += 1
        self._accepted_frame = None
        if rule is not None:
            self.failures += 1
            self.reasons[rule] += 1
        else:
            Vd = V.detach().to("cpu", torch.float64)
            self._accepted_frame = (Vd, *frame)
            self.accepted = Vd
            if self._candidate_pairs is not None:  # pairs that went away may not come back
                self.allowed = self._candidate_pairs
            if self.rules.turn_from == "step":
                # the reference normals follow the accepted mesh; the faces the rule trusts stay the start's:
                # a sound face squeezed into the sliver band (allowed where the start's own sliver lowered
                # the quality floor) and left out from then on turned over in the next step (review)
                self.normals = frame[0]
        self.seconds += time.perf_counter() - t0
        return rule is None

    def report(self) -> dict:
        """What the guard did, JSON-able: candidates checked, refused, refusals by rule, seconds, and how
        many passed the intersection rule by their :mod:`~meshmei.certify` certificate alone."""
        return {"checks": self.checks, "refused": self.failures, "reasons": dict(self.reasons),
                "seconds": round(self.seconds, 4), "certified": self.certified, "separated": self.separated}

    def barrier(self, V: torch.Tensor, *, turn_band_degrees: float = 20.0, quality_band: float = 2.0) -> torch.Tensor:
        """A smooth energy that keeps iterates away from the turn and quality bounds (a scalar with a graph
        to ``V``).

        ``sum_f b(cos t_f - cos T, cos(T - band) - cos T) + sum_f b(q_f - q_min, quality_band * q_min)`` with
        :func:`~meshmei.contact.log_barrier` ``b``: ``t_f`` is face ``f``'s turn from its reference, ``T``
        the rules' ``max_turn_degrees``, ``q_f`` its quality and ``q_min`` :attr:`quality_floor`. A face
        more than ``turn_band_degrees`` inside the turn bound, and a triangle of quality above
        ``(1 + quality_band) q_min``, add nothing; the energy grows without bound at the bounds. Added to an
        objective with a small weight, it turns the run before a step reaches a bound, where the guard would
        refuse it: with a quadratic margin penalty instead, a 3D-MEI run from the sheet had four steps in
        five refused and stalled (docs/benchmarks.md, *Valid steps*). The sum runs over faces, so a single
        face at its bound is felt whatever the mesh size. A batch ``V (B, n, 3)`` (meshes of this guard's
        start) gives the ``(B,)`` energies.

        On CPU, where the kernels are built, one pass of ``_guard.c`` over every face gives the energy in
        float64 and its gradient (:func:`_compiled_barrier`; equal to the torch code to rounding, tested):
        forward and backward of a crumpled 740-face sheet in float32 0.34 ms against the torch code's 1.8 ms.
        Elsewhere the torch code screens the faces without a graph and builds one over those inside a band.
        """
        if V.ndim not in (2, 3) or V.shape[-2:] != (self.n_vertices, 3):
            raise MeshError(f"the barrier's vertices must have shape ({self.n_vertices}, 3) or (B, "
                            f"{self.n_vertices}, 3), got {tuple(V.shape)}")
        if V.device.type != "cpu":  # a CUDA run's: on a copy on the CPU, with the guard's reference there
            return self.barrier(V.cpu(), turn_band_degrees=turn_band_degrees, quality_band=quality_band).to(V.device)
        q_band = quality_band * self.quality_floor
        turn = self.rules.max_turn_degrees < 180
        if turn:
            T = math.radians(self.rules.max_turn_degrees)
            band = math.cos(max(T - math.radians(turn_band_degrees), 0.0)) - self.cos_bound
        compiled = _compiled_barrier(self, V, q_band, band if turn else 0.0)
        if compiled is not None:
            return compiled
        # Most faces of most iterates lie outside both bands, where the energy is exactly zero with zero
        # slope: find the faces inside (the same comparisons as log_barrier's) without a graph, then build
        # the graph over those alone (a batch: faces inside for some item).
        with torch.no_grad():
            known = self._accepted_frame
            if V.ndim == 2 and known is not None and torch.equal(known[0], V.detach().double()):
                # the accepted candidate's float64 frame, with a margin over float32's rounding: a face it adds
                # lies outside both bands, where the energy below is exactly zero
                _, n, q = known
                tol = 1e-5
            else:
                (n, q), tol = face_frame(V.detach(), self.F), 0.0
            inside = q - self.quality_floor < q_band + tol
            if turn:
                near = sum_xyz(n * self.normals.to(n.dtype)) - self.cos_bound < band + tol
                inside |= near if self.turn_faces is None else near & self.turn_faces
            faces = inside.reshape(-1, self.F.shape[0]).any(0).nonzero().squeeze(1)
        total = V.sum((-2, -1)) * 0.0  # zero, with a (zero) gradient, where no face is near a bound
        if not len(faces):
            return total
        n, q = face_frame(V, self.F.index_select(0, faces))
        total = total + log_barrier(q - self.quality_floor, q_band).sum(-1)
        if turn:
            cos = sum_xyz(n * self.normals.index_select(-2, faces).to(n.dtype))
            if self.turn_faces is not None:  # no turn energy on a face the rule leaves out
                cos = torch.where(self.turn_faces.index_select(0, faces), cos, torch.ones_like(cos))
            total = total + log_barrier(cos - self.cos_bound, band).sum(-1)
        return total

    def acceptor(self, vertices):
        """A callable for :func:`meshmei.optim.minimize`'s ``accept``: ``vertices()`` (no gradient), checked."""

        def accept() -> bool:
            with torch.no_grad():
                return self.accept(vertices())

        return accept
