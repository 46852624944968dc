"""
Trifocal tensor (Kitt et al., eq. 4) and point-line-point transfer (eq. 5).

Index conventions follow Hartley & Zisserman: ``T[i, j, k] = T_i^{jk}`` for cameras A, B, C with
projection matrices ``P_A, P_B, P_C`` (3x4, pixels). A correspondence ``x_A <-> x_B`` is
transferred into image C through a line ``l_B`` through ``x_B``:
``x_C^k = x_A^i l_{B,j} T_i^{jk}`` (eq. 5). The line is chosen perpendicular to the epipolar line
of ``x_A`` in image B (H&Z Algorithm 15.1), which is the numerically stable choice.

Because eq. 4 is a determinant that is linear in the row ``c_r`` of ``P_C``, the tensor factors
as ``T_i^{qr} = G[i, q, :] . c_r`` with a 3x3x4 array ``G`` that depends on ``P_A`` and ``P_B``
only (:func:`tensor_basis`). Contracting eq. 5 with ``G`` first gives, per correspondence, a
4-vector ``X`` such that ``x_C = P_C X`` for ANY third camera (:func:`transfer_basis`). The
estimator uses this: the previous stereo pair fixes ``X`` once per frame, and every state
hypothesis then costs one 3x4 product per point. Tests check that it equals eq. 4 + eq. 5.
"""

from __future__ import annotations

import numpy as np


def _rows_without(P: np.ndarray, i: int) -> np.ndarray:
    return np.delete(P, i, axis=-2)


def trifocal_tensor(P_A: np.ndarray, P_B: np.ndarray, P_C: np.ndarray) -> np.ndarray:
    """
    Return the trifocal tensor of three cameras by eq. 4 (determinants).

    ``T_i^{qr} = (-1)^(i+1) det([~a_i; b_q; c_r])`` with ``~a_i`` = P_A without row i.

    Parameters
    ----------
    P_A : np.ndarray
        (..., 3, 4) float64 projection matrix of camera A (pixels), broadcast over leading axes.
    P_B : np.ndarray
        (..., 3, 4) float64 projection matrix of camera B.
    P_C : np.ndarray
        (..., 3, 4) float64 projection matrix of camera C.

    Returns
    -------
    (..., 3, 3, 3) float64 tensor ``T[..., i, q, r]``.

    """
    P_A, P_B, P_C = np.broadcast_arrays(*(np.asarray(P, np.float64) for P in (P_A, P_B, P_C)))
    lead = P_A.shape[:-2]
    T = np.empty(lead + (3, 3, 3))
    for i in range(3):
        a = _rows_without(P_A, i)  # (..., 2, 4)
        for q in range(3):
            for r in range(3):
                M = np.concatenate([a, P_B[..., q:q + 1, :], P_C[..., r:r + 1, :]], axis=-2)
                T[..., i, q, r] = (-1) ** i * np.linalg.det(M)
    return T


def tensor_basis(P_A: np.ndarray, P_B: np.ndarray) -> np.ndarray:
    """
    Return ``G`` (3, 3, 4) with ``T_i^{qr} = G[i, q] . P_C[r]`` for every third camera.

    ``G[i, q]`` is ``(-1)^(i+1)`` times the cofactor vector of the last row of the 4x4 matrix
    ``[~a_i; b_q; c]``, i.e. eq. 4 expanded along the row of ``P_C``.
    """
    P_A = np.asarray(P_A, np.float64)
    P_B = np.asarray(P_B, np.float64)
    G = np.empty((3, 3, 4))
    for i in range(3):
        a = _rows_without(P_A, i)
        for q in range(3):
            M = np.vstack([a, P_B[q]])  # (3, 4)
            for k in range(4):
                G[i, q, k] = (-1) ** i * (-1) ** (3 + k) * np.linalg.det(np.delete(M, k, axis=1))
    return G


def fundamental_from_projections(P_A: np.ndarray, P_B: np.ndarray) -> np.ndarray:
    """Return F (3, 3) with ``x_B^T F x_A = 0`` from two projection matrices (pixels)."""
    P_A = np.asarray(P_A, np.float64)
    P_B = np.asarray(P_B, np.float64)
    C = np.linalg.svd(P_A)[2][-1]  # camera centre of A (homogeneous)
    e = P_B @ C
    ex = np.array([[0, -e[2], e[1]], [e[2], 0, -e[0]], [-e[1], e[0], 0]])
    return ex @ P_B @ np.linalg.pinv(P_A)


