"""Normal forces between a parcel and the cells that support it (paper Section 4.1-4.2, eqs. 3-19).

Units: m for positions, N for forces.

Model (paper 4.1.2): every support is a spring of the same stiffness and the parcel's bottom is a rigid plane, so
the normal forces are an affine function of position, ``N_i = c + a x_i + b y_i`` (eq. 7), fixed by vertical and
moment equilibrium (eqs. 3-5). The paper writes this as an (m+3) x (m+3) system with a mask matrix (eqs. 8-19); here
the same solution comes from the 3x3 moment system: with ``B_i = [1, x_i, y_i]`` and ``theta = [c, a, b]``,
equilibrium reads ``(B^T B) theta = W [1, x_c, y_c]``, so no large matrix is ever inverted: the 3x3 matrix is made
from the sums of 1, x, y, x^2, xy and y^2 over the cells in contact and inverted by cofactors (LAPACK only for
contacts close to one line).

Beyond the paper:
- Lift-off: springs cannot pull, so a cell whose linear force would be negative leaves contact. The contact set is
  the solution of the tensionless-spring problem (minimum complementary energy ``sum N_i^2`` subject to equilibrium
  and ``N >= 0``, whose optimality conditions are ``N_i = max(0, B_i theta)``), found by a damped active-set Newton
  iteration that removes and re-adds cells until every force is >= 0 and every lifted cell's spring is unloaded.
- Tipping: if the centre of mass lies outside the convex hull of the supports no non-negative forces balance the
  parcel; :class:`~virtual_vehicle.errors.TippingError` is raised (never a NaN).
- Collinear supports use the 1-D model of the authors' earlier paper (vertical force and one moment equation). On a
  layout that is itself a single row the parcel is assumed held laterally (``lateral_support=True``); elsewhere the
  centre of mass must lie on the line of supports, or the parcel tips.

The work of a planar solve (the local frame, the supports' convex hull by Andrew's monotone chain, the contact-set
iteration, the plane and force map of eq. 19) is one compiled call (numba): it is a few 3 x 3 problems, where
numpy's and Qhull's per-call costs were most of the ~260 us a solve took; it now takes ~35 us (12 cells, all in
contact), most of it the checks and the solution object around it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numba import njit

from virtual_vehicle.compiled import leaf
from virtual_vehicle.errors import IntegrationError, TippingError
from virtual_vehicle.model.layout import COLLINEAR_TOL, _collinear_kernel, collinear

_REL_TOL = 1e-12  # relative tolerance for geometric ties (hull boundary, zero forces)
_SLAB = 1e-9  # relative half-width of the band in which a load counts as on the line of its contacts
_MAX_ITER = 200  # contact-set iterations before giving up
_PLANE_LIN = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])  # load [W, W x_c, W y_c] = W (r_lin @ xi + r_const)
_PLANE_CONST = np.array([1.0, 0.0, 0.0])


@dataclass(frozen=True, eq=False)
class SupportSolution:
    """Normal forces for one set of supporting cells and one contact set, as an affine map of the centre of mass.

    All coordinates are local: ``xi = X_c - origin``. For every centre of mass in the region where the contact set
    stays the same, ``N(xi) = force_lin @ xi + force_const`` (eq. 19 with the mask of the contact set).

    Attributes:
        origin: (2,) local origin, m (centroid of the supporting cells).
        points: (m, 2) supporting cells in local coordinates, m.
        in_contact: (m,) bool, False for cells that have lifted off.
        basis: (m, d) rows ``[1, x_i, y_i]`` (planar, d = 3) or ``[1, s_i]`` (1-D, d = 2).
        plane_lin, plane_const: ``plane(xi) = plane_lin @ xi + plane_const`` are the spring-plane parameters;
            ``basis @ plane(xi)`` is the spring force of every cell (negative for lifted cells).
        force_lin: (m, 2); force_const: (m,): the normal-force map, zero rows for lifted cells.
        hull_normals, hull_offsets: the centre of mass is supported iff ``hull_normals @ xi <= hull_offsets``.
        one_d: True when the 1-D model was used.
        weight: N.
    """

    origin: np.ndarray
    points: np.ndarray
    in_contact: np.ndarray
    basis: np.ndarray
    plane_lin: np.ndarray
    plane_const: np.ndarray
    force_lin: np.ndarray
    force_const: np.ndarray
    hull_normals: np.ndarray
    hull_offsets: np.ndarray
    one_d: bool
    weight: float

    def at(self, origin: np.ndarray) -> "SupportSolution":
        """This solution with its local origin at ``origin`` (m): a translated copy of its pattern, sharing its
        arrays and whatever was computed from them (``dataclasses.replace`` would recompute nothing either, but
        forgets cached properties and takes four times as long)."""
        new = object.__new__(SupportSolution)
        new.__dict__.update(self.__dict__)
        new.__dict__["origin"] = origin
        return new

    def __getattr__(self, name: str):
        """A solution made from a compiled engine's record holds ``_unpack``, a function returning its arrays by name
        (views of one read-only copy of the record): they are made only when one is first read, since most such
        solutions are only ever tested with :meth:`holds` (its ``_holding`` is made at once) and translated."""
        unpack = self.__dict__.get("_unpack")
        if unpack is None or name.startswith("__"):
            raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")
        return self._unpacked(name)

    def _unpacked(self, name: str):
        """Attribute ``name`` after unpacking the record (see :meth:`__getattr__`)."""
        d = self.__dict__
        unpack = d.pop("_unpack", None)
        if unpack is not None:
            for key, value in unpack().items():
                d.setdefault(key, value)
        try:
            return d[name]
        except KeyError:
            raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}") from None

    @cached_property
    def spring_lin(self) -> np.ndarray:
        """(m, 2) gradient of each cell's spring force in the local centre of mass (N/m)."""
        if "_unpack" in self.__dict__:  # a compiled record's own figures (see __getattr__)
            return self._unpacked("spring_lin")
        out = self.basis @ self.plane_lin
        out.setflags(write=False)
        return out

    @cached_property
    def spring_gradient(self) -> np.ndarray:
        """(m,) the norms of :attr:`spring_lin`'s rows (N/m)."""
        if "_unpack" in self.__dict__:  # a compiled record's own figures (see __getattr__)
            return self._unpacked("spring_gradient")
        out = np.hypot(self.spring_lin[:, 0], self.spring_lin[:, 1])
        out.setflags(write=False)
        return out

    @cached_property
    def contact_collinear(self) -> bool:
        """Whether the cells in contact lie on one line (or are one cell), as in every solution of the 1-D model:
        then the solution depends on the centre of mass it was solved at, not only on its pattern."""
        return self.one_d or collinear(self.points[self.in_contact])

    def forces(self, com) -> np.ndarray:
        """Normal forces (N) of the supporting cells for centre of mass ``com`` (world coordinates, m)."""
        xi = np.asarray(com, dtype=float) - self.origin
        return self.force_lin @ xi + self.force_const

    def spring_values(self, xi: np.ndarray) -> np.ndarray:
        """Spring force of every supporting cell for local centre of mass ``xi`` (negative = lifted), N."""
        return self.basis @ (self.plane_lin @ xi + self.plane_const)

    def hull_slack(self, xi: np.ndarray) -> np.ndarray:
        """Distance (m) of the local centre of mass inside each supporting half-plane (negative = tipping)."""
        return self.hull_offsets - self.hull_normals @ xi

    def holds(self, xi: np.ndarray) -> bool:
        """Whether this contact set and hull hold at local centre of mass ``xi`` (m): every contact's spring
        compressed, every lifted cell's slack, the centre of mass inside the hull."""
        return _holds(self._holding, float(xi[0]), float(xi[1]))

    @cached_property
    def _holding(self) -> np.ndarray:
        """What :meth:`holds` reads, packed in one array: ``[m, r, q]``, then the (m, r) basis, the (r, 2)
        ``plane_lin``, the (r,) ``plane_const``, the (m,) contact mask (1.0 in contact), the (q, 2) hull normals and
        the (q,) offsets, row by row. A compiled call costs by the argument, and the pattern cache asks this of every
        candidate solution. Filled in by the solve, so that the copies :meth:`at` makes share it."""
        out = _pack_holding(*(np.array(a) for a in (self.basis, self.plane_lin, self.plane_const, self.in_contact,
                                                     self.hull_normals, self.hull_offsets)))  # as _planar's types
        out.setflags(write=False)
        return out


