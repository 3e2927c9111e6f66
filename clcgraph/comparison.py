"""Has a rig's calibration changed? Two pose sets of the same rig, compared sensor by sensor.

SYNOPSIS
    import clcgraph
    c = clcgraph.compare("calib-2026-11/", "calib-2026-12/")   # outputs of solve / targetless
    c = clcgraph.compare("calib/", "capture/pose000.bag")       # against the bag's /tf_static
    print(c.table()); c.changed                                 # True if any sensor moved
    c.to_dict()                                                 # what `clcgraph compare --yaml` writes

A pose set is anything ``poses_of`` reads: a Result (of either method), a Calibration
(``load_result``), the output directory
(or calibration.yaml) of solve / targetless, a calibration.yaml without covariance (a nominal
pose set: ``sensors: [{topic, rt_lidar0_sensor | T_lidar0_sensor}]``), or a bag whose
/tf_static gives nominal poses of the other side's sensors.

Per sensor: the difference by composition, E = T_a^-1 T_b. Its tangent xi = [omega, v] is
in the same coordinates as the covariances (GTSAM's right perturbation T Exp(xi) to first
order: omega = Log(R_a^T R_b) about the sensor's own axes, v = R_a^T (t_b - t_a)); both
rt covariances of calibration.yaml (its ``coordinates:`` block) are mapped into them with
``geometry.tangent_covariance_from_rt``. The two estimates are independent, so
d2 = xi^T (Sigma_a + Sigma_b)^-1 xi is chi-square with 6 degrees of freedom when nothing
moved; "moved" when its p-value is below ``compare.false_alarm_rate``. Against a pose set
without covariance (CAD, /tf_static) there is no such test: the thresholds
``compare.max_rotation_deg`` / ``compare.max_translation_mm`` decide. The printed rotation
axis and translation are in the reference frame (lidar0): R_b R_a^T = Exp(angle * axis),
t_b - t_a.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .config import read_yaml
from .errors import DataError, InputError
from .types import Result

log = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class PoseSet:
    """Sensor poses in the reference frame: topic -> (T_ref_sensor (4,4), Var(rt_ref_sensor) (6,6) or None)."""

    reference: str
    poses: dict
    source: str = ""

    @property
    def has_covariance(self) -> bool:
        return all(c is not None for t, (_, c) in self.poses.items() if t != self.reference)


def _is_bag(path: Path) -> bool:
    return (path.is_file() and path.suffix == ".bag") or (path.is_dir() and (path / "metadata.yaml").exists())


def poses_of(source, *, topics=None, reference: str | None = None) -> PoseSet:
    """The one adapter from anything that holds poses to a PoseSet (see the module docstring).

    A bag needs ``topics`` (the sensors to look up; the first, or ``reference``, is lidar0):
    its /tf_static gives T_reference_sensor through the frames of the topics' messages.
    """
    if isinstance(source, PoseSet):
        return source
    if isinstance(source, Result):  # either method's: the same fields
        p = source.problem
        poses = {s.topic: (_T(source.rt_lidar0_sensor[i]), None if i == p.reference else
                           np.asarray(source.covariance_block(i), float)) for i, s in enumerate(p.sensors)}
        return PoseSet(p.sensors[p.reference].topic, poses, f"{source.method} result")
    if isinstance(source, Mapping):  # load_result's Calibration, or a nominal pose set
        return _from_calibration_dict(source, str(getattr(source, "path", "calibration")))
    path = Path(source)
    if _is_bag(path):
        if not topics:
            raise InputError(f"{path}: a bag's /tf_static has poses only of named sensors: compare it with a calibration")
        return _from_tf_static(path, list(topics), reference or list(topics)[0])
    if path.is_dir():
        path = path / "calibration.yaml"
    return _from_calibration_file(path)


def _T(rt) -> np.ndarray:
    from .geometry import T_from_rt

    return T_from_rt(np.asarray(rt, float).reshape(6))


def _from_calibration_file(path: Path) -> PoseSet:
    d = read_yaml(path, "calibration", hint="; give an output directory of clcgraph solve / targetless, "
                  "a calibration.yaml or a bag")
    if isinstance(d, dict) and "covariance_rt_lidar0_sensor" in d:
        from .outputs.results import load_result

        d = load_result(path)  # the full schema check of solve / targetless outputs
    return _from_calibration_dict(d, str(path))


def _from_calibration_dict(d, where: str) -> PoseSet:
    """calibration.yaml content (with or without covariance) -> PoseSet."""
    if not isinstance(d, Mapping) or not isinstance(d.get("sensors"), list) or not d["sensors"]:
        raise DataError(f"{where}: not a calibration: needs a non-empty 'sensors' list")
    poses, order = {}, []
    for k, s in enumerate(d["sensors"]):
        if not isinstance(s, dict) or "topic" not in s or not ({"rt_lidar0_sensor", "T_lidar0_sensor"} & set(s)):
            raise DataError(f"{where}: sensors[{k}] needs 'topic' and 'rt_lidar0_sensor' or 'T_lidar0_sensor'")
        try:
            T = _T(s["rt_lidar0_sensor"]) if "rt_lidar0_sensor" in s else np.asarray(s["T_lidar0_sensor"], float).reshape(4, 4)
        except (ValueError, TypeError):
            raise DataError(f"{where}: sensors[{k}] ({s['topic']}): a pose of the wrong shape") from None
        if not np.all(np.isfinite(T)):
            raise DataError(f"{where}: sensors[{k}] ({s['topic']}): the pose is not finite")
        poses[str(s["topic"])] = [T, None]
        order.append(str(s["topic"]))
    reference = str(d.get("reference", order[0]))
    if reference not in poses:
        raise DataError(f"{where}: reference {reference} is not one of the sensors")
    C = d.get("covariance_rt_lidar0_sensor")
    if C is not None:
        others = [t for t in order if t != reference]
        C = np.asarray(C, float).reshape(6 * len(others), 6 * len(others))
        for j, t in enumerate(others):
            poses[t][1] = C[6 * j:6 * j + 6, 6 * j:6 * j + 6]
    return PoseSet(reference, {t: tuple(v) for t, v in poses.items()}, where)


def _from_tf_static(bag: Path, topics: list[str], reference: str) -> PoseSet:
    from .frontend.bag import frame_id, read_tf_static

    tf = read_tf_static(bag)
    if not tf.frames:
        raise InputError(f"{bag}: no /tf_static: no nominal poses to compare with")
    frames = {}
    for t in topics:
        try:
            frames[t] = frame_id(bag, t)
        except DataError:
            log.info("%s: no messages of %s; its nominal pose is unknown", bag, t)
    if reference not in frames:
        raise InputError(f"{bag}: no message of the reference {reference}, so its frame is unknown")
    poses = {}
    for t, f in frames.items():
        try:
            poses[t] = (tf.lookup(frames[reference], f), None)
        except DataError as e:
            log.info("%s: %s", bag, e)
    return PoseSet(reference, poses, f"{bag} /tf_static")


# ---------------------------------------------------------------- the comparison


@dataclass(frozen=True)
class SensorChange:
    topic: str
    status: str  # "moved" | "same" | "reference" | "only in A" | "only in B"
    verdict: str  # in words
    rotation_deg: float | None = None
    axis_ref: tuple | None = None  # unit rotation axis in the reference frame
    translation_mm: tuple | None = None  # t_b - t_a in the reference frame
    mahalanobis: float | None = None  # sqrt(d2)
    chi2: float | None = None
    p_value: float | None = None
    test: str = ""  # "chi-square, 6 DoF" or "thresholds"

    def to_dict(self) -> dict:
        def f(v):  # 9 significant digits: BLAS thread counts change the last ones (same inputs, same bytes)
            return None if v is None else float(f"{float(v):.9g}")
        return {"topic": self.topic, "status": self.status, "verdict": self.verdict, "rotation_deg": f(self.rotation_deg),
                "axis_ref": None if self.axis_ref is None else [f(x) for x in self.axis_ref],
                "translation_mm": None if self.translation_mm is None else [f(x) for x in self.translation_mm],
                "mahalanobis": f(self.mahalanobis), "chi2": f(self.chi2), "p_value": f(self.p_value), "test": self.test}


@dataclass(frozen=True)
class Comparison:
    a: str
    b: str
    reference: str
    sensors: tuple = field(default_factory=tuple)  # SensorChange, A's order then B's extra
    false_alarm_rate: float = 0.01
    thresholds: tuple = (0.0, 0.0)  # (deg, mm)

    @property
    def changed(self) -> bool:
        return any(s.status == "moved" for s in self.sensors)

    def to_dict(self) -> dict:
        return {"a": self.a, "b": self.b, "reference": self.reference, "changed": self.changed,
                "false_alarm_rate": self.false_alarm_rate,
                "thresholds": {"max_rotation_deg": self.thresholds[0], "max_translation_mm": self.thresholds[1]},
                "sensors": [s.to_dict() for s in self.sensors]}

    def table(self) -> str:
        """What `clcgraph compare` prints (outputs.tables.comparison_table)."""
        from .outputs.tables import comparison_table

        return comparison_table(self)


def _axis_words(axis: np.ndarray) -> str:
    k = int(np.argmax(np.abs(axis)))
    if abs(axis[k]) >= 0.9:  # within ~25 deg of a reference axis: name it
        return f"about {'-' if axis[k] < 0 else ''}{'xyz'[k]}"
    return "about (" + ", ".join(f"{x:+.2f}" for x in axis) + ")"


def _p_words(p: float) -> str:
    return "p < 1e-6" if p < 1e-6 else f"p = {p:.2g}"


def sensor_change(topic: str, T_a, cov_a, T_b, cov_b, *, false_alarm_rate: float, max_rotation_deg: float,
                  max_translation_mm: float) -> SensorChange:
    """One sensor's difference and verdict (module docstring); ``cov_*`` (6,6) rt covariances or None."""
    from scipy.stats import chi2

    from .geometry import r_from_R, rt_from_T, tangent_covariance_from_rt

    T_a, T_b = np.asarray(T_a, float), np.asarray(T_b, float)
    R_a = T_a[:3, :3]
    omega = r_from_R(R_a.T @ T_b[:3, :3])  # about the sensor's own axes (A's)
    dt = T_b[:3, 3] - T_a[:3, 3]  # in the reference frame
    xi = np.concatenate([omega, R_a.T @ dt])
    angle = float(np.linalg.norm(omega))
    axis = R_a @ omega / angle if angle > 0 else np.zeros(3)
    what = f"{np.degrees(angle):.2f} deg {_axis_words(axis)} and {1e3 * np.linalg.norm(dt):.1f} mm" \
        if angle > 0 else f"{1e3 * np.linalg.norm(dt):.1f} mm"
    common = dict(rotation_deg=float(np.degrees(angle)), axis_ref=tuple(axis), translation_mm=tuple(1e3 * dt))
    if cov_a is None or cov_b is None:  # a nominal pose has no uncertainty to test against
        moved = np.degrees(angle) > max_rotation_deg or 1e3 * np.linalg.norm(dt) > max_translation_mm
        limits = f"{max_rotation_deg:g} deg, {max_translation_mm:g} mm"
        verdict = f"moved {what}: beyond the thresholds ({limits})" if moved else f"same within the thresholds ({limits})"
        return SensorChange(topic, "moved" if moved else "same", verdict, **common, test="thresholds")
    Sigma = tangent_covariance_from_rt(rt_from_T(T_a), cov_a) + tangent_covariance_from_rt(rt_from_T(T_b), cov_b)
    w, V = np.linalg.eigh(Sigma)
    if not np.all(np.isfinite(w)) or w.max() <= 0 or w.min() <= 1e-12 * w.max():
        raise DataError(f"{topic}: its covariances are singular (a direction with no uncertainty): "
                        "no chi-square test is possible; compare with thresholds against a nominal pose set")
    d2 = float(np.sum((V.T @ xi) ** 2 / w))
    p = float(chi2.sf(d2, 6))
    if p < false_alarm_rate:
        status, verdict = "moved", f"moved {what}: significant, {_p_words(p)}"
    else:
        status, verdict = "same", f"same within uncertainty ({_p_words(p)})"
    return SensorChange(topic, status, verdict, **common, mahalanobis=float(np.sqrt(d2)), chi2=d2, p_value=p,
                        test="chi-square, 6 DoF")


