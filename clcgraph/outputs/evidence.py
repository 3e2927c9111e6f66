"""What the report shows besides the Result, and the checks computed from it.

The Result says the fit is self-consistent; these say it is right: the LIDARs' board points
moved into each camera with the solved extrinsics must fall on the board the camera itself
found (its detected corners), within the calibration's uncertainty; the corners must cover
the image. Plain numpy on Result / Problem data; nothing here reads a bag (the API fills
``ReportInputs`` with the few decoded snapshots the report draws).

SYNOPSIS
    rows = lidar_board_in_images(result)            # one dict per (camera, LIDAR, snapshot)
    worst = max(r["spill_sigma"] for r in rows)      # spill past the board's edge in sigmas: ~3 or less when right
    cov = image_coverage([o.corners_px for o in obs], (w, h))   # hull share, empty thirds, warning
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Mapping

import numpy as np

from .. import cameras
from ..geometry import compose_rt, elevation, invert_rt, transform
from ..types import Result, Sensor, Snapshot

log = logging.getLogger(__name__)

# Image coverage rule: warn when the convex hull of every corner seen covers less than this share of
# the image, or when a third of the image (rows or columns) holds no corner at all.
MIN_HULL_FRACTION = 0.30
# The spill of a view is how far past the board's outline its third-farthest LIDAR point lies, not the farthest:
# one or two returns at a board's edge hit its rim or mix with the background (a beam's footprint), on real
# boards and in our simulator (a 1 cm thick box) alike, while a wrong calibration pushes a row of ring ends (one
# per ring crossing that edge) past the outline.
_SPILL_RANK = 3
# Monte-Carlo samples of the extrinsics to propagate their covariance to pixels (seeded: same bytes out).
_SAMPLES = 32


@dataclass(frozen=True, eq=False)
class ReportInputs:
    """The run's record and the data the report draws that the Result does not carry."""

    bags: tuple[tuple[str, int], ...] = ()  # (path, size in bytes)
    models: tuple[tuple[str, str], ...] = ()  # (camera topic, .cameramodel path)
    command: str | None = None  # the command line, or the API call
    config_yaml: str | None = None  # the effective settings
    snapshots: Mapping[int, Snapshot] = field(default_factory=dict)  # decoded images and scans, by snapshot index
    sources: Mapping[int, str] = field(default_factory=dict)  # snapshot index -> bag (and period)
    rt_nominal: Mapping[int, np.ndarray] = field(default_factory=dict)  # sensor -> nominal rt_lidar0_sensor
    nominal_source: str = ""  # where rt_nominal came from


# ---------------------------------------------------------------- the board as the camera saw it


def _normalized(q: np.ndarray, cam: Sensor) -> np.ndarray:
    """Pixels (N,2) -> pinhole coordinates (x/z, y/z) (N,2) through the camera's lens model."""
    v = cameras.unproject(np.asarray(q, float), cam.lensmodel, cam.intrinsics, normalize=False)
    return v[:, :2] / v[:, 2:3]


def _px(xy: np.ndarray, cam: Sensor) -> np.ndarray:
    return cameras.project(np.c_[xy, np.ones(len(xy))], cam.lensmodel, cam.intrinsics)


def board_homography(corners_px: np.ndarray, board, cam: Sensor) -> np.ndarray:
    """(3,3) H: board-plane (x, y, 1) -> pinhole coordinates of the camera, fitted (normalized DLT) to
    the detected corners. Exact for a plane in any lens model (the lens is undone by unprojecting), so the
    board's outline in the image comes from the camera's own detections, not from any extrinsics."""
    q = np.asarray(corners_px, float)
    ok = np.all(np.isfinite(q), axis=1)
    src, dst = board.corners()[ok, :2], _normalized(q[ok], cam)

    def conditioner(p):
        c = p.mean(0)
        s = np.sqrt(2) / np.mean(np.linalg.norm(p - c, axis=1))
        return np.array([[s, 0, -s * c[0]], [0, s, -s * c[1]], [0, 0, 1]])

    Ts, Td = conditioner(src), conditioner(dst)
    a = (Ts @ np.c_[src, np.ones(len(src))].T).T
    b = (Td @ np.c_[dst, np.ones(len(dst))].T).T
    z = np.zeros_like(a)
    A = np.r_[np.c_[a, z, -b[:, :1] * a], np.c_[z, a, -b[:, 1:2] * a]]
    H = np.linalg.svd(A)[2][-1].reshape(3, 3)
    H = np.linalg.inv(Td) @ H @ Ts
    return H / H[2, 2]


