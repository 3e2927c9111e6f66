"""Camera models as users have them: an mrcal .cameramodel, or a ROS camera calibration YAML
(`camera_calibration`'s ost.yaml), read into the same Sensor; what cannot be used is one line."""

import numpy as np
import pytest
import yaml

from clcgraph.cameras import load_camera, project
from clcgraph.errors import DataError

ROOT = __import__("pathlib").Path(__file__).resolve().parents[2]


def _ros_yaml(path, K, model, D, size=(1024, 768)):
    path.write_text(yaml.safe_dump({
        "image_width": size[0], "image_height": size[1], "camera_name": "front",
        "camera_matrix": {"rows": 3, "cols": 3, "data": np.asarray(K, float).ravel().tolist()},
        "distortion_model": model,
        "distortion_coefficients": {"rows": 1, "cols": len(D), "data": list(map(float, D))},
        "rectification_matrix": {"rows": 3, "cols": 3, "data": np.eye(3).ravel().tolist()},
        "projection_matrix": {"rows": 3, "cols": 4, "data": np.eye(3, 4).ravel().tolist()},
    }, sort_keys=False))
    return path


def test_a_ros_calibration_yaml_is_the_same_camera_as_its_cameramodel(tmp_path):
    mrcal_cam = load_camera("/cam", ROOT / "data" / "synthetic" / "front.cameramodel")  # LENSMODEL_OPENCV8
    fx, fy, cx, cy, *D = mrcal_cam.intrinsics
    K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]
    ros = load_camera("/cam", _ros_yaml(tmp_path / "ost.yaml", K, "rational_polynomial", D))
    assert ros.lensmodel == mrcal_cam.lensmodel and ros.imagersize == mrcal_cam.imagersize
    np.testing.assert_array_equal(ros.intrinsics, mrcal_cam.intrinsics)
    assert ros.intrinsics_covariance is None
    # plumb_bob: 5 coefficients (k1 k2 p1 p2 k3) as OPENCV5, 4 as OPENCV4; the same projection
    p = np.array([[0.3, -0.2, 2.0], [-0.5, 0.4, 3.0]])
    for D5, lens in (([-0.1, 0.02, 1e-4, -2e-4, 0.003], "LENSMODEL_OPENCV5"), ([-0.1, 0.02, 1e-4, -2e-4], "LENSMODEL_OPENCV4")):
        cam = load_camera("/cam", _ros_yaml(tmp_path / "pb.yml", K, "plumb_bob", D5))
        assert cam.lensmodel == lens
        k1, k2, p1, p2, *k3 = D5
        x, y = p[:, 0] / p[:, 2], p[:, 1] / p[:, 2]
        r2 = x * x + y * y
        radial = 1 + k1 * r2 + k2 * r2**2 + (k3[0] if k3 else 0) * r2**3
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        np.testing.assert_allclose(project(p, cam.lensmodel, cam.intrinsics), np.c_[fx * xd + cx, fy * yd + cy],
                                   atol=1e-9)


def test_a_ros_equidistant_fisheye_is_fitted_as_a_splined_model(tmp_path):
    """ROS's equidistant model (OpenCV's fisheye: theta_d = theta (1 + k1 theta^2 + ... + k4 theta^8)),
    which mrcal has not, becomes a splined stereographic model that projects as the fisheye does
    over the whole image, to 0.05 px, out to 85 deg off the axis (a 170 deg lens, 640x480)."""
    K = [[190.0, 0, 318.0], [0, 191.0, 243.0], [0, 0, 1]]
    D = [0.04, -0.012, 0.003, -0.0004]
    cam = load_camera("/fisheye", _ros_yaml(tmp_path / "fisheye.yaml", K, "equidistant", D, size=(640, 480)))
    assert cam.lensmodel.startswith("LENSMODEL_SPLINED_STEREOGRAPHIC") and cam.imagersize == (640, 480)
    rng = np.random.default_rng(3)
    th, ph = np.radians(rng.uniform(0, 85, 400)), rng.uniform(-np.pi, np.pi, 400)
    v = np.c_[np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)]
    t2 = th**2
    thd = th * (1 + t2 * (D[0] + t2 * (D[1] + t2 * (D[2] + t2 * D[3]))))
    q = np.c_[K[0][0] * thd * np.cos(ph) + K[0][2], K[1][1] * thd * np.sin(ph) + K[1][2]]
    seen = (q[:, 0] >= 0) & (q[:, 0] <= 639) & (q[:, 1] >= 0) & (q[:, 1] <= 479)
    assert seen.sum() > 200 and th[seen].max() > np.radians(75)
    err = np.linalg.norm(project(v[seen], cam.lensmodel, cam.intrinsics) - q[seen], axis=1)
    assert err.max() < 0.05, err.max()


def test_what_cannot_be_used_is_one_line_naming_the_file(tmp_path):
    K = [[500, 0, 320], [0, 500, 240], [0, 0, 1]]
    for model, D, words in (("equidistant", [0.1, 0.01, 0], "equidistant with 3 coefficients"),
                            ("plumb_bob", [0.1, 0.2, 0.3], "plumb_bob with 3 coefficients")):
        with pytest.raises(DataError, match=words):
            load_camera("/cam", _ros_yaml(tmp_path / "x.yaml", K, model, D))
    for text in ("image_width: 640\n",  # keys missing; a key of another shape
                 "image_width: 640\nimage_height: 480\ncamera_matrix: {data: [500, 0, 320, 0, 500, 240, 0, 0, 1]}\n"
                 "distortion_coefficients: [0.1, 0, 0, 0, 0]\n"):
        (tmp_path / "bad.yaml").write_text(text)
        with pytest.raises(DataError, match=r"bad.yaml: not a ROS camera calibration YAML"):
            load_camera("/cam", tmp_path / "bad.yaml")
    with pytest.raises(DataError, match=r"is not \[\[fx, 0, cx\]"):
        load_camera("/cam", _ros_yaml(tmp_path / "skew.yaml", [[500, 3, 320], [0, 500, 240], [0, 0, 1]], "plumb_bob",
                                      [0, 0, 0, 0, 0]))
