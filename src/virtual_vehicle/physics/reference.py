"""Literal implementations of the paper's formulas, for validation and benchmarks only (slow on purpose).

``paper_normal_forces`` builds the (n+3) x (n+3) system of eq. 8 over *all* n cells, the mask matrix of eq. 14 for
the cells under the parcel, and evaluates eq. 19 with an explicit matrix inverse, exactly as printed. It has no
lift-off and no tipping check: it is the paper's model, valid while every masked force is non-negative.
Units: m, N.
"""

from __future__ import annotations

import numpy as np


def paper_system(cells) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A, W_x / W and W_c / W of eqs. 8-10 for cells at ``cells`` ((n, 2), m); the W factors are applied later."""
    P = np.asarray(cells, dtype=float)
    n = len(P)
    x, y = P[:, 0], P[:, 1]
    A = np.zeros((n + 3, n + 3))
    A[:n, :n] = np.eye(n)  # eq. 7: N_i - c - b y_i - a x_i = 0
    A[:n, n] = -1.0
    A[:n, n + 1] = -y
    A[:n, n + 2] = -x
    A[n, :n] = -1.0  # eq. 3
    A[n + 1, :n] = -y  # eq. 4
    A[n + 2, :n] = -x  # eq. 5
    Wx = np.zeros((n + 3, 2))
    Wx[n + 1, 1] = -1.0
    Wx[n + 2, 0] = -1.0
    Wc = np.zeros(n + 3)
    Wc[n] = -1.0
    return A, Wx, Wc


def mask_matrix(n: int, under) -> np.ndarray:
    """Eq. 14: the (n+3) x (m+3) identity with the columns of cells not under the parcel removed."""
    keep = [i for i in range(n) if under[i]] + [n, n + 1, n + 2]
    return np.eye(n + 3)[:, keep]


def paper_normal_forces(cells, under, com, weight: float) -> np.ndarray:
    """Eq. 19: ``N = C M (M^T A M)^-1 (M^T W_x) X_c + C M (M^T A M)^-1 M^T W_c`` for all n cells (zeros where the
    parcel does not rest). ``under`` is a boolean mask of the cells under the parcel."""
    P = np.asarray(cells, dtype=float)
    n = len(P)
    A, Wx, Wc = paper_system(P)
    M = mask_matrix(n, under)
    C = np.eye(n, n + 3)  # eq. 12, the clip matrix
    inv = np.linalg.inv(M.T @ A @ M)
    return C @ M @ inv @ (M.T @ (weight * Wx)) @ np.asarray(com, dtype=float) + C @ M @ inv @ M.T @ (weight * Wc)
