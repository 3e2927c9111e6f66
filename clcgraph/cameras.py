"""The only mrcal wrapper: camera models on disk, projection with gradients.

SYNOPSIS
    cam = load_camera("/topic/image", "left.cameramodel")   # -> Sensor
    q, dq_dp, dq_di = project(p_cam, cam.lensmodel, cam.intrinsics, get_gradients=True)
    write_cameramodel("out.cameramodel", cam, rt_cam_ref=rt)

Shapes: p (...,3) in the camera frame (right-down-forward); q (...,2) pixels;
dq_dp (...,2,3); dq_di (...,2,Nintrinsics).
"""

from __future__ import annotations

import contextlib
import logging
import sys
import threading
import warnings
from pathlib import Path

import numpy as np

from .errors import DataError, DependencyError, InputError
from .types import Sensor

log = logging.getLogger(__name__)


# A .cameramodel is text of a few kB (splined models some 100 kB); a camera side is < 100k px.
_MAX_MODEL_BYTES = 16 << 20
_MAX_IMAGER_SIDE = 100_000
# Given for a camera's model: its CameraInfo in the bags (camera_from_info), beside files for the others
FROM_CAMERA_INFO = "camera_info"


def _mrcal():
    try:
        with _stdlib_distutils():
            import mrcal
    except ImportError as e:  # pragma: no cover - depends on the machine
        raise DependencyError(
            f"mrcal is not importable ({e}); install Debian's python3-mrcal and use a venv "
            "made with --system-site-packages (./dev.sh setup does both)"
        ) from None
    return mrcal


@contextlib.contextmanager
def _stdlib_distutils():
    """Python's own distutils for an import: mrcal's numpysane imports distutils, which setuptools'
    import hook (its distutils-precedence.pth) serves from setuptools, importing pkg_resources:
    0.15-0.3 s of every process start. Python 3.11 still has its own; the hook is back after
    (a later ``import setuptools`` in the same process warns that it replaces that distutils)."""
    with _DISTUTILS_LOCK:  # two threads' first imports: one takes the hook out and puts it back
        hooks = [f for f in sys.meta_path if type(f).__module__ == "_distutils_hack"]
        if sys.version_info >= (3, 12) or "distutils" in sys.modules or not hooks:
            yield
            return
        for f in hooks:
            sys.meta_path.remove(f)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", DeprecationWarning)  # stdlib distutils' own
                yield
        finally:
            sys.meta_path[:0] = hooks


_DISTUTILS_LOCK = threading.Lock()


def load_camera(topic: str, path: str | Path) -> Sensor:
    """Read a camera model into a camera Sensor (intrinsics only; extrinsics are solved): an mrcal
    .cameramodel, or a ROS camera calibration YAML (.yaml/.yml: `camera_calibration`'s ost.yaml,
    camera_info_manager's files; ``ros_calibration_yaml``)."""
    mrcal = _mrcal()
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: camera model file not found (given for camera topic {topic})")
    if path.stat().st_size > _MAX_MODEL_BYTES:
        raise DataError(f"{path}: {path.stat().st_size} bytes is too large for a .cameramodel "
                        f"(at most {_MAX_MODEL_BYTES >> 20} MB; given for camera topic {topic})")
    model = None
    if path.suffix.lower() in (".yaml", ".yml"):
        lensmodel, intrinsics, (w, h) = ros_calibration_yaml(path)
    else:
        try:
            model = mrcal.cameramodel(str(path))
            lensmodel, intrinsics = model.intrinsics()
            w, h = (int(v) for v in model.imagersize())
            intrinsics = np.array(intrinsics, dtype=float).reshape(-1)
        except Exception as e:  # mrcal's parser raises many kinds (and RecursionError on deep nesting)
            raise DataError(f"{path}: not a readable mrcal .cameramodel: {str(e).splitlines()[0] if str(e) else type(e).__name__}") from None
    if not (0 < w <= _MAX_IMAGER_SIDE and 0 < h <= _MAX_IMAGER_SIDE):
        raise DataError(f"{path}: imagersize {w}x{h} is not a camera's (each side 1..{_MAX_IMAGER_SIDE} px)")
    # every mrcal lens model starts with fx, fy, cx, cy
    if not np.all(np.isfinite(intrinsics)) or len(intrinsics) < 4 or not np.all(intrinsics[:2] > 0):
        raise DataError(f"{path}: intrinsics must be finite with positive focal lengths, got {intrinsics[:4].tolist()} ...")
    return Sensor(
        topic=topic,
        kind="camera",
        lensmodel=lensmodel,
        intrinsics=intrinsics,
        imagersize=(w, h),
        intrinsics_covariance=None if model is None else intrinsics_covariance(model, path),
    )


# ROS distortion models as mrcal lens models: the same polynomial, coefficients in the same order
_ROS_MODELS = {("plumb_bob", 4): "LENSMODEL_OPENCV4", ("plumb_bob", 5): "LENSMODEL_OPENCV5",
               ("rational_polynomial", 8): "LENSMODEL_OPENCV8"}
