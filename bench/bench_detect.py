"""Chessboard detection time per 1024x768 image: mrgingham CLI vs OpenCV, 1 and 2 jobs.

Images are rendered here (area-sampled pinhole view of the 10x10 board, random poses,
noise sigma 2 grey levels); detection accuracy vs truth is printed alongside.
"""

from __future__ import annotations

import time

import numpy as np

W, H, F = 1024, 768, 700.0
N_IMAGES = 8


def _render(r, t, rng, S=3):
    import cv2

    from clcgraph.types import BoardGeometry

    board = BoardGeometry()
    R, _ = cv2.Rodrigues(np.asarray(r, float))
    t = np.asarray(t, float)
    s, n = board.square_m, board.corners_x
    cx, cy = (W - 1) / 2, (H - 1) / 2
    off = (np.arange(S) + 0.5) / S - 0.5
    uu, vv = np.meshgrid((np.arange(W)[:, None] + off).ravel(), (np.arange(H)[:, None] + off).ravel())
    d = np.stack([(uu - cx) / F, (vv - cy) / F, np.ones_like(uu)], -1)
    lam = (R[:, 2] @ t) / (d @ R[:, 2])
    pb = (d * lam[..., None] - t) @ R
    x, y = pb[..., 0], pb[..., 1]
    black = ((np.floor(x / s) + np.floor(y / s)) % 2 == 0) & (x >= -s) & (x <= n * s) \
        & (y >= -s) & (y <= n * s)
    on = (x >= -1.5 * s) & (x <= (n + 0.5) * s) & (y >= -1.5 * s) & (y <= (n + 0.5) * s) & (lam > 0)
    val = np.where(on, 230.0, 100.0)
    val[black] = 25.0
    img = val.reshape(H, S, W, S).mean(axis=(1, 3)) + rng.normal(0, 2.0, (H, W))
    pc = board.corners() @ R.T + t
    return np.clip(img, 0, 255).astype(np.uint8), F * pc[:, :2] / pc[:, 2:] + [cx, cy]


def main() -> str:
    from dataclasses import replace

    from clcgraph.config import DetectionOptions
    from clcgraph.frontend.camera_board import detect_corners
    from clcgraph.types import BoardGeometry, Image

    rng = np.random.default_rng(0)
    imgs, truth = [], []
    for k in range(N_IMAGES):
        px, q = _render(rng.normal(0, 0.3, 3), (-0.5 + rng.normal(0, 0.3), -0.45, 2.5 + rng.normal(0, 0.4)), rng)
        imgs.append(Image("cam", k, px, "mono8"))
        truth.append(q)
    rows = []
    for det in ("mrgingham", "opencv"):
        for jobs in (1, 2):
            o = replace(DetectionOptions(), detector=det, jobs=jobs)
            t0 = time.perf_counter()
            out = detect_corners(imgs, o, BoardGeometry())
            dt = time.perf_counter() - t0
            found = [(c, q) for c, q in zip(out, truth) if isinstance(c, np.ndarray)]
            rms = np.sqrt(np.mean([np.mean(np.sum((c - q) ** 2, axis=1)) for c, q in found])) if found else np.nan
            rows.append((det, str(jobs), f"{len(found)}/{len(imgs)}", f"{1000 * dt / len(imgs):.0f}",
                         f"{rms:.3f}"))
    head = ("detector", "jobs", "found", "ms/image (wall)", "RMS px vs truth")
    w = [max(len(r[i]) for r in rows + [head]) for i in range(len(head))]
    fmt = lambda r: " | ".join(c.rjust(w[i]) for i, c in enumerate(r))  # noqa: E731
    return "\n".join([f"{W}x{H} mono8, {N_IMAGES} images per run"]
                     + [fmt(head), "-+-".join("-" * x for x in w)] + [fmt(r) for r in rows])


if __name__ == "__main__":
    print(main())
