"""Small ROS1 bags for the CLI tests: two LIDARs (16 x 360 spheres) and a 64x48 camera."""

import numpy as np
import pytest

from clcgraph.geometry import T_from_rt
from clcgraph.sim.bag_writer import BagWriter
from clcgraph.types import Image, LidarScan

T0 = 1_700_000_000_000_000_000


def _scan(rng, stamp_ns, topic, *, all_invalid=False):
    elev = np.linspace(-0.25, 0.25, 16)[:, None]
    az = np.linspace(-np.pi, np.pi, 360, endpoint=False)[None, :]
    r = rng.uniform(3, 15, (16, 360))
    pts = np.stack([r * np.cos(elev) * np.cos(az), r * np.cos(elev) * np.sin(az),
                    r * np.sin(elev) * np.ones_like(az)], -1).reshape(-1, 3)
    valid = np.zeros(len(pts), bool) if all_invalid else np.ones(len(pts), bool)
    return LidarScan(topic, stamp_ns, pts, valid, ring=np.repeat(np.arange(16), 360),
                     time_s=np.tile(np.linspace(0, 0.099, 360), 16), shape=(16, 360))


def make_bag(path, *, lidars=("/lidar0", "/lidar1"), camera="/cam0", all_invalid=False, encoding="mono8",
             camera_info_size=None):
    """``camera_info_size``: (width, height) of a pinhole CameraInfo written beside the camera's images."""
    rng = np.random.default_rng(0)
    with BagWriter(path, format="ros1") as w:
        if camera and camera_info_size:
            from clcgraph.frontend.bag import camera_info_topic

            w.write_camera_info(camera_info_topic(camera), stamp_ns=T0, frame_id="cam0", size=camera_info_size,
                                K=[[50, 0, 31.5], [0, 50, 23.5], [0, 0, 1]], distortion_model="plumb_bob", D=[0] * 5)
        w.write_tf_static([("base_link", "lidar0", np.eye(4)),
                           ("base_link", "lidar1", T_from_rt(np.array([0, 0, 0.1, 0.5, 0, 0])))], stamp_ns=T0)
        for k, t in enumerate(lidars):
            w.write_pointcloud(t, _scan(rng, T0 + k, t, all_invalid=all_invalid and k == 1),
                               frame_id=t.strip("/"), layout="velodyne")
        if camera:
            px = rng.integers(0, 255, (48, 64), dtype=np.uint8)
            if encoding == "mono8":
                w.write_image(camera, Image(camera, T0 + 5, px, "mono8"), frame_id="cam0")
            else:  # an encoding clcgraph cannot decode, written the way a driver would
                T = w.typestore.types
                msg = T["sensor_msgs/msg/Image"](header=w._header(camera, T0 + 5, "cam0"), height=48, width=64,
                                                 encoding=encoding, is_bigendian=0, step=64,
                                                 data=px.reshape(-1))
                w._write(camera, "sensor_msgs/msg/Image", msg, T0 + 5)
    return path


@pytest.fixture(scope="module")
def good(tmp_path_factory):
    return make_bag(tmp_path_factory.mktemp("bags") / "good.bag")


@pytest.fixture(scope="module")
def model(tmp_path_factory):
    import mrcal

    p = tmp_path_factory.mktemp("models") / "cam0.cameramodel"
    mrcal.cameramodel(intrinsics=("LENSMODEL_PINHOLE", np.array([50.0, 50.0, 31.5, 23.5])),
                      imagersize=np.array([64, 48])).write(str(p))
    return p


@pytest.fixture
def bag_factory():
    """make_bag(path, lidars=..., camera=..., all_invalid=..., encoding=..., camera_info_size=...) -> path."""
    return make_bag
