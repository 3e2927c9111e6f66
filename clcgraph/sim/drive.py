"""Driving capture plan for targetless calibration: a street scene, a slow drive, motion-distorted scans.

SYNOPSIS
    plan = DrivePlan.small()                 # test-sized; DrivePlan() is the 60 s drive
    drive = simulate_drive(plan, seed=0)
    drive.scans["/top/points"][0].time_s     # per-point time relative to the stamp
    drive.T_base_lidar["/side/points"]       # truth (4,4)
    write_drive_bag(drive, "drive.bag")      # bag + /tf_static with the perturbed guess

Each column of a scan is ray-cast (sim/lidar.py, organised Ouster-style clouds) from the
vehicle pose at that column's time, so the scans carry the same smear as a real driver's
output. The body rolls and pitches on its suspension (a sum of sines) about the base_link
frame, which stays on the ground.
Frames: world (z up, ground z = 0), base_link (on the ground below the body centre,
x forward), LIDARs front-left-up. ``scan.points`` are in the LIDAR frame at the
column's time; ``scan.time_s`` is the column time minus the stamp (scan start).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .. import geometry as geo
from ..types import LidarScan


@dataclass(frozen=True)
class LidarSpec:
    """A simulated rotating LIDAR (elevations in degrees, uniform between min and max)."""

    topic: str
    frame: str
    rings: int
    columns: int
    elev_min_deg: float
    elev_max_deg: float
    rt_base_lidar: tuple  # (6,) truth
    time_offset_s: float = 0.0  # stamp offset vs the 10 Hz grid (unsynchronised)
    range_noise_m: float = 0.005
    max_range_m: float = 80.0


def _rt(rpy_deg, xyz):
    return tuple(geo.rt_from_T(geo.T_from_xyz_rpy(xyz, rpy_deg)))


@dataclass(frozen=True)
class DrivePlan:
    """What to simulate: duration, speed, yaw rate, suspension motion, scene and LIDARs."""

    duration_s: float = 60.0
    speed_mps: float = 2.0 / 3.6
    yaw_rate_amp_dps: float = 3.0  # slow weaving: the yaw rate is a sine of this amplitude
    yaw_period_s: float = 20.0
    body_tilt_deg: float = 0.5  # suspension roll / pitch amplitude
    rate_hz: float = 10.0
    scene: str = "street"  # "street" | "flat"
    stopped: bool = False  # vehicle never moves
    lidars: tuple = field(default_factory=lambda: (
        LidarSpec("/top/points", "top_lidar", 64, 1024, -25.0, 15.0, _rt([0, 0, 0], [0.2, 0.0, 1.9]), 0.0),
        LidarSpec("/side/points", "side_lidar", 16, 1024, -15.0, 15.0, _rt([25.0, 10.0, 80.0], [0.6, 0.85, 1.3]), 0.037),
    ))
    # tf_static guess: each non-reference LIDAR off by this rotation / translation
    guess_rot_deg: float = 2.0
    guess_trans_m: float = 0.2

    @classmethod
    def small(cls, **kw) -> "DrivePlan":
        """Test-sized: 32/16 rings, 512 columns, 25 s."""
        base = cls()
        top, side = base.lidars
        lid = (LidarSpec(top.topic, top.frame, 32, 512, -25.0, 15.0, top.rt_base_lidar, 0.0),
               LidarSpec(side.topic, side.frame, 16, 512, -15.0, 15.0, side.rt_base_lidar, 0.037))
        d = dict(duration_s=25.0, lidars=lid)
        d.update(kw)
        return cls(**d)


@dataclass
class Drive:
    """Simulated drive: scans per topic, truth, and the perturbed tf_static guess."""

    plan: DrivePlan
    scans: dict  # topic -> list[LidarScan]
    T_base_lidar: dict  # topic -> (4,4) truth
    T_base_lidar_guess: dict  # topic -> (4,4) what /tf_static says
    frames: dict  # topic -> frame_id
    traj_t: np.ndarray  # (K,) s since start
    traj_T_world_base: np.ndarray  # (K,4,4)
    t0_ns: int = 1_700_000_000_000_000_000

    def T_lidar0_lidar(self, topic: str, ref: str) -> np.ndarray:
        return np.linalg.inv(self.T_base_lidar[ref]) @ self.T_base_lidar[topic]

    def truth_dict(self) -> dict:
        ref = self.plan.lidars[0].topic
        return {
            "reference": ref,
            "sensors": [{"topic": t, "frame": self.frames[t],
                         "T_base_link_sensor": self.T_base_lidar[t].tolist(),
                         "T_lidar0_sensor": self.T_lidar0_lidar(t, ref).tolist()} for t in self.scans],
            "trajectory": {"t_s": self.traj_t.tolist(),
                           "T_world_base": self.traj_T_world_base.reshape(-1, 16).tolist()},
        }


# ----------------------------------------------------------------------- motion

def base_pose(plan: DrivePlan, t: np.ndarray) -> np.ndarray:
    """(K,4,4) T_world_base at times t (s): weaving path, body roll/pitch on the suspension."""
    t = np.atleast_1d(np.asarray(t, float))
    v = 0.0 if plan.stopped else plan.speed_mps
    w = 2 * np.pi / plan.yaw_period_s
    amp = np.radians(plan.yaw_rate_amp_dps) if not plan.stopped else 0.0
    yaw = amp / w * (1 - np.cos(w * t))  # integral of amp*sin(w t)
    # x, y: integrate v*(cos yaw, sin yaw) numerically on a fine grid
    tg = np.linspace(0, max(t.max(), 1e-3) + 0.2, 20001)
    yg = amp / w * (1 - np.cos(w * tg))
    dt = tg[1] - tg[0]
    xg = np.concatenate([[0], np.cumsum(v * np.cos(yg[:-1] + np.diff(yg) / 2) * dt)])
    ygp = np.concatenate([[0], np.cumsum(v * np.sin(yg[:-1] + np.diff(yg) / 2) * dt)])
    x = np.interp(t, tg, xg) - 25.0 + (0.0 if not plan.stopped else 10.0)
    y = np.interp(t, tg, ygp)
    a = np.radians(plan.body_tilt_deg)
    roll = a * (0.6 * np.sin(2 * np.pi * t / 2.3) + 0.4 * np.sin(2 * np.pi * t / 3.7 + 1.0))
    pitch = a * (0.6 * np.sin(2 * np.pi * t / 2.9 + 0.5) + 0.4 * np.sin(2 * np.pi * t / 4.3 + 2.0))
    out = np.zeros((len(t), 4, 4))
    out[:, :3, :3] = geo.R_from_rpy(np.stack([roll, pitch, yaw], axis=1))
    out[:, 0, 3], out[:, 1, 3], out[:, 3, 3] = x, y, 1.0
    return out


# ----------------------------------------------------------------------- scene

def _street_meshes(rng, flat: bool):
    from .scene import box_mesh, cylinder_mesh

    meshes = []

    def box(sx, sy, sz, x, y, z, yaw=0.0):
        meshes.append(box_mesh(sx, sy, sz, x, y, z, yaw))

    def cyl(r, h, x, y):
        meshes.append(cylinder_mesh(r, h, x, y))

    box(400, 400, 0.1, 0, 0, -0.1)  # ground, top face at z = 0
    if flat:
        return meshes
    for side in (-1, 1):
        y0 = side * 9.0
        x = -60.0
        while x < 60.0:  # facades of varying depth and height with window recesses
            w = rng.uniform(6, 12)
            h = rng.uniform(6, 14)
            d = rng.uniform(0, 1.5)
            box(w, 4, h, x + w / 2, y0 + side * (2 + d), 0)
            for wx in np.arange(x + 1.0, x + w - 1.0, 2.0):  # window sills / pilasters
                box(0.3, 0.5, h, wx, y0 + side * (0.1 + d), 0)
                for wz in np.arange(1.0, h - 1.0, 3.0):
                    box(1.2, 0.35, 0.25, wx + 1.0, y0 + side * (0.05 + d), wz)
            x += w + rng.uniform(0.0, 2.0)
        for px in np.arange(-55, 55, rng.uniform(7, 11)):  # poles
            cyl(0.12, rng.uniform(3, 6), px + rng.uniform(-1, 1), side * 6.0 + rng.uniform(-0.3, 0.3))
        for cx in np.arange(-50, 50, 9.0):  # parked cars: body + cabin
            if rng.uniform() < 0.3:
                continue
            yy = side * 4.6 + rng.uniform(-0.2, 0.2)
            yaw = rng.uniform(-0.1, 0.1)
            box(4.3, 1.8, 0.8, cx, yy, 0.3, yaw)
            box(2.2, 1.6, 0.6, cx - 0.2, yy, 1.1, yaw)
        for tx in np.arange(-52, 52, rng.uniform(12, 16)):  # trees: trunk + crown boxes
            x0, y0t = tx + rng.uniform(-2, 2), side * 7.2
            cyl(0.2, 2.5, x0, y0t)
            for _ in range(3):
                box(*rng.uniform(1.0, 2.2, 3), x0 + rng.uniform(-0.6, 0.6), y0t + rng.uniform(-0.6, 0.6),
                    2.4 + rng.uniform(0, 1.2), rng.uniform(0, 1))
    for _ in range(12):  # uneven structure: kerb stones, bins, benches
        box(*rng.uniform(0.3, 1.2, 2), rng.uniform(0.2, 1.0), rng.uniform(-50, 50),
            rng.choice([-1, 1]) * rng.uniform(3.6, 5.5), 0, rng.uniform(0, 3))
    return meshes


def make_scene(kind: str, seed: int = 0):
    """An open3d RaycastingScene: "street" or "flat" (open field, ground only)."""
    import open3d as o3d

    rng = np.random.default_rng(seed)
    scene = o3d.t.geometry.RaycastingScene()
    for m in _street_meshes(rng, flat=(kind == "flat")):
        scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(m))
    return scene


# ----------------------------------------------------------------------- scans

def _scan(scene, spec: LidarSpec, plan: DrivePlan, t_start: float, t0_ns: int, rng) -> LidarScan:
    from .lidar import LidarModel, simulate_scan
    from .scene import Scene

    period = 1.0 / plan.rate_hz
    model = LidarModel(spec.topic, tuple(np.linspace(spec.elev_min_deg, spec.elev_max_deg, spec.rings)), spec.columns,
                       range_noise_m=spec.range_noise_m, dropout=0.0, max_range_m=spec.max_range_m, layout="ouster",
                       rotation_period_s=period)
    tc = t_start + np.arange(spec.columns) / spec.columns * period  # column times
    T_wl = base_pose(plan, tc) @ geo.T_from_rt(np.asarray(spec.rt_base_lidar))  # (cols,4,4)
    scan, _ = simulate_scan(model, T_wl, Scene(scene, -1, -1), rng, stamp_ns=t0_ns + int(round(t_start * 1e9)),
                            topic=spec.topic)
    return scan


def simulate_drive(plan: DrivePlan | None = None, *, seed: int = 0, progress=None) -> Drive:
    """Ray-cast every scan of every LIDAR along the drive (motion-distorted, per-column poses)."""
    plan = plan or DrivePlan.small()
    rng = np.random.default_rng(seed)
    scene = make_scene(plan.scene, seed)
    t0_ns = Drive.t0_ns
    scans, T_true, T_guess, frames = {}, {}, {}, {}
    ref = plan.lidars[0].topic
    for i, spec in enumerate(plan.lidars):
        n = int(plan.duration_s * plan.rate_hz)
        starts = spec.time_offset_s + np.arange(n) / plan.rate_hz
        it = progress(starts, desc=f"simulating {spec.topic}") if progress is not None else starts
        scans[spec.topic] = [_scan(scene, spec, plan, s, t0_ns, rng) for s in it]
        T_true[spec.topic] = geo.T_from_rt(np.asarray(spec.rt_base_lidar))
        frames[spec.topic] = spec.frame
        if spec.topic == ref:
            T_guess[spec.topic] = T_true[spec.topic]
        else:
            axis = rng.normal(size=3)
            axis /= np.linalg.norm(axis)
            dirn = rng.normal(size=3)
            dirn /= np.linalg.norm(dirn)
            dT = geo.T_from_rt(np.r_[axis * np.radians(plan.guess_rot_deg), dirn * plan.guess_trans_m])
            T_guess[spec.topic] = T_true[spec.topic] @ dT
    tt = np.arange(0, plan.duration_s + 0.2, 0.05)
    return Drive(plan, scans, T_true, T_guess, frames, tt, base_pose(plan, tt), t0_ns)


def write_drive_bag(drive: Drive, path, *, format: str = "ros1", base_frame: str = "base_link",
                    layout: str = "velodyne", log_delays: bool = True) -> None:
    """Write the scans and /tf_static (the perturbed guess, base_link -> each LIDAR) to a bag;
    ``layout``: the point layout of the drivers (bag_writer: "velodyne" or organised "ouster");
    ``log_delays``: log times as drivers write them (bag_writer.LogDelays), else log time = stamp."""
    from .bag_writer import BagWriter, LogDelays

    with BagWriter(path, format=format, log_delays=LogDelays() if log_delays else None) as w:
        w.write_tf_static([(base_frame, drive.frames[t], drive.T_base_lidar_guess[t]) for t in drive.scans],
                          stamp_ns=drive.t0_ns)
        allscans = sorted((s.stamp_ns, t, s) for t, ss in drive.scans.items() for s in ss)
        for _, t, s in allscans:
            w.write_pointcloud(t, s, frame_id=drive.frames[t], layout=layout)


def write_truth(drive: Drive, path) -> None:
    """truth.yaml: extrinsics (base_link and lidar0 frames) and the base trajectory."""
    import yaml

    from pathlib import Path
    Path(path).write_text(yaml.safe_dump(drive.truth_dict(), sort_keys=False))
