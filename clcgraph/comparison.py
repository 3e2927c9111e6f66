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
``geometry.tangent_covariance_from_rt``. The two captures' noise is independent, but the sensor
units' own errors e (a LIDAR ring's range bias and elevation error, a lens-model field) are the
same in both: the difference carries (J_b - J_a) e, J how each capture's solution moves with e
(calibration.yaml's ``unit_errors``, paired by name: ``unit_error_term``, sigmas from
``compare.unit_*``). So d2 = xi^T (Sigma_a + Sigma_b + that term)^-1 xi is chi-square with 6
degrees of freedom when nothing moved; "moved" when its p-value is below ``compare.false_alarm_rate``. Against a pose set
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
    # the units' named errors and each sensor's sensitivity to them (calibration.yaml's unit_errors), or None:
    # {"errors": [(sensor, error, at)], "J": {topic: (6, K) d rt / d error},
    #  "sigma_in_covariance": {kind: sigma, or {sensor topic: sigma}}}
    unit_errors: dict | None = None

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
        from .outputs.results import unit_errors_dict

        poses = {s.topic: (_T(source.rt_lidar0_sensor[i]), None if i == p.reference else
                           np.asarray(source.covariance_block(i), float)) for i, s in enumerate(p.sensors)}
        where = f"{source.method} result"
        return PoseSet(p.sensors[p.reference].topic, poses, where,
                       _unit_errors(unit_errors_dict(source).get("unit_errors"), where))
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
        from .outputs.results import calibration_from_dict

        d = calibration_from_dict(d, path)  # the full schema check of solve / targetless outputs
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
    return PoseSet(reference, {t: tuple(v) for t, v in poses.items()}, where, _unit_errors(d.get("unit_errors"), where))


def _unit_errors(block, where: str) -> dict | None:
    """calibration.yaml's ``unit_errors`` block (outputs/results.unit_errors_dict) -> PoseSet.unit_errors."""
    if block is None:
        return None
    try:
        errors = [(str(e[0]), str(e[1]), float(e[2])) for e in block["errors"]]
        J = {str(t): np.asarray(rows, float).reshape(len(errors), 6).T for t, rows in block["sensitivity_rt"].items()}
        # a kind's sigma, or per sensor topic (a LIDAR's ring range bias measured on its boards)
        sigma = {str(k): {str(t): float(x) for t, x in v.items()} if isinstance(v, dict) else float(v)
                 for k, v in block["sigma_in_covariance"].items()}
    except (KeyError, IndexError, TypeError, ValueError, AttributeError):
        raise DataError(f"{where}: unit_errors needs 'errors' ([sensor, error, at] each), 'sensitivity_rt' "
                        "(per sensor one row of 6 per error) and 'sigma_in_covariance'") from None
    if not all(np.all(np.isfinite(j)) for j in J.values()):
        raise DataError(f"{where}: unit_errors: a sensitivity is not finite")
    return {"errors": errors, "J": J, "sigma_in_covariance": sigma}


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
    unit_errors: str = ""  # how the units' shared errors entered the test (unit_error_term), in words

    @property
    def changed(self) -> bool:
        return any(s.status == "moved" for s in self.sensors)

    def to_dict(self) -> dict:
        return {"a": self.a, "b": self.b, "reference": self.reference, "changed": self.changed,
                "false_alarm_rate": self.false_alarm_rate,
                "thresholds": {"max_rotation_deg": self.thresholds[0], "max_translation_mm": self.thresholds[1]},
                "unit_errors": self.unit_errors,
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
                  max_translation_mm: float, unit_term=None) -> SensorChange:
    """One sensor's difference and verdict (module docstring); ``cov_*`` (6,6) rt covariances or None;
    ``unit_term``: (6,6) added to the difference's tangent covariance (the units' shared errors, unit_error_term)."""
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
    if unit_term is not None:
        Sigma = Sigma + unit_term
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