@njit(cache=True)
def _pack_holding(basis, plane_lin, plane_const, in_contact, hull_normals, hull_offsets):
    """:attr:`SupportSolution._holding` of these arrays (C-contiguous), compiled (np.concatenate of them took ~8 us
    a solve)."""
    (m, r), q = basis.shape, hull_offsets.shape[0]
    out = np.empty(3 + m * r + 3 * r + m + 3 * q)
    out[0], out[1], out[2] = m, r, q
    k = _put(out, 3, basis.ravel())
    k = _put(out, k, plane_lin.ravel())
    k = _put(out, k, plane_const)
    k = _put(out, k, in_contact.astype(np.float64))
    k = _put(out, k, hull_normals.ravel())
    _put(out, k, hull_offsets)
    return out


@njit(cache=True, inline="always")
def _put(out, k, flat):
    """Copy ``flat`` into ``out`` from index ``k``; the index after it."""
    out[k:k + flat.shape[0]] = flat
    return k + flat.shape[0]


@leaf
def _holds(p, x, y):
    """:meth:`SupportSolution.holds` on its packed arrays ``p`` (:attr:`SupportSolution._holding`), compiled (a leaf:
    the event loop asks it at every support event)."""
    m, r, q = int(p[0]), int(p[1]), int(p[2])
    basis, plane_lin = 3, 3 + m * r
    plane_const, in_contact = plane_lin + 2 * r, plane_lin + 3 * r
    hull_normals = in_contact + m
    hull_offsets = hull_normals + 2 * q
    for i in range(m):
        spring = 0.0
        for j in range(r):  # (the plane's value, the same floats each cell: no array made for it)
            spring += p[basis + r * i + j] * (p[plane_lin + 2 * j] * x + p[plane_lin + 2 * j + 1] * y
                                              + p[plane_const + j])
        if (spring > 0) != (p[in_contact + i] > 0.5):
            return False
    for k in range(q):
        if p[hull_offsets + k] - (p[hull_normals + 2 * k] * x + p[hull_normals + 2 * k + 1] * y) < 0:
            return False
    return True


