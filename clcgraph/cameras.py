"""The only mrcal wrapper: camera models on disk, projection with gradients.

SYNOPSIS
    cam = load_camera("/topic/image", "left.cameramodel")   # -> Sensor
    q, dq_dp, dq_di = project(p_cam, cam.lensmodel, cam.intrinsics, get_gradients=True)
    write_cameramodel("out.cameramodel", cam, rt_cam_ref=rt)

Shapes: p (...,3) in the camera frame (right-down-forward); q (...,2) pixels;
dq_dp (...,2,3); dq_di (...,2,Nintrinsics).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .errors import DataError, DependencyError, InputError
from .types import Sensor


# A .cameramodel is text of a few kB (splined models some 100 kB); a camera side is < 100k px.
_MAX_MODEL_BYTES = 16 << 20
_MAX_IMAGER_SIDE = 100_000


def _mrcal():
    try:
        import mrcal
    except ImportError as e:  # pragma: no cover - depends on the machine
        raise DependencyError(
            f"mrcal is not importable ({e}); install Debian's python3-mrcal and use a venv "
            "made with --system-site-packages (./dev.sh setup does both)"
        ) from None
    return mrcal


def load_camera(topic: str, path: str | Path) -> Sensor:
    """Read a .cameramodel file into a camera Sensor (intrinsics only; extrinsics are solved)."""
    mrcal = _mrcal()
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: camera model file not found (given for camera topic {topic})")
    if path.stat().st_size > _MAX_MODEL_BYTES:
        raise DataError(f"{path}: {path.stat().st_size} bytes is too large for a .cameramodel "
                        f"(at most {_MAX_MODEL_BYTES >> 20} MB; given for camera topic {topic})")
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
        intrinsics_covariance=intrinsics_covariance(model, path),
    )


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
