"""Hostile inputs through the real CLI (issue 13, item 6): out-of-range settings, bombs (YAML,
zip, decompression), lying headers (image dimensions, cloud sizes), bad camera models and
tampered problem.npz files. Each case: exit 2, exactly one line on stderr naming the key /
file / topic, no traceback, bounded memory, nothing left in --out.

Settings and dumps run in-process (``clcgraph.cli.main``; fd-level stderr captured, memory by
tracemalloc); the bombs and lying headers run as subprocesses under an address-space limit
(RLIMIT_AS), so a decoder that allocates what a header claims dies instead of passing.
"""

from __future__ import annotations

import io
import json
import resource
import subprocess
import sys
import tracemalloc
import zipfile
from pathlib import Path

import cv2
import numpy as np
import pytest

from clcgraph.cli import main
from clcgraph.geometry import T_from_rt
from clcgraph.sim.bag_writer import BagWriter
from clcgraph.types import Image, LidarScan

T0 = 1_700_000_000_000_000_000
ADDRESS_SPACE_LIMIT = 1_500_000_000  # the CLI with its libraries runs in ~1 GB of address space
IN_PROCESS_PEAK = 200 << 20


# ------------------------------------------------------------------------------- fixtures

def _scan(rng, topic, rings=16, cols=360):
    elev = np.linspace(-0.25, 0.25, rings)[:, None]
    az = np.linspace(-np.pi, np.pi, cols, endpoint=False)[None, :]
    r = rng.uniform(3, 15, (rings, cols))
    p = np.stack([r * np.cos(elev) * np.cos(az), r * np.cos(elev) * np.sin(az),
                  r * np.sin(elev) * np.ones_like(az)], -1).reshape(-1, 3)
    return LidarScan(topic, T0, p, np.ones(len(p), bool), ring=np.repeat(np.arange(rings), cols),
                     time_s=np.tile(np.linspace(0, 0.099, cols), rings), shape=(rings, cols))


def _bag(path, *, camera_msg=None, cloud_patch=None):
    """Two LIDARs and a camera; ``camera_msg(writer)`` writes a hand-made camera message,
    ``cloud_patch(msg)`` edits the second LIDAR's serialized-to-be message."""
    rng = np.random.default_rng(0)
    with BagWriter(path, format="ros1") as w:
        w.write_tf_static([("base_link", "lidar0", np.eye(4)),
                           ("base_link", "lidar1", T_from_rt(np.array([0, 0, 0.1, 0.5, 0, 0])))], stamp_ns=T0)
        w.write_pointcloud("/lidar0", _scan(rng, "/lidar0"), frame_id="lidar0", layout="velodyne")
        if cloud_patch is None:
            w.write_pointcloud("/lidar1", _scan(rng, "/lidar1"), frame_id="lidar1", layout="velodyne")
        else:
            T = w.typestore.types
            F = T["sensor_msgs/msg/PointField"]
            fields = [F(name=n, offset=4 * k, datatype=7, count=1) for k, n in enumerate("xyz")]
            msg = T["sensor_msgs/msg/PointCloud2"](
                header=w._header("/lidar1", T0 + 1, "lidar1"), height=1, width=4, fields=fields,
                is_bigendian=False, point_step=12, row_step=48, data=np.zeros(48, np.uint8), is_dense=True)
            w._write("/lidar1", "sensor_msgs/msg/PointCloud2", cloud_patch(msg), T0 + 1)
        if camera_msg is None:
            w.write_image("/cam0", Image("/cam0", T0 + 5, rng.integers(0, 255, (48, 64), dtype=np.uint8), "mono8"),
                          frame_id="cam0")
        else:
            camera_msg(w)
    return path


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    import mrcal

    d = tmp_path_factory.mktemp("rig")
    model = d / "cam0.cameramodel"
    mrcal.cameramodel(intrinsics=("LENSMODEL_PINHOLE", np.array([50.0, 50.0, 31.5, 23.5])),
                      imagersize=np.array([64, 48])).write(str(model))
    return _bag(d / "good.bag"), model


