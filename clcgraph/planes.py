"""Plane fits shared by the LIDAR board segmentation and the ground plane: least squares, and a
seeded RANSAC.

SYNOPSIS
    n, d, rms = fit_plane(points)              # n . x = d, unit n; RMS distance
    inliers = ransac_plane(points, tol=0.05)   # (N,) mask, refined by least squares

RANSAC is numpy with a fixed seed rather than Open3D's segment_plane: Open3D runs its
iterations in threads and returns different planes for the same points from run to run,
which made segmentation and ground results irreproducible.
"""

from __future__ import annotations

import numpy as np


def fit_plane(points: np.ndarray) -> tuple[np.ndarray, float, float]:
    """Least-squares plane: (unit normal n, offset d with n.x = d, RMS distance)."""
    c = points.mean(axis=0)
    _, s, vt = np.linalg.svd(points - c, full_matrices=False)
    n = vt[2]
    return n, float(n @ c), float(s[2] / np.sqrt(len(points)))


def ransac_plane(points: np.ndarray, tol: float, *, iterations: int = 256, max_scored: int = 20000,
                 seed: int = 0) -> np.ndarray:
    """(N,) inlier mask of the plane with the most points within ``tol``, refined by least squares.

    Hypotheses are scored on at most ``max_scored`` evenly spaced points.
    """
    rng = np.random.default_rng(seed)
    tri = points[rng.integers(0, len(points), (iterations, 3))]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    norm = np.linalg.norm(n, axis=1)
    ok = norm > 1e-9
    n, tri = n[ok] / norm[ok, None], tri[ok]
    if not len(n):
        return np.zeros(len(points), bool)
    d = np.einsum("ij,ij->i", n, tri[:, 0])
    scored = points[np.linspace(0, len(points) - 1, min(len(points), max_scored)).astype(np.int64)]
    counts = np.empty(len(n), np.int64)
    for k in range(0, len(n), 128):  # in chunks: 20k x 1000 would be 160 MB; in place, the same values
        x = scored @ n[k:k + 128].T
        x -= d[k:k + 128]
        np.abs(x, out=x)
        counts[k:k + 128] = np.count_nonzero(x <= tol, axis=0)
    best = int(np.argmax(counts))
    inl = np.abs(points @ n[best] - d[best]) <= tol
    n2, d2, _ = fit_plane(points[inl])
    return np.abs(points @ n2 - d2) <= tol