def normal_forces(points, com, weight: float, *, lateral_support: bool = False) -> np.ndarray:
    """Normal forces (N) of the cells at ``points`` ((m, 2), m) supporting a parcel of weight ``weight`` (N) whose
    centre of mass is at ``com`` ((2,), m). Eqs. 3-19, with lift-off (forces are never negative).

    Raises:
        TippingError: the centre of mass is outside the supports' convex hull (or off the line of collinear
            supports without ``lateral_support``).

    >>> normal_forces([[-1, -1], [1, -1], [-1, 1], [1, 1]], [0.5, 0.0], 4.0).round(6).tolist()
    [0.5, 1.5, 0.5, 1.5]
    """
    sol = solve_support(points, com, weight, lateral_support=lateral_support)
    return sol.forces(com)


def solve_support(points, com, weight: float, *, lateral_support: bool = False,
                  line_direction=None) -> SupportSolution:
    """Solve the normal forces and contact set of a parcel at ``com`` on the cells ``points`` (m).

    ``line_direction`` orients the 1-D model when a single cell supports a laterally held parcel.
    See :func:`normal_forces` for the model; this returns the full affine map (:class:`SupportSolution`).
    """
    pts = np.asarray(points, dtype=float)
    com = np.asarray(com, dtype=float)
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise ValueError(f"points must have shape (m, 2), got {pts.shape}")
    if com.shape != (2,):
        raise ValueError(f"com must have shape (2,), got {com.shape}")
    if not (math.isfinite(weight) and weight > 0):
        raise ValueError(f"weight must be a positive force in N, got {weight}")
    if not (np.isfinite(pts).all() and np.isfinite(com).all()):
        raise ValueError("points and com must be finite")
    if len(pts) == 0:
        raise TippingError("no cell supports the parcel")
    return solve_prechecked(np.ascontiguousarray(pts), com, weight, lateral_support, line_direction)


def solve_prechecked(pts, com, weight: float, lateral_support: bool, line_direction) -> SupportSolution:
    """:func:`solve_support` for inputs known to be valid: ``pts`` a contiguous (m, 2) float array of finite
    positions (m >= 1), ``com`` (2,) finite, ``weight`` positive (the event engine's new pieces, whose cells and
    states are checked where they come in)."""
    if collinear(pts):
        origin, local, xi, scale = _frame(pts, com)
        return _solve_line(origin, local, xi, weight, _REL_TOL * scale, lateral_support, line_direction)

    (outside, tol, origin, local, xi, h_normals, h_offsets, basis, mapped, forces,
     springs) = _planar(pts, com, float(weight), _MAX_ITER)
    if outside > tol:
        raise TippingError(
            f"centre of mass at ({com[0]:.6g}, {com[1]:.6g}) m is {outside:.3g} m outside the convex hull of its "
            f"{len(pts)} supporting cells: the parcel tips")
    return _finish(origin, local, xi, basis, mapped, weight, h_normals, h_offsets, one_d=False, forces=forces,
                   planar=True, springs=springs)