def compare(a, b, *, config=None) -> Comparison:
    """Compare two pose sets of one rig (anything ``poses_of`` reads; a bag on either side gives the
    nominal poses of the other side's sensors). ``config``: a Config (its ``compare`` section), a
    YAML path or a dict."""
    from .api import _config

    cfg = _config(config).compare
    pa = None if _is_bag_like(a) else poses_of(a)
    pb = poses_of(b) if not _is_bag_like(b) else None
    if pa is None and pb is None:
        raise InputError(f"{a}, {b}: two bags: at least one side must be a calibration")
    if pa is None:
        pa = poses_of(a, topics=[pb.reference, *pb.poses], reference=pb.reference)
    if pb is None:
        pb = poses_of(b, topics=[pa.reference, *pa.poses], reference=pa.reference)
    if pa.reference != pb.reference:
        raise InputError(f"{pa.source} has reference {pa.reference} but {pb.source} has {pb.reference}: "
                         "poses relative to different sensors cannot be compared")
    rows = []
    for t in [*pa.poses, *(t for t in pb.poses if t not in pa.poses)]:
        if t == pa.reference:
            rows.append(SensorChange(t, "reference", "reference"))
        elif t not in pb.poses or t not in pa.poses:
            side = "A" if t in pa.poses else "B"
            rows.append(SensorChange(t, f"only in {side}", f"only in {side}: not compared"))
        else:
            rows.append(sensor_change(t, *pa.poses[t], *pb.poses[t], false_alarm_rate=cfg.false_alarm_rate,
                                      max_rotation_deg=cfg.max_rotation_deg, max_translation_mm=cfg.max_translation_mm))
    return Comparison(pa.source or str(a), pb.source or str(b), pa.reference, tuple(rows), cfg.false_alarm_rate,
                      (cfg.max_rotation_deg, cfg.max_translation_mm))


def _is_bag_like(x) -> bool:
    return isinstance(x, (str, Path)) and _is_bag(Path(x))


def write_yaml(d: dict, path) -> Path:
    """Write ``d`` as YAML to ``path``, whole or not at all."""
    import yaml

    from .outputs.atomic import atomic_file

    return atomic_file(path, yaml.safe_dump(d, sort_keys=False, width=200))