@pytest.fixture(scope="module")
def dump(tmp_path_factory):
    from clcgraph.config import Config
    from clcgraph.outputs.dump import save_problem
    from clcgraph.sim.observations import simulate_problem

    problem, _ = simulate_problem(n_snapshots=8, seed=2)
    p = tmp_path_factory.mktemp("dump") / "problem.npz"
    save_problem(p, problem, Config())
    return p


def _one_line(capfd, argv, *names):
    """Run the CLI in-process: exit 2, one stderr line holding every name, bounded memory."""
    tracemalloc.start()
    try:
        rc = main([str(a) for a in argv])
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    err = capfd.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert rc == 2 and len(lines) == 1 and "Traceback" not in err, (rc, err)
    for n in names:
        assert str(n) in lines[0], (n, lines[0])
    assert peak < IN_PROCESS_PEAK, peak
    return lines[0]


def _limit_address_space():
    resource.setrlimit(resource.RLIMIT_AS, (ADDRESS_SPACE_LIMIT, ADDRESS_SPACE_LIMIT))


def _one_line_subprocess(argv, *names):
    r = subprocess.run([sys.executable, "-c", "import sys; from clcgraph.cli import main; sys.exit(main())",
                        *map(str, argv)], capture_output=True, text=True, timeout=120,
                       preexec_fn=_limit_address_space)
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 2 and len(lines) == 1 and "Traceback" not in r.stderr, (r.returncode, r.stderr)
    for n in names:
        assert str(n) in lines[0], (n, lines[0])
    return lines[0]


def _solve(bag, out, *extra, model=None, topics="/lidar0,/lidar1"):
    return ["solve", "--bag", bag, "--topics", topics + (",/cam0" if model else ""), "--out", out,
            *([model] if model else []), *extra]


# ----------------------------------------------------------------- out-of-range settings

SETTINGS = [
    # (flags, what the line must name)
    (["--Nsectors", "0"], ["--Nsectors", "sectors.n_sectors", "[1, 3600]"]),
    (["--set", "solve.outlier_sigma=.nan"], ["solve.outlier_sigma", "finite"]),
    (["--set", "solve.outlier_sigma=nan"], ["solve.outlier_sigma", "number"]),
    (["--exclude-bag", "("], ["--exclude-bag", "snapshots.exclude_bag", "regular expression"]),
    (["--prior-from-tf-static", "0,0.05"], ["--prior-from-tf-static", "solve.prior_from_tf_static_sigma_rad", "(0, inf)"]),
    (["--prior-from-tf-static", "0.01"], ["--prior-from-tf-static", "SIGMA_RAD,SIGMA_M"]),
    (["--set", "detection.jobs=0"], ["detection.jobs", "[1, 1024]"]),
    (["--set", "solve.max_iterations=-1"], ["solve.max_iterations", "[1, "]),
    (["--threshold-valid-lidar-range", "-1"], ["--threshold-valid-lidar-range", "sectors.threshold_valid_lidar_range_m"]),
    (["--threshold-valid-lidar-Npoints", "-5"], ["--threshold-valid-lidar-Npoints", "[0, "]),
    (["--uncertainty-quantification-range", "0"], ["--uncertainty-quantification-range", "(0, inf)"]),
    (["--max-time-spread-s", "inf"], ["--max-time-spread-s", "finite"]),
    (["--decimation-period", "0"], ["--decimation-period", "(0, inf)"]),
    (["--rt-vehicle-lidar0", "0,0,0,0,0,nan"], ["--rt-vehicle-lidar0", "6 finite numbers"]),
    (["--debug-region", "5,1,0,1"], ["--debug-region", "min < max"]),
    (["--max-tilt-deg", "nan"], ["--max-tilt-deg", "segmentation.max_tilt_deg"]),
    (["--max-tilt-deg", "120"], ["--max-tilt-deg", "(0, 90]"]),
    (["--min-rings", "0"], ["--min-rings", "segmentation.min_rings"]),
    (["--points-per-segment", "99999999999"], ["--points-per-segment", "2147483647"]),
    (["--segment-inlier-share", "1.5"], ["--segment-inlier-share", "(0, 1]"]),
    (["--set", "lidar.min_range_m=20"], ["lidar.min_range_m", "below", "lidar.max_range_m"]),
    (["--set", "lidar.static_range_quantum_m=0"], ["lidar.static_range_quantum_m", "[0.001, 10]"]),
    (["--set", "lidar.npoints_per_rotation=0"], ["lidar.npoints_per_rotation"]),
    (["--set", "solve.sigma_lidar_m=-0.01"], ["solve.sigma_lidar_m", "(0, inf)"]),
    (["--set", "solve.board_prior_sigma_rad=0"], ["solve.board_prior_sigma_rad"]),
    (["--set", "sectors.rt_vehicle_lidar0=[0,0,0]"], ["sectors.rt_vehicle_lidar0", "6 finite numbers"]),
    (["--set", "segmentation.min_segments_per_cluster=10", "--set", "segmentation.max_segments_per_cluster=5"],
     ["segmentation.min_segments_per_cluster", "at most"]),
    (["--set", "targetless.mapping_min_range=100"], ["targetless.mapping_min_range", "targetless.mapping_max_range"]),
    (["--set", "targetless.base_lidar_crop_box_min_z=30"], ["base_lidar_crop_box_min_z"]),
    (["--set", "detection.detector=foo"], ["detection.detector", "mrgingham, opencv"]),
    (["--set", "targetless.mapper_num_threads=0"], ["targetless.mapper_num_threads"]),
]