@njit(cache=True)
def _planar(pts, com, weight, max_iter):
    """The planar model for supports at ``pts`` ((m, 2), m, not collinear) and centre of mass ``com`` (m), in one
    compiled call: the tie tolerance ``tol`` (m), the local frame (origin at the supports' centroid; the supports and
    the centre of mass in it), the hull's half-planes and how far outside them the centre of mass lies (m; > ``tol``:
    it tips, and the map is not solved), the basis rows ``[1, x_i, y_i]``, :func:`_affine_map`'s results,
    :func:`_force_map`'s, and the springs' gradients and their norms (:attr:`SupportSolution.spring_lin`,
    :attr:`SupportSolution.spring_gradient`, the same floats: numba's ``np.dot`` calls the BLAS numpy's ``@`` does)
    with what its holds test reads (:attr:`SupportSolution._holding`). The moment system is solved in closed form
    (:func:`_affine_map_planar`)."""
    m = pts.shape[0]
    origin, local, xi, scale = _frame(pts, com)
    tol = _REL_TOL * scale
    h_normals, h_offsets = _hull(local, tol * scale)
    outside = -np.inf
    for k in range(h_offsets.shape[0]):
        outside = max(outside, h_normals[k, 0] * xi[0] + h_normals[k, 1] * xi[1] - h_offsets[k])
    basis = np.empty((m, 3))
    basis[:, 0] = 1.0
    basis[:, 1:] = local
    if outside > tol:
        mapped = (np.zeros(m, np.bool_), True, np.zeros((3, 2)), np.zeros(3))
    else:
        mapped = _affine_map_planar(basis, weight, xi, max_iter)
    forces = _force_map(basis, mapped[0], mapped[2], mapped[3])
    spring_lin = np.dot(basis, mapped[2])
    springs = (spring_lin, np.hypot(spring_lin[:, 0], spring_lin[:, 1]),
               _pack_holding(basis, mapped[2], mapped[3], mapped[0], h_normals, h_offsets))
    return outside, tol, origin, local, xi, h_normals, h_offsets, basis, mapped, forces, springs


SOLVED, SOLVE_LINE, SOLVE_TIPS, SOLVE_STUCK, SOLVE_FLAT = 0, 1, 2, 3, 4
"""Outcomes of :func:`solve_planar_kernel`: solved; the supports lie on one line (the 1-D model, Python's); the
centre of mass is outside their hull (Python raises TippingError); the contact-set iteration did not converge
(IntegrationError); the contact set lies on one line (its plane is tilted in Python, ``_on_contact_line``)."""


@njit(cache=True)
def solve_planar_kernel(pts, com, weight, max_iter):
    """:func:`solve_prechecked`'s common case without Python, for a compiled event loop that meets a support set it
    has never solved: supports at ``pts`` ((m, 2), m), centre of mass ``com`` (m), weight (N). The same compiled
    arithmetic (:func:`_planar`), so the same floats. Returns (outcome, origin, points, in_contact, basis,
    plane_lin, plane_const, hull_normals, hull_offsets, spring_lin, spring_gradient, holding, force_lin,
    force_const): the arrays of :class:`SupportSolution` (the last three of its cached properties), valid only when
    the outcome is ``SOLVED``; any other outcome (``SOLVE_*``) is left to :func:`solve_prechecked`."""
    if _collinear_kernel(pts, COLLINEAR_TOL):
        status = SOLVE_LINE
        origin, local, xi, _ = _frame(pts, com)
        empty2, empty1 = np.zeros((0, 2)), np.zeros(0)
        return (status, origin, local, np.zeros(0, np.bool_), np.zeros((0, 3)), np.zeros((3, 2)), np.zeros(3),
                empty2, empty1, empty2, empty1, empty1, empty2, empty1)
    (outside, tol, origin, local, xi, h_normals, h_offsets, basis, mapped, forces,
     springs) = _planar(pts, com, weight, max_iter)
    in_contact, converged, plane_lin, plane_const = mapped
    status = SOLVED
    if outside > tol:
        status = SOLVE_TIPS
    elif not converged:
        status = SOLVE_STUCK
    elif not np.all(in_contact) and _collinear_kernel(_rows(local, in_contact), COLLINEAR_TOL):
        status = SOLVE_FLAT  # as _finish's test, which goes to _on_contact_line
    return (status, origin, local, in_contact, basis, plane_lin, plane_const, h_normals, h_offsets, springs[0],
            springs[1], springs[2], forces[0], forces[1])


@njit(cache=True)
def _frame(pts, com):
    """The local frame of supports at ``pts`` ((m, 2), m) under a centre of mass at ``com`` (m): its origin (the
    supports' centroid), the supports and the centre of mass relative to it, and their scale (the largest coordinate
    in it, at least 1e-9 m), to which the tolerances of ties are relative."""
    origin = np.zeros(2)
    for i in range(pts.shape[0]):  # as numpy's mean over axis 0: row by row, then divided
        origin[0] += pts[i, 0]
        origin[1] += pts[i, 1]
    origin /= pts.shape[0]
    local = pts - origin
    xi = com - origin
    return origin, local, xi, max(np.max(np.abs(local)), np.max(np.abs(xi)), 1e-9)


@njit(cache=True)
def _force_map(basis, in_contact, plane_lin, plane_const):
    """The normal-force map of eq. 19 from the spring plane: ``force_lin`` (m, 2) and ``force_const`` (m,), the
    springs' rows ``basis @ plane_lin`` and ``basis @ plane_const`` for cells in contact, zero for lifted ones."""
    m, r = basis.shape
    force_lin = np.zeros((m, 2))
    force_const = np.zeros(m)
    for i in range(m):
        if in_contact[i]:
            for j in range(r):
                force_lin[i, 0] += basis[i, j] * plane_lin[j, 0]
                force_lin[i, 1] += basis[i, j] * plane_lin[j, 1]
                force_const[i] += basis[i, j] * plane_const[j]
    return force_lin, force_const