def _apply(H: np.ndarray, xy: np.ndarray) -> np.ndarray:
    p = np.c_[xy, np.ones(len(xy))] @ H.T
    return p[:, :2] / p[:, 2:3]


def board_outline_px(H: np.ndarray, board, cam: Sensor, *, n_per_edge: int = 25) -> np.ndarray:
    """(4*n_per_edge+1, 2) the physical board's edge in the image (densified: the lens bends it)."""
    xmin, xmax, ymin, ymax = board.extent()
    c = np.array([[xmin, ymin], [xmax, ymin], [xmax, ymax], [xmin, ymax], [xmin, ymin]])
    s = np.linspace(0, 1, n_per_edge, endpoint=False)[:, None]
    edge = np.concatenate([c[k] + s * (c[k + 1] - c[k]) for k in range(4)] + [c[:1]])
    return _px(_apply(H, edge), cam)


def _edge_excess_px(P: np.ndarray, H: np.ndarray, board, cam: Sensor) -> np.ndarray:
    """(N,) how far each camera-frame point (N,3) lies outside the board's outline in the image (0 inside), in px."""
    b = _apply(np.linalg.inv(H), P[:, :2] / P[:, 2:3])
    xmin, xmax, ymin, ymax = board.extent()
    bc = np.c_[np.clip(b[:, 0], xmin, xmax), np.clip(b[:, 1], ymin, ymax)]
    out = np.any(b != bc, axis=1)
    d = np.zeros(len(P))
    if out.any():
        d[out] = np.linalg.norm(_px(_apply(H, b[out]), cam) - _px(_apply(H, bc[out]), cam), axis=1)
    return d


def _rt_samples(result: Result, n: int) -> np.ndarray:
    """(n, Nsensors, 6) rt_lidar0_sensor drawn from the solved joint covariance (reference fixed)."""
    rt = np.asarray(result.rt_lidar0_sensor, float)
    var = result.variable_sensors()
    cov = np.asarray(result.covariance_rt, float)
    out = np.repeat(rt[None], n, axis=0)
    if var and cov.size:
        w, V = np.linalg.eigh(0.5 * (cov + cov.T))
        L = V * np.sqrt(np.clip(w, 0, None))
        d = np.random.default_rng(0).normal(size=(n, len(w))) @ L.T
        out[:, var] = rt[var][None] + d.reshape(n, len(var), 6)
    return out


def _T_cam_lidar(rt_cam: np.ndarray, rt_lidar: np.ndarray):
    """(R (n,3,3), t (n,3)) of T_cam_lidar for n samples of rt_lidar0_cam and rt_lidar0_lidar."""
    from scipy.spatial.transform import Rotation

    Rc, Rl = Rotation.from_rotvec(rt_cam[:, :3]).as_matrix(), Rotation.from_rotvec(rt_lidar[:, :3]).as_matrix()
    R = np.einsum("sji,sjk->sik", Rc, Rl)
    t = np.einsum("sji,sj->si", Rc, rt_lidar[:, 3:] - rt_cam[:, 3:])
    return R, t