@pytest.mark.parametrize("flags, names", SETTINGS, ids=[" ".join(f) for f, _ in SETTINGS])
def test_out_of_range_setting_is_one_line_naming_it(capfd, tmp_path, rig, flags, names):
    bag, _ = rig
    out = tmp_path / "out"
    _one_line(capfd, _solve(bag, out, *flags), *names)
    assert not out.exists()


CONFIG_FILES = {
    "jobs: 0": ("detection:\n  jobs: 0\n", ["detection.jobs", "[1, 1024]"]),
    "max_iterations: -1": ("solve:\n  max_iterations: -1\n", ["solve.max_iterations"]),
    "nan": ("solve:\n  outlier_sigma: .nan\n", ["solve.outlier_sigma", "finite"]),
    "alias bomb": ("a: &a [x, x, x, x, x, x, x, x, x]\nb: &b [*a, *a, *a, *a, *a, *a, *a, *a, *a]\n"
                   "c: &c [*b, *b, *b, *b, *b, *b, *b, *b, *b]\nd: &d [*c, *c, *c, *c, *c, *c, *c, *c, *c]\n"
                   "e: &e [*d, *d, *d, *d, *d, *d, *d, *d, *d]\nf: &f [*e, *e, *e, *e, *e, *e, *e, *e, *e]\n"
                   "g: &g [*f, *f, *f, *f, *f, *f, *f, *f, *f]\nh: &h [*g, *g, *g, *g, *g, *g, *g, *g, *g]\n"
                   "snapshots:\n  exclude_time_periods: *h\n", ["cfg.yaml", "alias *a"]),
    "huge": ("solve:\n  outlier_sigma: 4\n" + "#" * (2 << 20) + "\n", ["cfg.yaml", "larger than"]),
    "binary": (None, ["cfg.yaml", "UTF-8"]),
    "not a mapping": ("[1, 2, 3]\n", ["cfg.yaml", "mapping"]),
}


@pytest.mark.parametrize("case", list(CONFIG_FILES))
def test_bad_config_file_is_one_line(capfd, tmp_path, rig, case):
    text, names = CONFIG_FILES[case]
    cfg = tmp_path / "cfg.yaml"
    if text is None:
        cfg.write_bytes(b"\xff\xfe\x00garbage\x80")
    else:
        cfg.write_text(text)
    _one_line(capfd, ["config", "check", "--config", cfg], *names)
    out = tmp_path / "out"
    _one_line(capfd, _solve(rig[0], out, "--config", cfg), *names)
    assert not out.exists()