@njit(cache=True)
def _hull(points, tol):
    """Convex hull of points ((m, 2), m; not all on one line) as half-planes: unit outward normals (k, 2) and offsets
    (k,), the hull being ``normals @ x <= offsets``. Andrew's monotone chain; a vertex that turns by less than
    ``tol`` (m^2, a cross product: the distance it sticks out times an edge) is dropped, as Qhull merges nearly
    coplanar facets, so that no edge is rounding-short with a meaningless normal."""
    m = points.shape[0]
    order = np.argsort(points[:, 1], kind="mergesort")
    order = order[np.argsort(points[order, 0], kind="mergesort")]  # by x, ties by y
    chain = np.empty(2 * m, np.int64)
    k = 0
    for sweep in range(2):  # lower hull left to right, then upper hull right to left
        start = k + 1
        for j in range(m) if sweep == 0 else range(m - 2, -1, -1):
            i = order[j]
            while k >= max(start, 2):
                a, b = chain[k - 2], chain[k - 1]
                cross = ((points[b, 0] - points[a, 0]) * (points[i, 1] - points[a, 1])
                         - (points[b, 1] - points[a, 1]) * (points[i, 0] - points[a, 0]))
                if cross > tol:
                    break
                k -= 1
            chain[k] = i
            k += 1
    n = k - 1  # the chain ends where it began: n counter-clockwise vertices
    normals = np.empty((n, 2))
    offsets = np.empty(n)
    for e in range(n):
        a, b = chain[e], chain[e + 1]
        dx, dy = points[b, 0] - points[a, 0], points[b, 1] - points[a, 1]
        length = np.hypot(dx, dy)
        normals[e, 0], normals[e, 1] = dy / length, -dx / length  # the interior is on the left
        offsets[e] = normals[e, 0] * points[a, 0] + normals[e, 1] * points[a, 1]
    return normals, offsets


def _solve_line(origin, local, xi, weight, tol, lateral_support, line_direction) -> SupportSolution:
    """Collinear supports: the 1-D model (vertical force and one moment equation)."""
    m = len(local)
    if m >= 2 and np.ptp(local, axis=0).max() > 0:
        u = np.linalg.svd(local, full_matrices=False)[2][0]
    elif line_direction is not None:
        u = np.asarray(line_direction, dtype=float)
        u = u / np.linalg.norm(u)
    else:
        u = np.array([1.0, 0.0])
    n = np.array([-u[1], u[0]])
    s = local @ u
    s_c = float(xi @ u)
    normals = [u, -u]
    offsets = [s.max(), -s.min()]
    off_line = abs(float(xi @ n))
    if not lateral_support:
        if off_line > tol:
            raise TippingError(
                f"the {m} supporting cell(s) are collinear and the centre of mass is {off_line:.3g} m off their line: "
                "the parcel tips")
        normals += [n, -n]
        offsets += [tol, tol]
    h_normals = np.array(normals)
    h_offsets = np.array(offsets, dtype=float)
    if s_c > s.max() + tol or s_c < s.min() - tol:
        raise TippingError(
            f"centre of mass is beyond the end of the line of {m} supporting cell(s) "
            f"(by {max(s_c - s.max(), s.min() - s_c):.3g} m): the parcel tips")
    basis = np.column_stack([np.ones(m), s])
    r_lin = np.vstack([[0.0, 0.0], u])
    r_const = np.array([1.0, 0.0])
    mapped = _affine_map(basis, r_lin, r_const, float(weight), xi, _MAX_ITER)
    return _finish(origin, local, xi, basis, mapped, weight, h_normals, h_offsets, one_d=True)