# The same ring in two captures: its elevation measured from its board points agrees to < 0.02 deg (a
# beam's origin offset); rings are >= 0.06 deg apart (backend/consider.RING_GAP_RAD): half of that.
RING_MATCH_DEG = 0.03


def _kind(error: str) -> str:
    return "lens field" if error.startswith("lens field") else error


def pair_unit_errors(ua: dict, ub: dict) -> tuple[list, np.ndarray, np.ndarray]:
    """(the union of A's and B's named errors [(sensor, error, at)], (K_A,) and (K_B,) the index of each
    of A's and B's errors in it): a ring is the same ring within RING_MATCH_DEG of elevation, a lens
    mode the same index; an error named by one side only (a ring no board of the other capture met)
    has no effect on the other's solution."""
    union = list(ua["errors"])
    ia, ib = np.arange(len(union)), np.full(len(ub["errors"]), -1)
    group_a = {}
    for k, (sensor, error, at) in enumerate(union):
        group_a.setdefault((sensor, error), []).append(k)
    group_b = {}
    for k, (sensor, error, at) in enumerate(ub["errors"]):
        group_b.setdefault((sensor, error), []).append(k)
    for key, kb in group_b.items():
        kb = np.array(kb)
        at_b = np.array([ub["errors"][k][2] for k in kb])
        ka = np.array(group_a.get(key, []), int)
        tol = RING_MATCH_DEG if key[1].startswith("ring") else 0.0
        if len(ka):
            d = np.abs(at_b[:, None] - np.array([union[k][2] for k in ka])[None, :])
            nearest = np.argmin(d, axis=1)
            same = d[np.arange(len(kb)), nearest] <= tol + 1e-9
            ib[kb[same]] = ka[nearest[same]]
        new = kb[ib[kb] < 0]
        ib[new] = len(union) + np.arange(len(new))
        union += [ub["errors"][k] for k in new]
    return union, ia, ib


def paired_sensitivities(topic: str, rt_a, rt_b, ua: dict, ub: dict) -> tuple[list, np.ndarray, np.ndarray]:
    """(the union of the named errors, (6, K) J_A, (6, K) J_B): how one sensor's pose in A and in B moves
    per unit of each error, in each side's tangent (sensor_change's coordinates); 0 where a side does not name it."""
    from .geometry import drt_dxi

    union, ia, ib = pair_unit_errors(ua, ub)

    def tangent(u, idx, rt):
        J = np.zeros((6, len(union)))
        if topic in u["J"]:
            J[:, idx] = np.linalg.solve(drt_dxi(np.asarray(rt, float)), u["J"][topic])
        return J

    return union, tangent(ua, ia, rt_a), tangent(ub, ib, rt_b)


def unit_error_term(topic: str, rt_a, rt_b, ua: dict, ub: dict, sigma: dict, *, same_units: bool = True) -> np.ndarray:
    """(6,6) what the units' errors add to the covariance of one sensor's difference (tangent, as
    sensor_change's Sigma), beyond what the two covariances already hold.

    Same units: one draw e of the errors in both captures, so the difference carries (J_A - J_B) e:
    ``+ D S D^T`` with D = J_A - J_B over the paired errors and S their variances (``sigma`` per
    kind: "ring range bias" m, "ring elevation" rad, "lens field" px), ``- J_A S_A J_A^T - J_B S_B J_B^T``
    for what each solve already put into its covariance (its sigma_in_covariance). Replaced units:
    independent draws, ``J_A (S - S_A) J_A^T + J_B (S - S_B) J_B^T``. J in each side's tangent
    (``drt_dxi`` inverted: the coordinates sensor_change tests in).
    """
    union, Ja, Jb = paired_sensitivities(topic, rt_a, rt_b, ua, ub)
    kinds = [_kind(e[1]) for e in union]
    s2 = np.array([sigma.get(k, 0.0) for k in kinds]) ** 2
    sa2 = np.array([_in_covariance(ua, e) for e in union]) ** 2
    sb2 = np.array([_in_covariance(ub, e) for e in union]) ** 2
    if same_units:
        D = Ja - Jb
        term = (D * s2) @ D.T - (Ja * sa2) @ Ja.T - (Jb * sb2) @ Jb.T
    else:
        term = (Ja * (s2 - sa2)) @ Ja.T + (Jb * (s2 - sb2)) @ Jb.T
    return 0.5 * (term + term.T)