def perpendicular_lines(F: np.ndarray, x_A: np.ndarray, x_B: np.ndarray) -> np.ndarray:
    """
    Lines through ``x_B`` perpendicular to the epipolar lines ``F x_A`` (H&Z Alg. 15.1).

    Parameters
    ----------
    F : np.ndarray
        (3, 3) fundamental matrix with ``x_B^T F x_A = 0``.
    x_A : np.ndarray
        (N, 2) float64 pixel coordinates in image A.
    x_B : np.ndarray
        (N, 2) float64 pixel coordinates of the matches in image B.

    Returns
    -------
    (N, 3) float64 homogeneous lines in image B.

    """
    return perpendicular_lines_t(F, np.asarray(x_A, np.float64).T,
                                 np.asarray(x_B, np.float64).T).T


def perpendicular_lines_t(F: np.ndarray, x_A: np.ndarray, x_B: np.ndarray) -> np.ndarray:
    """:func:`perpendicular_lines` on transposed arrays: x_A, x_B (2, N) -> lines (3, N)."""
    l1 = F[0, 0] * x_A[0] + F[0, 1] * x_A[1] + F[0, 2]  # epipolar lines F x_A in B
    l2 = F[1, 0] * x_A[0] + F[1, 1] * x_A[1] + F[1, 2]
    out = np.empty((3, x_A.shape[1]))
    out[0] = l2
    np.negative(l1, out=out[1])
    out[2] = x_B[1] * l1 - x_B[0] * l2
    return out


def transfer_points(T: np.ndarray, x_A: np.ndarray, l_B: np.ndarray) -> np.ndarray:
    """
    Point-line-point transfer, eq. 5: ``x_C^k = x_A^i l_{B,j} T_i^{jk}``.

    Parameters
    ----------
    T : np.ndarray
        (..., 3, 3, 3) trifocal tensor(s).
    x_A : np.ndarray
        (N, 2) pixel coordinates in image A.
    l_B : np.ndarray
        (N, 3) lines through the matching points in image B.

    Returns
    -------
    (..., N, 2) float64 pixel coordinates in image C.

    """
    xh = np.hstack([np.asarray(x_A, np.float64), np.ones((len(x_A), 1))])
    xc = np.einsum('ni,nj,...ijk->...nk', xh, l_B, T)
    return xc[..., :2] / xc[..., 2:3]


def transfer_basis(G: np.ndarray, x_A: np.ndarray, l_B: np.ndarray) -> np.ndarray:
    """
    Contract eq. 5 with the tensor basis: ``X_n = x_A^i l_{B,j} G[i, j]``.

    Parameters
    ----------
    G : np.ndarray
        (3, 3, 4) from :func:`tensor_basis`.
    x_A : np.ndarray
        (N, 2) pixel coordinates in image A.
    l_B : np.ndarray
        (N, 3) lines in image B.

    Returns
    -------
    (N, 4) float64 homogeneous vectors with ``x_C ~ P_C @ X_n`` for any camera C; geometrically
    the intersection of the ray of ``x_A`` with the plane back-projected from ``l_B``, in the
    frame in which the projection matrices are expressed.

    """
    return transfer_basis_t(G, np.asarray(x_A, np.float64).T, np.asarray(l_B, np.float64).T).T


def transfer_basis_t(G: np.ndarray, x_A: np.ndarray, l_B: np.ndarray,
                     normalize: bool = True) -> np.ndarray:
    """
    :func:`transfer_basis` on transposed arrays: x_A (2, N), l_B (3, N) -> X (4, N).

    ``normalize=False`` leaves out the unit norm and the sign (X is homogeneous).
    """
    # G[i]^T l_B for i = 0, 1, 2 stacked (12, N), then weighted by x_A^i (x_A^2 = 1).
    lg = np.swapaxes(G, 1, 2).reshape(12, 3) @ l_B
    X = x_A[0] * lg[0:4]
    X += x_A[1] * lg[4:8]
    X += lg[8:12]
    if not normalize:
        return X
    # Fix the arbitrary sign and scale so that the homogeneous part is positive when finite.
    norm = np.sqrt((X * X).sum(axis=0))
    X /= np.where(norm > 0, norm, 1.0)
    X *= np.where(X[3] < 0, -1.0, 1.0)
    return X