def test_every_numeric_setting_has_a_range():
    """The range table covers every int/float setting (the board's keys come with the board section)."""
    import dataclasses
    import typing

    from clcgraph import config as C

    unranged = []
    for sec in dataclasses.fields(C.Config):
        cls = getattr(C, sec.type) if isinstance(sec.type, str) else sec.type
        hints = typing.get_type_hints(cls)
        for f in dataclasses.fields(cls):
            key = f"{sec.name}.{f.name}"
            base = {a for a in typing.get_args(hints[f.name]) if a is not type(None)} or {hints[f.name]}
            if base & {int, float} and key not in C._RANGES and not any(key in p for p in C._ORDERED):
                unranged.append(key)
    assert not unranged, unranged


# ---------------------------------------------------------------- bombs and lying headers

def _jpeg_claiming(w, h):
    """A 64x48 JPEG whose frame header says w x h (631 bytes claiming 30000x30000 in the issue)."""
    px = np.full((48, 64, 3), 128, np.uint8)
    d = bytearray(cv2.imencode(".jpg", px)[1].tobytes())
    sof = next(i for i in range(2, len(d) - 1) if d[i] == 0xFF and d[i + 1] == 0xC0)
    d[sof + 5:sof + 9] = h.to_bytes(2, "big") + w.to_bytes(2, "big")
    return np.frombuffer(bytes(d), np.uint8)


def _png_claiming(w, h):
    import struct
    import zlib

    d = bytearray(cv2.imencode(".png", np.zeros((48, 64), np.uint8))[1].tobytes())
    d[16:24] = struct.pack(">II", w, h)
    d[29:33] = struct.pack(">I", zlib.crc32(bytes(d[12:29])))
    return np.frombuffer(bytes(d), np.uint8)


def _compressed(data):
    def write(w):
        T = w.typestore.types
        msg = T["sensor_msgs/msg/CompressedImage"](header=w._header("/cam0", T0 + 5, "cam0"), format="jpeg",
                                                     data=data)
        w._write("/cam0", "sensor_msgs/msg/CompressedImage", msg, T0 + 5)
    return write


def _raw_image(h, w, step, nbytes, encoding="mono8"):
    def write(wr):
        T = wr.typestore.types
        msg = T["sensor_msgs/msg/Image"](header=wr._header("/cam0", T0 + 5, "cam0"), height=h, width=w,
                                           encoding=encoding, is_bigendian=0, step=step,
                                           data=np.zeros(nbytes, np.uint8))
        wr._write("/cam0", "sensor_msgs/msg/Image", msg, T0 + 5)
    return write


def _cloud(**fields):
    def patch(msg):
        for k, v in fields.items():
            setattr(msg, k, v)
        return msg
    return patch


LYING = {
    "jpeg 30000x30000 in 600 bytes": (dict(camera_msg=_compressed(_jpeg_claiming(30000, 30000))), "100 Mpixel"),
    "jpeg 9000x9000": (dict(camera_msg=_compressed(_jpeg_claiming(9000, 9000))), "more than its data can encode"),
    "jpeg 64x4000": (dict(camera_msg=_compressed(_jpeg_claiming(64, 4000))), "/cam0"),
    "png 20000x20000": (dict(camera_msg=_compressed(_png_claiming(20000, 20000))), "Mpixel"),
    "png 3000x3000 (CRC fixed)": (dict(camera_msg=_compressed(_png_claiming(3000, 3000))), "/cam0"),
    "png 640x480 (CRC fixed)": (dict(camera_msg=_compressed(_png_claiming(640, 480))), "lying header"),
    "raw 100000x100000 in 3 kB": (dict(camera_msg=_raw_image(100_000, 100_000, 100_000, 3072)), "/cam0"),
    "yuv odd width": (dict(camera_msg=_raw_image(48, 63, 126, 48 * 126, "yuv422")), "even width"),
    "cloud 10^9 points in 48 bytes": (dict(cloud_patch=_cloud(height=1_000_000_000, row_step=48)), "/lidar1"),
    "cloud 4e9 x 1, point_step 4e9": (dict(cloud_patch=_cloud(height=4_000_000_000, width=1, point_step=4_000_000_000,
                                                              row_step=4_000_000_000)), "/lidar1"),
    "cloud field past point_step": (dict(cloud_patch=_cloud(point_step=8, row_step=32)), "point_step 8 too small"),
}


