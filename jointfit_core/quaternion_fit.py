"""The largest eigenpair of Horn's 4 x 4 quaternion matrix, for many frames at once.

The least-squares rotation between two point sets is the eigenvector of the
largest eigenvalue of Horn's symmetric, traceless 4 x 4 matrix ``N`` built from
the 3 x 3 correlation matrix ``S`` (Horn 1987). LAPACK's ``eigh`` computes all
four eigenpairs of each matrix in ~1.8 us; for blocks of frames this module
finds only the largest one with vectorised elementwise arithmetic:

* the characteristic polynomial ``p(l) = l^4 + c2 l^2 + c1 l + c0`` with
  ``c2 = -2 sum(S_ij^2)``, ``c1 = -8 det(S)``, ``c0 = det(N)`` (Horn 1987, eq. 40-42);
* Newton's method on ``p`` from the upper bound ``(|x_c|^2 + |y_c|^2) / 2`` of the
  largest root (the quaternion characteristic polynomial method of Theobald
  2005): ``p`` is increasing and convex above its largest root, so the
  iterates decrease monotonically onto it;
* the eigenvector from the adjugate of ``N - l I``: for a simple eigenvalue
  its columns are all multiples of the eigenvector (Liu, Agrafiotis and
  Theobald 2010); the column with the largest diagonal entry is taken;
* one refinement: the eigenvalue becomes that vector's Rayleigh quotient and
  the eigenvector is taken again, which brings both to LAPACK's accuracy when
  eigenvalues are close (the polynomial's root is ill-conditioned there).

Rows whose largest eigenvalue is not simple to working precision (the
adjugate vanishes), or whose Newton iteration does not settle, are handed to
``numpy.linalg.eigh``. Each row's result depends only on that row (converged
rows are frozen), so a frame gives the same result in any block.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

__all__ = ["HORN_A", "HORN_B", "largest_eigenpair", "largest_eigenpair_entries", "rotations_from_correlations"]

#: Newton stops for a row when a step changes the eigenvalue by less than this times the bound.
NEWTON_RTOL = 1e-15
NEWTON_MAX_STEPS = 60
#: The eigenvector is taken again where its Rayleigh quotient moves the eigenvalue by more than this
#: times the bound (a few ulp: the polynomial's root was ill-conditioned).
REFINE_RTOL = 1e-14
#: A row goes to ``eigh`` when the adjugate's largest diagonal entry is below this times bound^3.
ADJUGATE_RTOL = 1e-10


def _horn_matrices() -> tuple[FloatArray, FloatArray]:
    """Fixed linear maps of Horn's method: ``N = A @ vec(S)`` (16, 9) and ``vec(R) = B @ vec(q q^T)`` (9, 16).

    ``S = sum x y^T`` of centred template points ``x`` and measured points ``y``; the rotation
    ``R`` maximising ``sum y . R x`` comes from the unit quaternion ``q = (w, x, y, z)`` of the
    largest eigenvalue of the symmetric ``N`` (Horn 1987), and that eigenvalue is ``tr(R S)``.
    """
    A = np.zeros((4, 4, 3, 3))
    xx, xy, xz, yx, yy, yz, zx, zy, zz = ((i, j) for i in range(3) for j in range(3))
    entries = {
        (0, 0): [(xx, 1), (yy, 1), (zz, 1)],
        (0, 1): [(yz, 1), (zy, -1)],
        (0, 2): [(zx, 1), (xz, -1)],
        (0, 3): [(xy, 1), (yx, -1)],
        (1, 1): [(xx, 1), (yy, -1), (zz, -1)],
        (1, 2): [(xy, 1), (yx, 1)],
        (1, 3): [(zx, 1), (xz, 1)],
        (2, 2): [(xx, -1), (yy, 1), (zz, -1)],
        (2, 3): [(yz, 1), (zy, 1)],
        (3, 3): [(xx, -1), (yy, -1), (zz, 1)],
    }
    for (r, c), terms in entries.items():
        for (i, j), sign in terms:
            A[r, c, i, j] += sign
            if r != c:
                A[c, r, i, j] += sign
    B = np.zeros((3, 3, 4, 4))
    w, x, y, z = range(4)
    rot = {
        (0, 0): [((w, w), 1), ((x, x), 1), ((y, y), -1), ((z, z), -1)],
        (0, 1): [((x, y), 2), ((w, z), -2)],
        (0, 2): [((x, z), 2), ((w, y), 2)],
        (1, 0): [((x, y), 2), ((w, z), 2)],
        (1, 1): [((w, w), 1), ((x, x), -1), ((y, y), 1), ((z, z), -1)],
        (1, 2): [((y, z), 2), ((w, x), -2)],
        (2, 0): [((x, z), 2), ((w, y), -2)],
        (2, 1): [((y, z), 2), ((w, x), 2)],
        (2, 2): [((w, w), 1), ((x, x), -1), ((y, y), -1), ((z, z), 1)],
    }
    for (r, c), terms in rot.items():
        for (i, j), coef in terms:
            B[r, c, i, j] += coef
    return A.reshape(16, 9), B.reshape(9, 16)


#: Horn's maps: ``N = HORN_A @ vec(S)`` (16, 9) and ``vec(R) = HORN_B @ vec(q q^T)`` (9, 16).
HORN_A, HORN_B = _horn_matrices()


def _entries(A: FloatArray) -> list[list[FloatArray]]:
    """The entries of ``A`` (..., 4, 4) as 16 contiguous arrays of shape (...) (fast elementwise work)."""
    At = np.ascontiguousarray(np.moveaxis(A, (-2, -1), (0, 1)))
    return [[At[i, j] for j in range(4)] for i in range(4)]


def _minors(a: list[list[FloatArray]]) -> tuple[list[FloatArray], list[FloatArray]]:
    """The twelve 2 x 2 minors of rows (0, 1) and of rows (2, 3) of a 4 x 4 matrix given by its entries."""
    pairs = ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))
    top = [a[0][i] * a[1][j] - a[1][i] * a[0][j] for i, j in pairs]
    bottom = [a[2][i] * a[3][j] - a[3][i] * a[2][j] for i, j in pairs]
    return top, bottom


def _det3(S: FloatArray) -> FloatArray:
    """Determinants of 3 x 3 matrices (..., 3, 3) by cofactors of the first row, shape (...)."""
    return (
        S[..., 0, 0] * (S[..., 1, 1] * S[..., 2, 2] - S[..., 1, 2] * S[..., 2, 1])
        - S[..., 0, 1] * (S[..., 1, 0] * S[..., 2, 2] - S[..., 1, 2] * S[..., 2, 0])
        + S[..., 0, 2] * (S[..., 1, 0] * S[..., 2, 1] - S[..., 1, 1] * S[..., 2, 0])
    )


def determinant(A: FloatArray) -> FloatArray:
    """Determinants of 4 x 4 matrices ``A`` (..., 4, 4) by Laplace expansion in 2 x 2 minors, shape (...)."""
    s, c = _minors(_entries(A))
    return s[0] * c[5] - s[1] * c[4] + s[2] * c[3] + s[3] * c[2] - s[4] * c[1] + s[5] * c[0]


def adjugate(A: FloatArray) -> FloatArray:
    """The adjugate of 4 x 4 matrices ``A`` (..., 4, 4): ``adj(A) = det(A) inv(A)``, shape (..., 4, 4)."""
    return np.moveaxis(_adjugate_entries(_entries(A)), (0, 1), (-2, -1))


def _adjugate_entries(a: list[list[FloatArray]]) -> FloatArray:
    """The adjugate of a 4 x 4 matrix given by its entries (arrays of shape (...)), entries first: (4, 4, ...).

    Each entry is written as one contiguous array (the matrices-last layout of ``adjugate``'s
    result would scatter every write).
    """
    s, c = _minors(a)
    adj = np.empty((4, 4, *a[0][0].shape))
    adj[0, 0] = a[1][1] * c[5] - a[1][2] * c[4] + a[1][3] * c[3]
    adj[0, 1] = -a[0][1] * c[5] + a[0][2] * c[4] - a[0][3] * c[3]
    adj[0, 2] = a[3][1] * s[5] - a[3][2] * s[4] + a[3][3] * s[3]
    adj[0, 3] = -a[2][1] * s[5] + a[2][2] * s[4] - a[2][3] * s[3]
    adj[1, 0] = -a[1][0] * c[5] + a[1][2] * c[2] - a[1][3] * c[1]
    adj[1, 1] = a[0][0] * c[5] - a[0][2] * c[2] + a[0][3] * c[1]
    adj[1, 2] = -a[3][0] * s[5] + a[3][2] * s[2] - a[3][3] * s[1]
    adj[1, 3] = a[2][0] * s[5] - a[2][2] * s[2] + a[2][3] * s[1]
    adj[2, 0] = a[1][0] * c[4] - a[1][1] * c[2] + a[1][3] * c[0]
    adj[2, 1] = -a[0][0] * c[4] + a[0][1] * c[2] - a[0][3] * c[0]
    adj[2, 2] = a[3][0] * s[4] - a[3][1] * s[2] + a[3][3] * s[0]
    adj[2, 3] = -a[2][0] * s[4] + a[2][1] * s[2] - a[2][3] * s[0]
    adj[3, 0] = -a[1][0] * c[3] + a[1][1] * c[1] - a[1][2] * c[0]
    adj[3, 1] = a[0][0] * c[3] - a[0][1] * c[1] + a[0][2] * c[0]
    adj[3, 2] = -a[3][0] * s[3] + a[3][1] * s[1] - a[3][2] * s[0]
    adj[3, 3] = a[2][0] * s[3] - a[2][1] * s[1] + a[2][2] * s[0]
    return adj


def _adjugate_symmetric_entries(a: list[list[FloatArray]]) -> FloatArray:
    """:func:`_adjugate_entries` of a symmetric matrix: the upper triangle, mirrored (10 entries instead of 16)."""
    s, c = _minors(a)
    adj = np.empty((4, 4, *a[0][0].shape))
    adj[0, 0] = a[1][1] * c[5] - a[1][2] * c[4] + a[1][3] * c[3]
    adj[0, 1] = adj[1, 0] = -a[0][1] * c[5] + a[0][2] * c[4] - a[0][3] * c[3]
    adj[0, 2] = adj[2, 0] = a[3][1] * s[5] - a[3][2] * s[4] + a[3][3] * s[3]
    adj[0, 3] = adj[3, 0] = -a[2][1] * s[5] + a[2][2] * s[4] - a[2][3] * s[3]
    adj[1, 1] = a[0][0] * c[5] - a[0][2] * c[2] + a[0][3] * c[1]
    adj[1, 2] = adj[2, 1] = -a[3][0] * s[5] + a[3][2] * s[2] - a[3][3] * s[1]
    adj[1, 3] = adj[3, 1] = a[2][0] * s[5] - a[2][2] * s[2] + a[2][3] * s[1]
    adj[2, 2] = a[3][0] * s[4] - a[3][1] * s[2] + a[3][3] * s[0]
    adj[2, 3] = adj[3, 2] = -a[2][0] * s[4] + a[2][1] * s[2] - a[2][3] * s[0]
    adj[3, 3] = a[2][0] * s[3] - a[2][1] * s[1] + a[2][2] * s[0]
    return adj


def largest_eigenpair(N: FloatArray, S: FloatArray, bound: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Largest eigenvalue and its unit eigenvector of Horn's matrices, vectorised over the leading axes.

    Parameters
    ----------
    N : ndarray, shape (..., 4, 4)
        Horn's symmetric, traceless quaternion matrices (length^2).
    S : ndarray, shape (..., 3, 3)
        The correlation matrices ``N`` was built from, ``sum_i x_c,i y_i^T`` (length^2).
    bound : ndarray, shape (...)
        An upper bound of the largest eigenvalue: ``(|x_c|^2 + |y_c|^2) / 2`` over the
        points (length^2), by Cauchy-Schwarz.

    Returns
    -------
    lam : ndarray, shape (...)
        The largest eigenvalue.
    q : ndarray, shape (..., 4)
        A unit eigenvector for it (the sign is arbitrary: the rotation depends on ``q q^T``).

    Notes
    -----
    Horn (1987), "Closed-form solution of absolute orientation using unit
    quaternions", J. Opt. Soc. Am. A 4, eq. 40-42 for the coefficients;
    Theobald (2005), Acta Cryst. A61, for Newton's method from the bound;
    Liu, Agrafiotis and Theobald (2010), J. Comput. Chem. 31, for the
    eigenvector from the adjugate. Agrees with ``numpy.linalg.eigh`` to a few
    ulp of ``bound`` in the eigenvalue (tested).
    """
    shape = N.shape[:-2]
    Nt = np.ascontiguousarray(np.moveaxis(N.reshape(-1, 4, 4), (1, 2), (0, 1)))
    lam, qt = largest_eigenpair_entries(Nt, S, bound)
    return lam.reshape(shape), np.ascontiguousarray(qt.T).reshape(*shape, 4)