def _in_covariance(u: dict, error) -> float:
    """The 1-sigma of named ``error`` (sensor, error, at) that calibration ``u`` holds in its covariance."""
    v = u["sigma_in_covariance"].get(_kind(error[1]), 0.0)
    return float(v.get(error[0], 0.0)) if isinstance(v, dict) else float(v)


def _unit_errors_words(pa: PoseSet, pb: PoseSet, sigma: dict, same_units: bool) -> str:
    """How the units' errors entered the test, for the verdict's record."""
    if pa.unit_errors is None and pb.unit_errors is None:
        return "not in the test: neither calibration names its units' errors"
    if pa.unit_errors is None or pb.unit_errors is None:
        return (f"not in the test: only {'A' if pb.unit_errors is None else 'B'} names its units' errors "
                "(the other: targetless, a nominal pose set or an older calibration)")
    union, ia, ib = pair_unit_errors(pa.unit_errors, pb.unit_errors)
    both = len(ia) + len(ib) - len(union)
    how = "same units, shared draw" if same_units else "units replaced, independent draws"
    # many errors named by one side only: rings at other elevations (another LIDAR model) or another camera
    one = f", {len(union) - both} named by one side only (a ring no board of the other capture met" + \
        ("; or other units: compare.same_units=false)" if len(union) - both > both else ")") if len(union) > both else ""
    return (f"{both} named errors of the units paired{one} ({how}; 1-sigma: ring range bias "
            f"{1e3 * sigma['ring range bias']:g} mm, ring elevation {np.degrees(sigma['ring elevation']):g} deg, "
            f"lens field {sigma['lens field']:g} px)")


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
    sigma = {"ring range bias": cfg.unit_ring_range_bias_m, "ring elevation": float(np.radians(cfg.unit_ring_elevation_deg)),
             "lens field": cfg.unit_lens_field_px}
    paired = pa.unit_errors is not None and pb.unit_errors is not None
    rows = []
    for t in [*pa.poses, *(t for t in pb.poses if t not in pa.poses)]:
        if t == pa.reference:
            rows.append(SensorChange(t, "reference", "reference"))
        elif t not in pb.poses or t not in pa.poses:
            side = "A" if t in pa.poses else "B"
            rows.append(SensorChange(t, f"only in {side}", f"only in {side}: not compared"))
        else:
            from .geometry import rt_from_T

            term = unit_error_term(t, rt_from_T(pa.poses[t][0]), rt_from_T(pb.poses[t][0]), pa.unit_errors,
                                   pb.unit_errors, sigma, same_units=cfg.same_units) if paired else None
            rows.append(sensor_change(t, *pa.poses[t], *pb.poses[t], false_alarm_rate=cfg.false_alarm_rate,
                                      max_rotation_deg=cfg.max_rotation_deg, max_translation_mm=cfg.max_translation_mm,
                                      unit_term=term))
    return Comparison(pa.source or str(a), pb.source or str(b), pa.reference, tuple(rows), cfg.false_alarm_rate,
                      (cfg.max_rotation_deg, cfg.max_translation_mm), _unit_errors_words(pa, pb, sigma, cfg.same_units))


def _is_bag_like(x) -> bool:
    return isinstance(x, (str, Path)) and _is_bag(Path(x))


def write_yaml(d: dict, path) -> Path:
    """Write ``d`` as YAML to ``path``, whole or not at all (its first line says clcgraph wrote it:
    a later --yaml may replace it)."""
    import yaml

    from .outputs.atomic import atomic_file

    return atomic_file(path, "# clcgraph comparison\n" + yaml.safe_dump(d, sort_keys=False, width=200))
