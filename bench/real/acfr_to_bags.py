"""Turn the ACFR Ouster-64 + fisheye captures into ROS1 bags clcgraph reads, one bag per board pose.

SYNOPSIS
    # from a checkout of the raw data (git archive of acfr/cam_lidar_calibration, parent of ff2dd49):
    python -m bench.real.acfr_to_bags RAW/data/2022-11-09_00-54-42 --camera-info RAW/cfg/camera_info.yaml \\
        --out /work/realdata/acfr/run1
    # from the compact copy in this repository:
    python -m bench.real.acfr_to_bags data/real/acfr-ouster/run1 --out /tmp/run1
    # make the compact copy (clouds as compressed npz, images as the original PNG):
    python -m bench.real.acfr_to_bags RAW/data/2022-11-09_00-54-42 --camera-info ... --pack data/real/acfr-ouster/run1

Each ``poseK_full.pcd`` (ASCII, organised 1024 x 64, fields x y z intensity ring, ring as u8,
invalid returns as 0 0 0) becomes an Ouster-driver PointCloud2 (organised, point_step 48, see
clcgraph/sim/bag_writer.py) on ``/os_cloud_node/points``, and ``poseK.png`` a raw bgr8
sensor_msgs/Image on ``/sekonix_camera/port_a_cam_1/image_color``, as the drivers publish them.
The fisheye intrinsics (OpenCV fisheye, cfg/camera_info.yaml) become ``camera.cameramodel``: a
mrcal splined stereographic model fitted to that projection over the whole image (fit error
written to ``lens_fit.txt``). The ACFR tool's own result (its CSV, 50 rows of roll, pitch, yaw,
x, y, z of T_lidar_camera, R = Rz(yaw) Ry(pitch) Rx(roll)) is copied as ``acfr_result.csv``.
"""

from __future__ import annotations

import argparse
import logging
import shutil
import sys
from pathlib import Path

import numpy as np

LIDAR_TOPIC = "/os_cloud_node/points"
CAMERA_TOPIC = "/sekonix_camera/port_a_cam_1/image_color"
LIDAR_FRAME, CAMERA_FRAME = "os_sensor", "port_a_cam_1"
T0_NS = 1_667_955_282_000_000_000  # 2022-11-09 00:54:42 UTC, the first run's start
POSE_PERIOD_NS = 30_000_000_000  # poses were taken about half a minute apart
CAMERA_DELAY_NS = 40_000_000  # the image stamp 40 ms after the scan's (one camera frame)

log = logging.getLogger(__name__)


def read_pcd(path: Path) -> dict:
    """An ASCII organised PCD (x y z intensity ring) as arrays of shape (height, width)."""
    header, n_header = {}, 0
    with open(path, "rb") as f:
        for line in f:
            n_header += 1
            key, *vals = line.decode().split()
            header[key] = vals
            if key == "DATA":
                break
        if header["DATA"] != ["ascii"] or header["FIELDS"] != ["x", "y", "z", "intensity", "ring"]:
            raise ValueError(f"{path}: expected an ASCII PCD with fields x y z intensity ring")
        a = np.loadtxt(f, dtype=np.float64)
    h, w = int(header["HEIGHT"][0]), int(header["WIDTH"][0])
    a = a.reshape(h, w, 5)
    return {"xyz": a[..., :3].astype(np.float32), "intensity": a[..., 3].astype(np.uint16),
            "ring": a[..., 4].astype(np.uint8)}


def read_camera_info(path: Path) -> tuple[np.ndarray, np.ndarray, tuple[int, int]]:
    import yaml

    c = yaml.safe_load(Path(path).read_text())
    if c.get("distortion_model") != "fisheye":
        raise ValueError(f"{path}: distortion_model {c.get('distortion_model')!r}, expected fisheye")
    return np.array(c["K"], float).reshape(3, 3), np.array(c["D"], float), (int(c["width"]), int(c["height"]))


def _poses(run: Path) -> list[int]:
    """Pose numbers present, in numeric order: raw layout (pcd/poseK_full.pcd) or packed (poseK.npz)."""
    names = [p.stem for p in (run / "pcd").glob("pose*_full.pcd")] if (run / "pcd").is_dir() else \
        [p.stem for p in run.glob("pose*.npz")]
    return sorted(int(n[4:].split("_")[0]) for n in names)


def _load_pose(run: Path, k: int) -> tuple[dict, Path]:
    if (run / "pcd").is_dir():
        return read_pcd(run / "pcd" / f"pose{k}_full.pcd"), run / "images" / f"pose{k}.png"
    z = np.load(run / f"pose{k}.npz")
    return {"xyz": z["xyz"], "intensity": z["intensity"], "ring": z["ring"]}, run / f"pose{k}.png"


def _acfr_csv(run: Path) -> Path | None:
    found = sorted(run.glob("calibration_*.csv")) or sorted(run.glob("acfr_result.csv"))
    return found[0] if found else None