def _finish(origin, local, xi, basis, mapped, weight, h_normals, h_offsets, *, one_d, forces=None,
            planar: bool = False, springs=None) -> SupportSolution:
    """The :class:`SupportSolution` from the results of :func:`_affine_map` (``mapped``) and, when computed, of
    :func:`_force_map` (``forces``) and of :func:`_planar`'s last (``springs``: the springs' gradients, their norms
    and the packed holds arrays). ``planar``: the supports at ``local`` are known not to lie on one line."""
    in_contact, converged, plane_lin, plane_const = mapped
    if not converged:
        raise IntegrationError("the normal-force contact-set iteration did not converge")
    # the contacts lie on one line only if some have lifted off, when the supports do not (most new solutions)
    flat = one_d or (not (planar and all(in_contact.tolist())) and collinear(local[in_contact]))  # (.all(): ~1 us)
    if flat and not one_d:
        plane_const, h_normals, h_offsets = _on_contact_line(local, xi, basis, in_contact, plane_lin, plane_const,
                                                             weight, h_normals, h_offsets)
        forces = None
    force_lin, force_const = forces if forces is not None else _force_map(
        np.ascontiguousarray(basis), in_contact, np.ascontiguousarray(plane_lin), np.ascontiguousarray(plane_const))
    for arr in (local, basis, plane_lin, plane_const, force_lin, force_const, h_normals, h_offsets, in_contact,
                *(springs or ())):
        arr.setflags(write=False)
    sol = SupportSolution(origin, local, in_contact, basis, plane_lin, plane_const, force_lin, force_const,
                          h_normals, h_offsets, one_d, float(weight))
    if springs is not None:  # the cached properties, filled in (what holds reads, unless the hull was changed)
        sol.__dict__["spring_lin"], sol.__dict__["spring_gradient"] = springs[:2]
        if not flat:
            sol.__dict__["_holding"] = springs[2]
    sol.spring_gradient  # computed now (with spring_lin), so that the copies SupportSolution.at makes share them
    sol._holding  # likewise
    sol.__dict__["contact_collinear"] = flat  # known now: the cached property, filled in
    return sol


@njit(cache=True)
def _affine_map(basis, r_lin, r_const, weight, xi, max_iter):
    """The contact set and spring plane of supports with rows ``basis`` under the load ``weight (r_lin @ xi +
    r_const)``: (contact mask, converged, plane_lin, plane_const).

    Compiled code here calls only compiled code of this file: numba's cache does not notice edits to a compiled
    function in another file from its callers (a documented limitation), so a call into, say, layout's collinearity
    test would keep running the old version after an edit there."""
    load = np.empty(r_const.shape[0])
    for i in range(load.shape[0]):
        load[i] = weight * (r_lin[i, 0] * xi[0] + r_lin[i, 1] * xi[1] + r_const[i])
    in_contact, converged = _contact_set(basis, load, max_iter)
    ba = _rows(basis, in_contact)
    minv = np.linalg.pinv(ba.T @ ba)
    plane_lin = weight * minv @ r_lin  # eq. 19: theta = W (M^T A M)^-1 (W_x X_c + W_c), reduced to the moment system
    plane_const = weight * minv @ r_const
    return in_contact, converged, plane_lin, plane_const


_CLOSED_SINGULAR = 1e-8
"""Below this ratio of the moment matrix's determinant to the product of its diagonal (Hadamard's bound, which it
never exceeds) the contacts are close to one line: the closed-form solve hands over to the LAPACK one."""


@njit(cache=True)
def _moment_inverse(basis, act, out):
    """The inverse of the moment matrix ``sum_i B_i^T B_i`` over the cells in ``act`` (rows ``B_i = [1, x_i, y_i]``
    of ``basis``, m), into ``out`` (3, 3), from the sums of 1, x, y, x^2, xy and y^2 by cofactors: the moment
    system that eqs. 8-19 reduce to, without LAPACK (an SVD took ~10 us a solve). Whether the matrix is far enough
    from singular (contacts not near one line) for that to be accurate."""
    s0 = sx = sy = sxx = sxy = syy = 0.0
    for i in range(basis.shape[0]):
        if act[i]:
            x, y = basis[i, 1], basis[i, 2]
            s0 += 1.0
            sx += x
            sy += y
            sxx += x * x
            sxy += x * y
            syy += y * y
    c00, c11, c22 = sxx * syy - sxy * sxy, s0 * syy - sy * sy, s0 * sxx - sx * sx
    c01, c02, c12 = sy * sxy - sx * syy, sx * sxy - sy * sxx, sx * sy - s0 * sxy
    det = s0 * c00 + sx * c01 + sy * c02
    if not det > _CLOSED_SINGULAR * s0 * sxx * syy:
        return False
    out[0, 0], out[1, 1], out[2, 2] = c00 / det, c11 / det, c22 / det
    out[0, 1] = out[1, 0] = c01 / det
    out[0, 2] = out[2, 0] = c02 / det
    out[1, 2] = out[2, 1] = c12 / det
    return True