def largest_eigenpair_entries(Nt: FloatArray, S: FloatArray, bound: FloatArray) -> tuple[FloatArray, FloatArray]:
    """:func:`largest_eigenpair` of M matrices given entries first: ``Nt`` (4, 4, M); returns ``lam`` (M,), ``q`` (4, M).

    The layout its elementwise steps work in (each entry one contiguous array); a caller that
    builds ``N`` as ``A @ vec(S)`` gets it from one matrix product.
    """
    S = S.reshape(-1, 3, 3)
    bound = np.asarray(bound, dtype=np.float64).reshape(-1)
    a = [[Nt[i, j] for j in range(4)] for i in range(4)]
    c2 = -2.0 * np.einsum("mij,mij->m", S, S)
    c1 = -8.0 * _det3(S)
    s, c = _minors(a)
    c0 = s[0] * c[5] - s[1] * c[4] + s[2] * c[3] + s[3] * c[2] - s[4] * c[1] + s[5] * c[0]
    lam = bound.copy()
    active = lam > 0.0
    tol = NEWTON_RTOL * lam
    for _ in range(NEWTON_MAX_STEPS):
        if not active.any():
            break
        l2 = lam * lam
        p = (l2 + c2) * l2 + c1 * lam + c0
        dp = (4.0 * l2 + 2.0 * c2) * lam + c1
        with np.errstate(divide="ignore", invalid="ignore"):
            step = np.where(active & (dp > 0.0), p / dp, 0.0)
        lam = np.where(active, lam - step, lam)
        active &= np.abs(step) > tol
    q, bad = _eigenvector(Nt, lam, bound)
    bad |= active
    # The polynomial's root is only as good as its conditioning (close eigenvalues, e.g. three
    # markers); the Rayleigh quotient of its eigenvector is good to O(error^2). Where it moves
    # the eigenvalue by more than rounding, the eigenvector is taken again from it.
    rayleigh = np.einsum("im,ijm,jm->m", q, Nt, q)
    redo = np.flatnonzero(~bad & (np.abs(rayleigh - lam) > REFINE_RTOL * bound))
    lam = np.where(bad, lam, rayleigh)
    if redo.size:
        q_redo, bad_redo = _eigenvector(Nt[:, :, redo], lam[redo], bound[redo])
        q[:, redo] = q_redo
        bad[redo] |= bad_redo
    if bad.any():
        w, v = np.linalg.eigh(np.moveaxis(Nt[:, :, bad], 2, 0))
        lam[bad] = w[:, 3]
        q[:, bad] = v[:, :, 3].T
    return lam, q