@pytest.mark.parametrize("case", list(LYING))
def test_lying_header_is_one_line_with_bounded_memory(tmp_path, rig, case):
    kw, name = LYING[case]
    bag = _bag(tmp_path / "lying.bag", **kw)
    out = tmp_path / "out"
    line = _one_line_subprocess(_solve(bag, out, model=rig[1]), "lying.bag", name)
    assert "message 0" in line
    assert not out.exists()


def test_empty_cloud_of_3e8_rows_allocates_nothing(tmp_path, rig):
    """height 3e8, width 0, no ring field: an empty scan (it allocated 2.3 GB); solve names the
    missing board, under the address-space limit."""
    bag = _bag(tmp_path / "empty.bag", cloud_patch=_cloud(height=300_000_000, width=0, row_step=0))
    out = tmp_path / "out"
    _one_line_subprocess(_solve(bag, out, model=rig[1]), "/lidar1")
    assert not out.exists()


# ------------------------------------------------------------------------- camera models

def _model_text(rig):
    return rig[1].read_text()


MODELS = {
    "negative focal length": lambda t: t.replace("50, 50,", "-50, 50,"),
    "infinite intrinsics": lambda t: t.replace("50, 50,", "1e400, 50,"),
    "zero imagersize": lambda t: t.replace("[ 64, 48,]", "[ 0, 48,]"),
    "deep nesting": lambda t: "{'lensmodel': " + "[" * 50_000 + "]" * 50_000 + "}",
    "17 MB": lambda t: t + " " * (17 << 20),
    "garbage": lambda t: "\x00\x01 not a model",
}


@pytest.mark.parametrize("case", list(MODELS))
def test_bad_cameramodel_is_one_line(capfd, tmp_path, rig, case):
    text = _model_text(rig)
    assert "50, 50," in text and "[ 64, 48,]" in text
    bad = tmp_path / "bad.cameramodel"
    bad.write_text(MODELS[case](text))
    out = tmp_path / "out"
    _one_line(capfd, _solve(rig[0], out, model=bad), "bad.cameramodel")
    assert not out.exists()


# ------------------------------------------------------------------- tampered problem.npz

def _members(path):
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def _rewrite(src, dst, **changes):
    a = _members(src)
    a.update(changes)
    np.savez(dst, **{k: v for k, v in a.items() if v is not None})


def _meta(src, **changes):
    m = json.loads(str(_members(src)["meta"]))
    m.update(changes)
    return np.array(json.dumps(m))