def pack(run: Path, camera_info: Path, out: Path) -> None:
    """The compact copy of one run: poseK.npz (float32 xyz, u16 intensity, u8 ring per
    (ring row, column), zlib) + the original poseK.png, camera_info.yaml, acfr_result.csv."""
    out.mkdir(parents=True, exist_ok=True)
    for k in _poses(run):
        cloud, png = _load_pose(run, k)
        np.savez_compressed(out / f"pose{k}.npz", **cloud)
        shutil.copyfile(png, out / f"pose{k}.png")
    shutil.copyfile(camera_info, out / "camera_info.yaml")
    csv = _acfr_csv(run)
    if csv is not None:
        shutil.copyfile(csv, out / "acfr_result.csv")


def convert(run: Path, out: Path, *, camera_info: Path | None = None, run_index: int = 0,
            lens_fit=None) -> list[Path]:
    """Write ``out``/poseK.bag per pose, camera.cameramodel, lens_fit.txt and acfr_result.csv;
    return the bag paths. ``lens_fit``: a fisheye_fit.SplinedFit to reuse (else fitted here)."""
    import cv2
    import mrcal

    from clcgraph.sim.bag_writer import BagWriter
    from clcgraph.types import Image, LidarScan

    from clcgraph.fisheye_fit import fit_splined

    camera_info = Path(camera_info) if camera_info else run / "camera_info.yaml"
    K, D, size = read_camera_info(camera_info)
    out.mkdir(parents=True, exist_ok=True)
    fit = lens_fit or fit_splined(K, D, size)
    mrcal.cameramodel(intrinsics=(fit.lensmodel, fit.intrinsics), imagersize=np.array(size),
                      extrinsics_rt_fromref=np.zeros(6)).write(str(out / "camera.cameramodel"))
    (out / "lens_fit.txt").write_text(
        f"{fit.lensmodel} fitted to the OpenCV fisheye model K={K.tolist()} D={D.tolist()}\n"
        f"over a 16 px grid: RMS {fit.rms_px:.4f} px, max {fit.max_px:.4f} px; "
        f"on a finer offset grid: RMS {fit.check_rms_px:.4f} px, max {fit.check_max_px:.4f} px\n")
    csv = _acfr_csv(run)
    if csv is not None and csv.parent != out:
        shutil.copyfile(csv, out / "acfr_result.csv")
    bags = []
    for k in _poses(run):
        cloud, png = _load_pose(run, k)
        h, w = cloud["ring"].shape
        if not (cloud["ring"] == cloud["ring"][:, :1]).all():
            raise ValueError(f"{run}: pose{k}: a cloud row holds more than one ring")
        stamp = T0_NS + run_index * 3600 * 10**9 + k * POSE_PERIOD_NS
        scan = LidarScan(topic=LIDAR_TOPIC, stamp_ns=stamp, points=cloud["xyz"].reshape(-1, 3).astype(float),
                         valid=(cloud["xyz"].reshape(-1, 3) != 0).any(axis=1),
                         intensity=cloud["intensity"].reshape(-1).astype(np.float32),
                         ring=cloud["ring"].reshape(-1).astype(np.int64), shape=(h, w))
        px = cv2.imread(str(png), cv2.IMREAD_COLOR)
        if px is None:
            raise ValueError(f"{png}: not a readable image")
        path = out / f"pose{k:02d}.bag"
        path.unlink(missing_ok=True)
        with BagWriter(path, format="ros1", compress=True) as bw:
            bw.write_pointcloud(LIDAR_TOPIC, scan, frame_id=LIDAR_FRAME, layout="ouster")
            bw.write_image(CAMERA_TOPIC, Image(CAMERA_TOPIC, stamp + CAMERA_DELAY_NS, px, "bgr8"),
                           frame_id=CAMERA_FRAME)
        bags.append(path)
    return bags


def acfr_result(csv: Path) -> tuple[np.ndarray, np.ndarray]:
    """(T_lidar_camera (4,4) from the mean of the ACFR tool's 50 rows, their (6,) std of
    roll pitch yaw x y z): the tool reports the mean over its board subsets."""
    from scipy.spatial.transform import Rotation

    a = np.loadtxt(csv, delimiter=",", skiprows=1)
    m = a.mean(axis=0)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("ZYX", m[[2, 1, 0]]).as_matrix()  # Rz(yaw) Ry(pitch) Rx(roll)
    T[:3, 3] = m[3:]
    return T, a.std(axis=0, ddof=1)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", type=Path, help="a run directory: raw (pcd/, images/) or packed (poseK.npz + .png)")
    ap.add_argument("--camera-info", type=Path, help="cfg/camera_info.yaml (packed runs carry their own)")
    ap.add_argument("--out", type=Path, help="write the bags and camera.cameramodel here")
    ap.add_argument("--pack", type=Path, help="write the compact copy of the raw run here")
    ap.add_argument("--run-index", type=int, default=0, help="offsets the stamps by this many hours")
    a = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    if a.pack:
        pack(a.run, a.camera_info, a.pack)
    if a.out:
        bags = convert(a.run, a.out, camera_info=a.camera_info, run_index=a.run_index)
        print(f"{len(bags)} bags in {a.out}; " + (a.out / "lens_fit.txt").read_text().splitlines()[1])
    return 0


if __name__ == "__main__":
    sys.exit(main())