def _eigenvector(Nt: FloatArray, lam: FloatArray, bound: FloatArray) -> tuple[FloatArray, NDArray[np.bool_]]:
    """Unit eigenvectors (4, M) of ``Nt`` (4, 4, M) for eigenvalues ``lam`` (M,) from the adjugate of ``N - lam I``.

    Also returns the rows where the adjugate vanishes (the eigenvalue is not simple to working
    precision, or ``lam`` is not one): their vectors are meaningless.
    """
    a = [[Nt[i, j] - lam if i == j else Nt[i, j] for j in range(4)] for i in range(4)]
    adj = _adjugate_symmetric_entries(a)
    diag = np.abs(adj[_DIAGONAL, _DIAGONAL])  # (4, M)
    j = np.argmax(diag, axis=0)
    col = np.take_along_axis(adj, j[None, None, :], axis=1)[:, 0]  # (4, M): column j of each
    norm = np.sqrt(np.einsum("im,im->m", col, col))
    bad = ~(np.take_along_axis(diag, j[None, :], axis=0)[0] > ADJUGATE_RTOL * bound**3)
    with np.errstate(divide="ignore", invalid="ignore"):
        q = col / norm
    return q, bad


_DIAGONAL = np.arange(4)


def rotations_from_correlations(S: FloatArray, bound: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Least-squares rotations of M point-set pairs from their correlation matrices (Horn 1987).

    Parameters
    ----------
    S : ndarray, shape (M, 3, 3)
        ``sum_i x_c,i y_i^T`` of centred template points ``x_c`` and measured points ``y``
        (length^2).
    bound : ndarray, shape (M,)
        ``(|x_c|^2 + |y_c|^2) / 2`` summed over the points (length^2).

    Returns
    -------
    R : ndarray, shape (M, 3, 3)
        The proper rotation maximising ``sum_i y_i . R x_c,i`` (never a reflection).
    lam : ndarray, shape (M,)
        ``tr(R S)``, the largest eigenvalue of Horn's matrix: the residual sum of
        squares is ``|x_c|^2 + |y_c|^2 - 2 lam``.
    """
    m = S.shape[0]
    Nt = (HORN_A @ S.reshape(m, 9).T).reshape(4, 4, m)
    if m <= EIGH_BELOW:  # a few pairs (a frame's gate): LAPACK beats the ~100 array operations of the closed form
        w, v = _eigh(np.moveaxis(Nt, 2, 0))
        lam, q = w[:, 3], v[:, :, 3].T
    else:
        lam, q = largest_eigenpair_entries(Nt, S, bound)
    R = (HORN_B @ (q[:, None, :] * q[None, :, :]).reshape(16, m)).T.reshape(m, 3, 3)
    return R, lam


try:  # the gufunc behind np.linalg.eigh (the same LAPACK call, the same numbers), without its Python-level checks
    from numpy.linalg import _umath_linalg

    _eigh: Any = _umath_linalg.eigh_lo
except (ImportError, AttributeError):  # pragma: no cover - other numpy versions
    _eigh = np.linalg.eigh

#: Up to this many pairs :func:`rotations_from_correlations` takes ``numpy.linalg.eigh`` (the same
#: eigenpair to a few ulp, tested): the closed form pays off on many pairs at once.
EIGH_BELOW = 16