def lidar_board_in_images(result: Result, *, rt_lidar0_sensor=None) -> list[dict]:
    """Per (camera, LIDAR, snapshot) that both saw the board: the LIDAR's board points moved into the
    camera (with ``rt_lidar0_sensor``, default the solved poses) and projected, against the board outline
    fitted to the camera's detected corners.

    Each row: camera, lidar, snapshot (ints), n_points, n_outside (points beyond the outline), worst_px
    (the largest distance beyond the outline), spill_px (the third-largest: see _SPILL_RANK), sigma_px
    (median 1-sigma of a point's pixel: the solved extrinsics' covariance propagated by sampling, the
    LIDAR's range noise and the camera's noise, which moves the fitted outline), spill_sigma (the
    third-largest of each point's distance beyond the outline over its own sigma). Right extrinsics leave
    spill_sigma at ~3 or less; points sampled along rings reach the board's edges, so an error of a few
    sigma pushes a row of them out. With ``rt_lidar0_sensor`` given, its sigmas leave out the extrinsics'.
    """
    p = result.problem
    rt = np.asarray(result.rt_lidar0_sensor if rt_lidar0_sensor is None else rt_lidar0_sensor, float)
    per = result.noise.get("per_sensor") or {}
    samples = _rt_samples(result, _SAMPLES) if rt_lidar0_sensor is None else None
    lidar_by_snap: dict[int, list] = {}
    for o in p.lidar_observations:
        lidar_by_snap.setdefault(o.snapshot, []).append(o)
    pair_samples: dict = {}
    rows = []
    for oc in p.camera_observations:
        cam = p.sensors[oc.sensor]
        H = None
        for ol in lidar_by_snap.get(oc.snapshot, ()):
            if H is None:
                H = board_homography(oc.corners_px, p.board, cam)
            P = transform(compose_rt(invert_rt(rt[oc.sensor]), rt[ol.sensor]), np.asarray(ol.points, float))
            front = P[:, 2] > 0.1
            if front.sum() < 3:
                continue
            P = P[front]
            q = cameras.project(P, cam.lensmodel, cam.intrinsics)
            excess = _edge_excess_px(P, H, p.board, cam)
            var = np.zeros(len(P))
            if samples is not None:  # spread of each point's pixel over the extrinsics' distribution
                key = (oc.sensor, ol.sensor)
                if key not in pair_samples:
                    pair_samples[key] = _T_cam_lidar(samples[:, oc.sensor], samples[:, ol.sensor])
                Rs, ts = pair_samples[key]
                Ps = np.asarray(ol.points, float)[front] @ Rs.transpose(0, 2, 1) + ts[:, None]
                qs = cameras.project(Ps.reshape(-1, 3), cam.lensmodel, cam.intrinsics).reshape(len(samples), -1, 2)
                var += np.sum(np.var(qs, axis=0), axis=1)
            sig_l = float(per.get(ol.sensor, result.noise.get("lidar_m", 0.0)) or 0.0)
            if sig_l > 0:  # range noise moves a point along the LIDAR's ray, which the camera sees sideways
                o_l = transform(compose_rt(invert_rt(rt[oc.sensor]), rt[ol.sensor]), np.zeros((1, 3)))[0]
                ray = P - o_l
                P2 = P + ray / np.linalg.norm(ray, axis=1, keepdims=True) * sig_l
                var += np.sum((cameras.project(P2, cam.lensmodel, cam.intrinsics) - q) ** 2, axis=1)
            var += float(per.get(oc.sensor, result.noise.get("camera_px", 0.0)) or 0.0) ** 2
            sigma = np.sqrt(np.maximum(var, 1e-12))
            k = min(len(P), _SPILL_RANK)
            rows.append({"camera": oc.sensor, "lidar": ol.sensor, "snapshot": oc.snapshot, "n_points": int(len(P)),
                         "n_outside": int(np.sum(excess > 0)), "worst_px": float(excess.max()),
                         "spill_px": float(np.sort(excess)[-k]), "sigma_px": float(np.median(sigma)),
                         "spill_sigma": float(np.sort(excess / sigma)[-k])})
    return rows


# ---------------------------------------------------------------- image coverage


def image_coverage(corners: list, imagersize) -> dict:
    """Where a camera's corners fell: {hull_fraction, empty_thirds, rows_px, warning}.

    ``corners``: (N_k,2) arrays of detected corners; ``imagersize``: (width, height). The warning
    (None when coverage is fine) says the rule it broke: the convex hull of all corners covers less than
    MIN_HULL_FRACTION of the image, or a third of the image (top/middle/bottom rows, left/centre/right
    columns) has no corner. Corners only in one band fit the lens there and constrain the pose weakly.
    """
    from scipy.spatial import ConvexHull, QhullError

    w, h = imagersize
    q = np.concatenate([np.asarray(c, float).reshape(-1, 2) for c in corners]) if corners else np.zeros((0, 2))
    q = q[np.all(np.isfinite(q), axis=1)]
    if len(q) < 3:
        return {"hull_fraction": 0.0, "empty_thirds": [], "rows_px": None,
                "warning": "no corners detected: nothing constrains this camera"}
    try:
        hull = ConvexHull(q).volume / float(w * h)  # a 2-D hull's volume is its area
    except QhullError:
        hull = 0.0
    empty = []
    for axis, size, names in ((1, h, ("top", "middle", "bottom")), (0, w, ("left", "centre", "right"))):
        k = np.clip((q[:, axis] / size * 3).astype(int), 0, 2)
        empty += [f"{names[i]} third ({'rows' if axis else 'columns'} {i * size // 3}-{(i + 1) * size // 3})"
                  for i in range(3) if not np.any(k == i)]
    why = []
    if hull < MIN_HULL_FRACTION:
        why.append(f"the corners' convex hull covers {100 * hull:.0f} % of the image (< {100 * MIN_HULL_FRACTION:.0f} %)")
    if empty:
        why.append("no corner in the " + ", ".join(empty))
    rows = (float(q[:, 1].min()), float(q[:, 1].max()))
    warning = None if not why else (f"corners only in rows {rows[0]:.0f}-{rows[1]:.0f} and columns "
                                    f"{q[:, 0].min():.0f}-{q[:, 0].max():.0f} of {w}x{h}: " + "; ".join(why)
                                    + ". Capture boards near the empty parts of the image.")
    return {"hull_fraction": float(hull), "empty_thirds": empty, "rows_px": rows, "warning": warning}