ROS_DISTORTION = {lens: model for (model, _), lens in _ROS_MODELS.items()}  # and back (a CameraInfo's)
# ROS's name for OpenCV's fisheye model (camera_calibration's), and other tools' names for it
_ROS_FISHEYE = ("equidistant", "fisheye", "kannala_brandt")
# a splined model fitted to a fisheye is off by less than this anywhere (corner detection: 0.1-0.3 px)
_MAX_FISHEYE_FIT_PX = 0.25


def ros_calibration_yaml(path) -> tuple[str, np.ndarray, tuple[int, int]]:
    """(mrcal lens model, intrinsics, (width, height)) of a ROS camera calibration YAML
    (image_width, image_height, camera_matrix, distortion_model, distortion_coefficients):
    ``ros_lens``'s; DataError naming the file for anything it cannot use."""
    from .config import read_yaml

    d = read_yaml(path, "ROS camera calibration", error=DataError,
                  mapping="with image_width, camera_matrix, distortion_model, ...")
    try:
        w, h = int(d["image_width"]), int(d["image_height"])
        K = np.asarray(d["camera_matrix"]["data"], float).reshape(3, 3)
        model = str(d.get("distortion_model", "plumb_bob"))
        D = np.asarray((d.get("distortion_coefficients") or {}).get("data", []), float).reshape(-1)
    except (AttributeError, KeyError, TypeError, ValueError) as e:
        raise DataError(f"{path}: not a ROS camera calibration YAML ({type(e).__name__}: {e}); it needs image_width, "
                        "image_height, camera_matrix.data (9 numbers), distortion_model, distortion_coefficients.data") from None
    return ros_lens(K, model, D, (w, h), where=str(path), other="give a .cameramodel")


def camera_from_info(topic: str, info) -> Sensor:
    """A camera Sensor from its sensor_msgs/CameraInfo (frontend/bag.camera_info: its K, D,
    distortion_model, width, height and where it was read), as ``ros_lens`` maps it."""
    lens, intrinsics, size = ros_lens(info.K, info.distortion_model, info.D, info.size, where=info.where,
                                      other=f"give a camera model for {topic}")
    return Sensor(topic=topic, kind="camera", lensmodel=lens, intrinsics=intrinsics, imagersize=size)


def ros_lens(K: np.ndarray, model: str, D: np.ndarray, size: tuple[int, int], *, where: str,
             other: str) -> tuple[str, np.ndarray, tuple[int, int]]:
    """(mrcal lens model, intrinsics, size) of a ROS camera calibration (K, distortion_model, D):
    plumb_bob as LENSMODEL_OPENCV4/5, rational_polynomial as LENSMODEL_OPENCV8 (the same model,
    exactly); equidistant (OpenCV's fisheye, Kannala-Brandt k1-k4), which mrcal has not, as a
    splined stereographic model fitted to it over the image (fisheye_fit; ~0.5-3 s; refused if it
    is more than _MAX_FISHEYE_FIT_PX off anywhere); DataError naming ``where`` (and saying
    ``other``) for anything else."""
    K, D = np.asarray(K, float).reshape(3, 3), np.asarray(D, float).reshape(-1)
    w, h = size
    # before the model's checks: an uncalibrated driver publishes zeros (and the fisheye fit needs a camera)
    if not (0 < w <= _MAX_IMAGER_SIDE and 0 < h <= _MAX_IMAGER_SIDE and np.all(np.isfinite(K)) and K[0, 0] > 0
            and K[1, 1] > 0 and np.all(np.isfinite(D))):
        raise DataError(f"{where}: not a calibrated camera (width x height {w}x{h}, K {K.tolist()}, D {D.tolist()}): "
                        f"{other}")
    n = len(D)
    if model == "plumb_bob" and n > 5 and not np.any(D[5:]):  # zeros padded by some tools
        D, n = D[:5], 5
    if model == "rational_polynomial" and n < 8:
        D, n = np.r_[D, np.zeros(8 - n)], 8
    fisheye = model in _ROS_FISHEYE and n == 4
    lens = _ROS_MODELS.get((model, n))
    if lens is None and not fisheye:
        raise DataError(f"{where}: distortion_model {model} with {n} coefficients is not one clcgraph can use as an "
                        f"mrcal lens model; plumb_bob (4 or 5), rational_polynomial (8) and equidistant (4) are; or "
                        f"{other}")
    if K[0, 1] != 0 or K[1, 0] != 0 or K[2, 0] != 0 or K[2, 1] != 0 or K[2, 2] != 1:
        raise DataError(f"{where}: camera_matrix {K.tolist()} is not [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]")
    if not fisheye:
        return lens, np.r_[K[0, 0], K[1, 1], K[0, 2], K[1, 2], D], (w, h)
    from .fisheye_fit import fit_splined

    fit = fit_splined(K, D, (w, h))
    worst = max(fit.max_px, fit.check_max_px)
    if not worst <= _MAX_FISHEYE_FIT_PX:
        raise DataError(f"{where}: the equidistant model (fx {K[0, 0]:g}, D {D.tolist()}) could not be fitted as an mrcal "
                        f"model: {worst:.2g} px off somewhere in the image (> {_MAX_FISHEYE_FIT_PX} px); {other} "
                        "(mrcal-calibrate-cameras)")
    log.info("%s: the equidistant (fisheye) model as %s, fitted to within %.3f px over the image (RMS %.4f px)",
             where, fit.lensmodel, worst, fit.rms_px)
    return fit.lensmodel, fit.intrinsics, (w, h)