def _zip_bomb(src, dst):
    """The valid dump's members plus a well-formed .npy member inflating to 1 GB of zeros (1 MB
    on disk). The deflate stream is one fully flushed 16 MB block repeated (a valid stream),
    so the bomb is built in well under a second."""
    import struct
    import zlib

    n_rep, chunk = 64, bytes(16 << 20)
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        header, {"descr": "<f8", "fortran_order": False, "shape": (n_rep * len(chunk) // 8,)})
    head = header.getvalue()
    c = zlib.compressobj(9, zlib.DEFLATED, -15)
    first = c.compress(head) + c.flush(zlib.Z_FULL_FLUSH)
    c = zlib.compressobj(9, zlib.DEFLATED, -15)
    block = c.compress(chunk) + c.flush(zlib.Z_FULL_FLUSH)
    data = first + block * n_rep + b"\x03\x00"  # an empty final fixed-Huffman block ends the stream
    crc = zlib.crc32(head)
    for _ in range(n_rep):
        crc = zlib.crc32(chunk, crc)
    size = len(head) + n_rep * len(chunk)
    with zipfile.ZipFile(dst, "w") as z:  # the genuine members first
        for k, v in _members(src).items():
            z.writestr(k + ".npy", _npy_bytes(v))
    body = bytearray(dst.read_bytes())
    eocd = body.rindex(b"PK\x05\x06")
    cd_size, cd_offset = struct.unpack("<II", body[eocd + 12:eocd + 20])
    count = struct.unpack("<H", body[eocd + 10:eocd + 12])[0]
    name = b"bomb.npy"
    offset = cd_offset
    local = struct.pack("<IHHHHHIIIHH", 0x04034B50, 20, 0, 8, 0, 0, crc, len(data), size, len(name), 0) + name
    central = struct.pack("<IHHHHHHIIIHHHHHII", 0x02014B50, 20, 20, 0, 8, 0, 0, crc, len(data), size,
                          len(name), 0, 0, 0, 0, 0, offset) + name
    old_cd = bytes(body[cd_offset:cd_offset + cd_size])
    new_cd = old_cd + central
    cd_start = offset + len(local) + len(data)
    end = struct.pack("<IHHHHIIH", 0x06054B50, 0, 0, count + 1, count + 1, len(new_cd), cd_start, 0)
    dst.write_bytes(bytes(body[:cd_offset]) + local + data + new_cd + end)


def _npy_bytes(v):
    b = io.BytesIO()
    np.lib.format.write_array(b, np.asanyarray(v), allow_pickle=False)
    return b.getvalue()


def _lying_npy(src, dst):
    """lidar_points' .npy header claims 10^12 rows."""
    a = _members(src)
    np.savez(dst, **a)
    with zipfile.ZipFile(dst) as z:
        items = {n: z.read(n) for n in z.namelist()}
    raw = items["lidar_points.npy"]
    hdr_end = raw.index(b"\n") + 1
    header = raw[10:hdr_end].decode("latin1")
    new = header.replace(f"({len(a['lidar_points'])}, 3)", "(1000000000000, 3)")
    new = new.rstrip("\n").ljust(len(header) - 1) + "\n"
    items["lidar_points.npy"] = raw[:10] + new.encode("latin1") + raw[hdr_end:]
    with zipfile.ZipFile(dst, "w") as z:
        for n, b in items.items():
            z.writestr(n, b)


def _tamper(case, src, dst):
    a = _members(src)
    if case == "truncated":
        dst.write_bytes(src.read_bytes()[: src.stat().st_size // 2])
    elif case == "empty file":
        dst.write_bytes(b"")
    elif case == "not a zip":
        dst.write_bytes(b"PK\x03\x04 but nothing else" * 10)
    elif case == "sensor 99":
        ss = a["lidar_sensor_snapshot"].copy()
        ss[0, 0] = 99
        _rewrite(src, dst, lidar_sensor_snapshot=ss)
    elif case == "snapshot -1":
        ss = a["camera_sensor_snapshot"].copy()
        ss[0, 1] = -1
        _rewrite(src, dst, camera_sensor_snapshot=ss)
    elif case == "camera observation on a lidar":
        ss = a["camera_sensor_snapshot"].copy()
        ss[0, 0] = 0
        _rewrite(src, dst, camera_sensor_snapshot=ss)
    elif case == "zip bomb":
        _zip_bomb(src, dst)
    elif case == "lying npy header":
        _lying_npy(src, dst)
    elif case == "points as strings":
        _rewrite(src, dst, lidar_points=a["lidar_points"].astype(str))
    elif case == "indices as floats":
        _rewrite(src, dst, lidar_sensor_snapshot=a["lidar_sensor_snapshot"].astype(float))
    elif case == "pickled object array":
        b = dict(a)
        b["lidar_points"] = np.array([object(), 1], dtype=object)
        np.savez(dst, **b)  # written with pickle (the default allow_pickle=True for saving)
    elif case == "counts do not add up":
        c = a["lidar_counts"].copy()
        c[0] += 5
        _rewrite(src, dst, lidar_counts=c)
    elif case == "NaN points":
        p = a["lidar_points"].copy()
        p[3] = np.nan
        _rewrite(src, dst, lidar_points=p)
    elif case == "prior sigma 0":
        _rewrite(src, dst, prior_sensor=np.array([1]), prior_rt=np.zeros((1, 6)), prior_sigma=np.zeros((1, 6)))
    elif case == "missing member":
        _rewrite(src, dst, lidar_planes=None)
    elif case == "wrong shape":
        _rewrite(src, dst, lidar_planes=a["lidar_planes"][:, :3])
    elif case == "intrinsics of the wrong lens model":
        k = next(n for n in a if n.startswith("intrinsics_"))
        _rewrite(src, dst, **{k: a[k][:4]})
    elif case == "asymmetric intrinsics covariance":
        k = next(n for n in a if n.startswith("intrinsics_"))
        m = json.loads(str(a["meta"]))
        m["sensors"][int(k.rsplit("_", 1)[1])]["has_intrinsics_covariance"] = True
        n = len(a[k])
        _rewrite(src, dst, meta=np.array(json.dumps(m)), **{k.replace("intrinsics_", "intrinsics_covariance_"):
                                                           np.triu(np.ones((n, n)))})
    elif case == "version 99":
        _rewrite(src, dst, meta=_meta(src, version=99))
    elif case == "config out of range":
        m = json.loads(str(a["meta"]))
        m["config"]["solve"]["outlier_sigma"] = float("nan")
        _rewrite(src, dst, meta=np.array(json.dumps(m)))
    elif case == "deeply nested meta":
        _rewrite(src, dst, meta=np.array("[" * 100_000 + "]" * 100_000))
    elif case == "no sensors":
        _rewrite(src, dst, meta=_meta(src, sensors=[]))
    else:
        raise AssertionError(case)


DUMPS = ["truncated", "empty file", "not a zip", "sensor 99", "snapshot -1", "camera observation on a lidar",
         "zip bomb", "lying npy header", "points as strings", "indices as floats", "pickled object array",
         "counts do not add up", "NaN points", "prior sigma 0", "missing member", "wrong shape",
         "intrinsics of the wrong lens model", "asymmetric intrinsics covariance", "version 99", "config out of range", "deeply nested meta",
         "no sensors"]


@pytest.mark.parametrize("case", DUMPS)
def test_tampered_dump_replay_is_one_line(capfd, tmp_path, dump, case):
    bad = tmp_path / "problem.npz"
    _tamper(case, dump, bad)
    before = sorted(tmp_path.iterdir())
    _one_line(capfd, ["replay", bad], "problem.npz")
    assert sorted(tmp_path.iterdir()) == before  # nothing written beside it


def test_genuine_dump_replays(capfd, dump):
    """The control: the untampered dump replays with exit 0 (the harness can tell)."""
    assert main(["replay", str(dump), "--fit-seed"]) == 0
    assert capfd.readouterr().err == ""


def test_fleet_manifest_and_rig_file_refuse_alias_bombs(tmp_path):
    """The fleet manifest and the simulator's rig file are user YAML too: the config's loader refuses
    aliases of lists and mappings (nested ones expand exponentially) there as well."""
    from clcgraph.errors import InputError
    from clcgraph.fleet import Manifest
    from clcgraph.sim.rig import load_rig

    bomb = "a: &a [x, x]\nb: &b [*a, *a]\nc: &c [*b, *b]\n"
    (tmp_path / "m.yaml").write_text(bomb + "vehicles: []\n")
    (tmp_path / "r.yaml").write_text(bomb)
    for path, load in ((tmp_path / "m.yaml", Manifest.load), (tmp_path / "r.yaml", load_rig)):
        with pytest.raises(InputError, match=r"alias \*a of a mapping or list") as e:
            load(path)
        assert str(path) in str(e.value) and "\n" not in str(e.value)


def test_calibration_files_refuse_alias_bombs_and_ours_have_no_aliases(tmp_path):
    """A calibration.yaml handed to load_result or compare is user YAML too: aliases of lists and
    mappings are refused in one line naming the file; the writer never emits one (a list used
    twice is written twice), so every calibration clcgraph wrote still loads."""
    import yaml

    from clcgraph import compare, load_result
    from clcgraph.config import SafeDumperNoAliases
    from clcgraph.errors import ClcgraphError

    bomb = tmp_path / "calibration.yaml"
    bomb.write_text("a: &a [x, x]\nb: &b [*a, *a]\nsensors: *b\n")
    for load in (load_result, lambda p: compare(p, p)):
        with pytest.raises(ClcgraphError, match=r"alias \*a of a mapping or list") as e:
            load(bomb)
        assert str(bomb) in str(e.value) and "\n" not in str(e.value)
    shared = [1.0, 2.0]
    assert "*" not in yaml.dump({"x": shared, "y": shared}, Dumper=SafeDumperNoAliases)