def moved_from_nominal(result: Result, rt_nominal: Mapping[int, np.ndarray]) -> list[dict]:
    """Per sensor with a nominal pose: how far the solution is from it (angle, distance, and in sigmas)."""
    from ..geometry import T_from_rt, pose_difference, pose_stdevs

    rows = []
    for i, s in enumerate(result.problem.sensors):
        if i not in rt_nominal or i == result.problem.reference:
            continue
        rt = np.asarray(result.rt_lidar0_sensor[i], float)
        rot, dist = pose_difference(T_from_rt(np.asarray(rt_nominal[i], float)), T_from_rt(rt))
        sd_rot, sd_pos = pose_stdevs(rt, result.covariance_block(i))
        rows.append({"sensor": i, "topic": s.topic, "rotation_deg": float(np.degrees(rot)),
                     "translation_mm": float(dist * 1e3), "sigma_deg": float(np.degrees(np.linalg.norm(sd_rot))),
                     "sigma_mm": float(np.linalg.norm(sd_pos) * 1e3)})
    return rows


# ---------------------------------------------------------------- residuals next to where they were measured


def _chunks(obs, sens: np.ndarray, snap: np.ndarray, length) -> list:
    """[(observation, slice)] of the flat residual arrays: they hold the observations in order, each
    one's residuals together, skipping observations the solve left out (no residuals)."""
    out, at = [], 0
    for o in obs:
        n = length(o)
        if at + n <= len(sens) and n and sens[at] == o.sensor and snap[at] == o.snapshot \
                and sens[at + n - 1] == o.sensor and snap[at + n - 1] == o.snapshot:
            out.append((o, slice(at, at + n)))
            at += n
    return out


def camera_residual_vectors(result: Result) -> dict[int, dict]:
    """camera index -> {"corners": (M,2), "residuals": (M,2) observed - predicted px, "outlier": (M,)}."""
    r = result.residuals
    x = np.asarray(r.get("camera_px", []), float)
    if not len(x):
        return {}
    sens, snap = np.asarray(r["camera_sensor"]), np.asarray(r["camera_snapshot"])
    bad = np.asarray(r.get("camera_outlier", np.zeros(len(x), bool)), bool)
    ok = lambda o: np.all(np.isfinite(o.corners_px), axis=1)  # noqa: E731
    out: dict[int, dict] = {}
    for o, sl in _chunks(result.problem.camera_observations, sens, snap, lambda o: 2 * int(ok(o).sum())):
        d = out.setdefault(o.sensor, {"corners": [], "residuals": [], "outlier": []})
        d["corners"].append(np.asarray(o.corners_px, float)[ok(o)])
        d["residuals"].append(x[sl].reshape(-1, 2))
        d["outlier"].append(bad[sl][::2])
    return {i: {k: np.concatenate(v) for k, v in d.items()} for i, d in out.items()}


def lidar_residual_geometry(result: Result) -> dict[int, dict]:
    """LIDAR index -> {"residual": (N,) m, "range": (N,) m, "elevation_deg": (N,), "outlier": (N,)}:
    each residual next to its point's range and elevation angle (a rotating LIDAR's ring)."""
    r = result.residuals
    x = np.asarray(r.get("lidar_m", []), float)
    if not len(x):
        return {}
    sens, snap = np.asarray(r["lidar_sensor"]), np.asarray(r["lidar_snapshot"])
    bad = np.asarray(r.get("lidar_outlier", np.zeros(len(x), bool)), bool)
    out: dict[int, dict] = {}
    for o, sl in _chunks(result.problem.lidar_observations, sens, snap, lambda o: len(o.points)):
        p = np.asarray(o.points, float)
        d = out.setdefault(o.sensor, {"residual": [], "range": [], "elevation_deg": [], "outlier": []})
        d["residual"].append(x[sl])
        d["range"].append(np.linalg.norm(p, axis=1))
        d["elevation_deg"].append(np.degrees(elevation(p)))
        d["outlier"].append(bad[sl])
    return {i: {k: np.concatenate(v) for k, v in d.items()} for i, d in out.items()}