@njit(cache=True)
def _affine_map_planar(basis, weight, xi, max_iter):
    """:func:`_affine_map` of planar supports (rows ``basis`` ``[1, x_i, y_i]``, m) under the load of a parcel of
    ``weight`` (N) at local centre of mass ``xi`` (m), with the moment system solved in closed form
    (:func:`_moment_inverse`): the contact-set iteration's full Newton steps, every cell in contact first, so one
    solve when no force nears zero. Where a contact set is close to one line, or the iteration would repeat a set
    (its damped steps), the LAPACK solve takes over from the start."""
    m = basis.shape[0]
    load = np.empty(3)
    load[0], load[1], load[2] = weight, weight * xi[0], weight * xi[1]  # W [1, x_c, y_c] (eqs. 3-5)
    tie = _REL_TOL * max(abs(load[0]), 1e-300)
    minv = np.empty((3, 3))
    theta = np.empty(3)
    act = np.ones(m, np.bool_)
    seen = np.zeros((max_iter, m), np.bool_)
    if _moment_inverse(basis, act, minv):  # every cell in contact: the iteration's start, as _contact_set's
        _times(minv, load, theta)
        for it in range(max_iter):
            act = np.empty(m, np.bool_)
            for i in range(m):
                act[i] = theta[0] + theta[1] * basis[i, 1] + theta[2] * basis[i, 2] > tie
            if not act.any() or _contains(seen[:it], act) or not _moment_inverse(basis, act, minv):
                break
            _times(minv, load, theta)  # the set's spring plane: theta = M^-1 W [1, x_c, y_c] (eq. 19, reduced)
            holds = True
            for i in range(m):
                p = theta[0] + theta[1] * basis[i, 1] + theta[2] * basis[i, 2]
                holds = holds and (p > -tie if act[i] else p <= tie)
            if holds:
                plane_lin = np.empty((3, 2))
                plane_const = np.empty(3)
                for j in range(3):
                    plane_lin[j, 0], plane_lin[j, 1] = weight * minv[j, 1], weight * minv[j, 2]
                    plane_const[j] = weight * minv[j, 0]
                return act, True, plane_lin, plane_const
            seen[it] = act
    return _affine_map(basis, _PLANE_LIN, _PLANE_CONST, weight, xi, max_iter)


@njit(cache=True, inline="always")
def _times(a, v, out):
    """``out = a @ v`` for a (3, 3) matrix and a (3,) vector."""
    for j in range(3):
        out[j] = a[j, 0] * v[0] + a[j, 1] * v[1] + a[j, 2] * v[2]


@njit(cache=True)
def _rows(a, mask):
    """The rows of ``a`` where ``mask``, as a new contiguous array."""
    out = np.empty((np.count_nonzero(mask), a.shape[1]))
    k = 0
    for i in range(a.shape[0]):
        if mask[i]:
            out[k] = a[i]
            k += 1
    return out


@njit(cache=True)
def _null_space(a):
    """Orthonormal rows spanning the null space of the rows of ``a`` ((k, d) -> (d - rank, d))."""
    _, sv, vt = np.linalg.svd(a, full_matrices=True)
    return vt[np.sum(sv > 1e-12 * max(sv.max(), 1e-300)):]


@njit(cache=True)
def _lstsq(a, b):
    """Least-squares solution of ``a x = b``, cut off as numpy's ``lstsq(a, b, rcond=None)``."""
    return np.linalg.lstsq(a, b, rcond=np.finfo(np.float64).eps * max(a.shape[0], a.shape[1]))[0]


def _on_contact_line(local, xi, basis, in_contact, plane_lin, plane_const, weight, h_normals, h_offsets):
    """A load exactly on the line (or point) of a collinear contact set under planar supports: the plate tilts about
    that line, which the moment equations leave free. Tilt it so that the other springs are slack (the solution is
    then consistent), and add to the hull the slab in which the centre of mass stays on the line (half-width ``_SLAB``
    relative to the supports' size: far wider than the contact-set tie, so that beyond it the other cells' share is
    clearly positive and a planar contact set is found): the solution holds only there, so leaving it is an event
    and the next piece is solved afresh, the other cells touching down and sharing the load."""
    tol = _SLAB * max(float(np.max(np.abs(local))), float(np.max(np.abs(xi))), 1e-9)
    pts = local[in_contact]
    centre = pts.mean(axis=0)
    if len(pts) >= 2 and np.ptp(pts, axis=0).max() > 0:
        u = np.linalg.svd(pts - centre, full_matrices=False)[2][0]
        dirs = [np.array([-u[1], u[0]])]
    else:
        dirs = [np.array([1.0, 0.0]), np.array([0.0, 1.0])]
    rows = [d * sign for d in dirs for sign in (1.0, -1.0)]
    h_normals = np.vstack([h_normals, rows])
    h_offsets = np.concatenate([h_offsets, [float(r @ centre) + tol for r in rows]])
    null = _null_space(np.ascontiguousarray(basis[in_contact]))
    if len(null) == 1:
        p, q = basis[~in_contact] @ (plane_lin @ xi + plane_const), basis[~in_contact] @ null[0]
        for margin in (_SLAB * 1e3 * weight, 0.0):  # each other spring clearly slack, else at most 0
            hi = min([(-margin - a) / b for a, b in zip(p, q) if b > 1e-15], default=np.inf)
            lo = max([(-margin - a) / b for a, b in zip(p, q) if b < -1e-15], default=-np.inf)
            if lo <= hi:
                break
        lam = 0.0 if lo <= 0.0 <= hi else (hi if np.isfinite(hi) and hi < 0 else lo)
        plane_const = plane_const + lam * null[0]
    return plane_const, h_normals, h_offsets


