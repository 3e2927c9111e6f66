"""A mrcal splined model fitted to a Kannala-Brandt (OpenCV "fisheye") camera.

SYNOPSIS
    from clcgraph.fisheye_fit import fit_splined
    fit = fit_splined(K, D, (1920, 1208))
    fit.lensmodel, fit.intrinsics        # mrcal LENSMODEL_SPLINED_STEREOGRAPHIC_...
    fit.rms_px, fit.max_px               # fit error over the image (within MAX_THETA_DEG of the axis)

mrcal has no Kannala-Brandt model and LENSMODEL_OPENCV8 cannot follow that projection to
the image corners of a wide fisheye (0.65 px off on the ACFR camera). A splined
stereographic model can: it is fitted by least squares to the observation vectors of a
dense grid of pixels covering the whole image (unprojected exactly through the fisheye
model), with a light ridge on the spline controls so the knots outside the image stay put.
The fit's error is measured within MAX_THETA_DEG of the axis: a circular fisheye's corners
beyond it are dark or look backwards (no board is seen there), and the spline is looser there.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

MAX_THETA_DEG = 100.0


def fisheye_project(p: np.ndarray, K: np.ndarray, D: np.ndarray) -> np.ndarray:
    """(N,3) camera-frame points -> (N,2) pixels through OpenCV's fisheye model
    (theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8), no skew)."""
    p = np.asarray(p, float)
    rxy = np.hypot(p[:, 0], p[:, 1])
    th = np.arctan2(rxy, p[:, 2])
    t2 = th * th
    thd = th * (1 + t2 * (D[0] + t2 * (D[1] + t2 * (D[2] + t2 * D[3]))))
    s = np.where(rxy > 1e-12, thd / np.maximum(rxy, 1e-12), 1.0 / np.maximum(p[:, 2], 1e-12))
    return np.c_[K[0, 0] * s * p[:, 0] + K[0, 2], K[1, 1] * s * p[:, 1] + K[1, 2]]


def fisheye_unproject(q: np.ndarray, K: np.ndarray, D: np.ndarray) -> np.ndarray:
    """(N,2) pixels -> (N,3) unit observation vectors (Newton on theta_d(theta))."""
    q = np.asarray(q, float)
    x = (q[:, 0] - K[0, 2]) / K[0, 0]
    y = (q[:, 1] - K[1, 2]) / K[1, 1]
    thd = np.hypot(x, y)
    th = thd.copy()
    for _ in range(30):
        t2 = th * th
        f = th * (1 + t2 * (D[0] + t2 * (D[1] + t2 * (D[2] + t2 * D[3])))) - thd
        df = 1 + t2 * (3 * D[0] + t2 * (5 * D[1] + t2 * (7 * D[2] + t2 * 9 * D[3])))
        th = th - f / df
    phi = np.arctan2(y, x)
    v = np.c_[np.sin(th) * np.cos(phi), np.sin(th) * np.sin(phi), np.cos(th)]
    return v


@dataclass(frozen=True)
class SplinedFit:
    lensmodel: str
    intrinsics: np.ndarray
    rms_px: float  # over the fit grid
    max_px: float
    check_rms_px: float  # over a finer grid offset from the fit grid
    check_max_px: float


def _grid(imagersize, step: float, offset: float = 0.0) -> np.ndarray:
    w, h = imagersize
    u = np.arange(offset, w - 1 + 1e-9, step)
    v = np.arange(offset, h - 1 + 1e-9, step)
    return np.stack(np.meshgrid(np.r_[u, w - 1], np.r_[v, h - 1]), -1).reshape(-1, 2)


def _seen(q: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The pixels ``q`` and their observation vectors ``v`` within MAX_THETA_DEG of the axis."""
    ok = v[:, 2] >= np.cos(np.radians(MAX_THETA_DEG))
    return q[ok], v[ok]


def fit_splined(K, D, imagersize, *, Nx: int = 30, Ny: int = 20, fov_margin: float = 1.1,
                step_px: float = 16.0, ridge: float = 1e-3) -> SplinedFit:
    """Least-squares LENSMODEL_SPLINED_STEREOGRAPHIC (order 3, ``Nx`` x ``Ny`` knots) fitted to
    the fisheye model (K (3,3), D (4,)) over every ``step_px`` pixels of the image."""
    from .cameras import num_intrinsics, project  # the mrcal wrapper

    K = np.asarray(K, float)
    D = np.asarray(D, float)
    q = _grid(imagersize, step_px)
    v = fisheye_unproject(q, K, D)
    # the knots must span the image in the stereographic plane, u = 2 tan(theta/2) (x, y)
    th = np.arccos(np.clip(v[:, 2], -1, 1))
    ux = np.abs(2 * np.tan(th / 2) * v[:, 0] / np.maximum(np.hypot(v[:, 0], v[:, 1]), 1e-12))
    fov_x_deg = int(np.ceil(np.degrees(4 * np.arctan(fov_margin * ux.max() / 2))))
    lensmodel = f"LENSMODEL_SPLINED_STEREOGRAPHIC_order=3_Nx={Nx}_Ny={Ny}_fov_x_deg={fov_x_deg}"
    n = num_intrinsics(lensmodel)
    x = np.zeros(n)
    x[:4] = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    # Gauss-Newton on the normal equations: q is nearly linear in the spline controls, a
    # few steps converge
    reg = ridge * np.r_[np.zeros(4), np.ones(n - 4)]
    for _ in range(5):
        qp, _, dq_di = project(v, lensmodel, x, get_gradients=True)
        r = (qp - q).reshape(-1)
        J = dq_di.reshape(-1, n)
        dx = np.linalg.solve(J.T @ J + np.diag(reg), -(J.T @ r + reg * x))
        x += dx
        if np.abs(dx).max() < 1e-9:
            break
    q, v = _seen(q, v)
    err = np.linalg.norm(project(v, lensmodel, x) - q, axis=1)
    qc = _grid(imagersize, step_px / 2.3, offset=step_px / 4)
    qc, vc = _seen(qc, fisheye_unproject(qc, K, D))
    errc = np.linalg.norm(project(vc, lensmodel, x) - qc, axis=1)
    return SplinedFit(lensmodel, x, float(np.sqrt(np.mean(err**2))), float(err.max()),
                      float(np.sqrt(np.mean(errc**2))), float(errc.max()))