def intrinsics_covariance(model, path="the camera model") -> np.ndarray | None:
    """(Nintrinsics, Nintrinsics) covariance of a model's intrinsics from the calibration that
    made it (mrcal's ``optimization_inputs``, kept by mrcal-calibrate-cameras), or None if the
    model has none. mrcal's own propagation of its calibration noise (the observed pixel noise
    estimated from that calibration's residuals, regularization accounted for, as
    mrcal.projection_uncertainty does); rows of intrinsics the calibration held fixed are 0."""
    mrcal = _mrcal()
    inputs = model.optimization_inputs()
    if inputs is None:
        return None
    from mrcal.model_analysis import _propagate_calibration_uncertainty  # mrcal 2.2's own propagation

    lensmodel = model.intrinsics()[0]
    n = num_intrinsics(lensmodel)
    if not (inputs.get("do_optimize_intrinsics_core") or inputs.get("do_optimize_intrinsics_distortions")):
        return np.zeros((n, n))
    try:
        _, x, J, factorization = mrcal.optimizer_callback(**inputs)
        if factorization is None:
            raise ValueError("its calibration's normal equations are singular")
        icam = model.icam_intrinsics()
        i0 = mrcal.state_index_intrinsics(icam, **inputs)
        ncore = 4 if lensmodel_metadata(lensmodel)["has_core"] else 0
        first = 0 if inputs.get("do_optimize_intrinsics_core") else ncore
        last = n if inputs.get("do_optimize_intrinsics_distortions") else ncore
        scale = np.ones(J.shape[1])
        mrcal.unpack_state(scale, **inputs)  # b = D b*: D on the diagonal
        dF = np.zeros((last - first, J.shape[1]))
        dF[np.arange(last - first), i0 + np.arange(last - first)] = scale[i0:i0 + last - first]
        n_obs = mrcal.num_measurements_boards(**inputs)
        n_obs = None if n_obs == mrcal.num_measurements(**inputs) else n_obs
        sigma_px = float(np.std(mrcal.residuals_chessboard(inputs, residuals=x).ravel()))
        C = _propagate_calibration_uncertainty(dF, factorization, J, n_obs, sigma_px, "covariance")
    except Exception as e:  # mrcal raises many kinds for inconsistent inputs
        raise DataError(f"{path}: its optimization_inputs do not give the intrinsics' uncertainty: "
                        f"{str(e).splitlines()[0] if str(e) else type(e).__name__}") from None
    out = np.zeros((n, n))
    out[first:last, first:last] = 0.5 * (C + C.T)
    return out


def write_cameramodel(path: str | Path, camera: Sensor, *, rt_cam_ref: np.ndarray) -> None:
    """Write ``camera`` with extrinsics rt_cam_ref (ref -> camera) as a .cameramodel."""
    mrcal = _mrcal()
    model = mrcal.cameramodel(
        intrinsics=(camera.lensmodel, np.asarray(camera.intrinsics, dtype=float)),
        imagersize=np.array(camera.imagersize),
        extrinsics_rt_fromref=np.asarray(rt_cam_ref, dtype=float),  # mrcal 2.2 keyword
    )
    model.write(str(path))


def project(p: np.ndarray, lensmodel: str, intrinsics: np.ndarray, *, get_gradients: bool = False):
    """Project camera-frame points to pixels. With gradients: (q, dq_dp, dq_dintrinsics)."""
    mrcal = _mrcal()
    p = np.ascontiguousarray(p, dtype=float)
    intrinsics = np.ascontiguousarray(intrinsics, dtype=float)
    if get_gradients:
        return mrcal.project(p, lensmodel, intrinsics, get_gradients=True)
    return mrcal.project(p, lensmodel, intrinsics)


def unproject(q: np.ndarray, lensmodel: str, intrinsics: np.ndarray, *, normalize: bool = True) -> np.ndarray:
    """Pixels (...,2) -> observation vectors (...,3) in the camera frame."""
    mrcal = _mrcal()
    return mrcal.unproject(
        np.ascontiguousarray(q, dtype=float), lensmodel, np.ascontiguousarray(intrinsics, dtype=float), normalize=normalize
    )


def lensmodel_metadata(lensmodel: str) -> dict:
    return _mrcal().lensmodel_metadata_and_config(lensmodel)


def num_intrinsics(lensmodel: str) -> int:
    return _mrcal().lensmodel_num_params(lensmodel)