@njit(cache=True)
def _tilt_clear(active: np.ndarray, inactive: np.ndarray, theta: np.ndarray, tie: float) -> bool:
    """Whether a degenerate (collinear) contact set's solution ``theta`` can be moved along its null space, which
    leaves the active springs unchanged, so that every inactive spring is slack (a load exactly on the line of the
    contacts; otherwise rounding decides which side the plate tilts to)."""
    null = _null_space(active)
    if null.shape[0] != 1:
        return False
    p = inactive @ theta
    q = inactive @ np.ascontiguousarray(null[0])
    lo, hi = -np.inf, np.inf
    for pk, qk in zip(p, q):
        if abs(qk) <= 1e-15:
            if pk > tie:
                return False
        elif qk > 0:
            hi = min(hi, (tie - pk) / qk)
        else:
            lo = max(lo, (tie - pk) / qk)
    return lo <= hi


def contact_set(basis: np.ndarray, rhs: np.ndarray, max_iter: int = _MAX_ITER) -> np.ndarray:
    """Contact set of tensionless springs: minimise ``phi(theta) = 1/2 sum max(0, B_i theta)^2 - rhs . theta``.

    The gradient of ``phi`` is the equilibrium residual ``B^T max(0, B theta) - rhs``, so its minimiser gives forces
    ``N = max(0, B theta)`` that are non-negative and balance the load; ``phi`` is convex, and coercive when the load
    lies strictly inside the supports. A full Newton step on the current contact set is the paper's solve with that
    set's mask (the fast path, usually exact in one or two steps). When that step is not an exact solution (the set
    would cycle, or is degenerate), a damped Newton step with backtracking line search on ``phi`` is taken, which
    converges for this convex function. Compiled (numba): a support solve is a few 3 x 3 problems, where numpy's
    per-call cost was most of the time.

    Returns the boolean contact mask.
    """
    act, converged = _contact_set(np.ascontiguousarray(basis, dtype=np.float64),
                                  np.ascontiguousarray(rhs, dtype=np.float64), max_iter)
    if not converged:
        raise IntegrationError("the normal-force contact-set iteration did not converge")
    return act


@njit(cache=True)
def _phi(basis, rhs, theta):
    """The convex function :func:`contact_set` minimises, at ``theta``."""
    p = np.maximum(basis @ theta, 0.0)
    return 0.5 * (p @ p) - rhs @ theta


@njit(cache=True)
def _contact_set(basis, rhs, max_iter):
    """:func:`contact_set`, compiled: (contact mask, converged)."""
    m, d = basis.shape
    scale = max(abs(rhs[0]), 1e-300)
    tie = _REL_TOL * scale
    res_tol = 1e-9 * scale * max(1.0, np.max(np.abs(basis)))
    theta = _lstsq(basis.T @ basis, rhs)
    seen = np.zeros((max_iter, m), np.bool_)
    n_seen = 0
    act = np.zeros(m, np.bool_)
    for _ in range(max_iter):
        p = basis @ theta
        act = p > tie
        if not act.any():
            act = p >= p.max()
        ba = _rows(basis, act)
        hess = ba.T @ ba
        full = _lstsq(hess, rhs)
        p_full = basis @ full
        exact = np.max(np.abs(ba.T @ (ba @ full) - rhs)) <= res_tol
        if exact and np.all(p_full[act] > -tie):
            if np.all(p_full[~act] <= tie):
                return act, True
            if _tilt_clear(ba, _rows(basis, ~act), full, tie):
                return act, True  # a collinear contact set carrying the load on its line: the plate tilts about it
        if exact and not _contains(seen[:n_seen], act):
            seen[n_seen] = act
            n_seen += 1
            theta = full
            continue
        # Damped Newton step on the convex function phi (regularised where the contact set is degenerate).
        grad = basis.T @ np.maximum(p, 0.0) - rhs
        reg = 1e-12 * (np.trace(hess) + 1.0)
        step = -np.linalg.solve(hess + reg * np.eye(d), grad)
        slope = grad @ step
        f0 = _phi(basis, rhs, theta)
        t = 1.0
        while t > 1e-14 and _phi(basis, rhs, theta + t * step) > f0 + 1e-4 * t * slope:
            t *= 0.5
        theta = theta + t * step
    return act, False


@njit(cache=True)
def _contains(rows, row):
    """Whether ``row`` is one of ``rows``."""
    for i in range(rows.shape[0]):
        if np.array_equal(rows[i], row):
            return True
    return False
