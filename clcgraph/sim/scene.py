"""The calibration scene: ground, walls, clutter, a person and the chessboard, for ray casting.

World frame: z up, ground at z = 0; the rig stands near the origin. The board is a thin
box of its physical size (margin included); a person (a round body) stands half a metre behind
one edge of it (someone holding it). Clutter: walls 12-25 m away, parked cars, poles and
boxes whose faces are not board-sized (the segmentation must still never take them).

SYNOPSIS
    scene = make_scene(board, T_world_board, rng)        # open3d RaycastingScene inside
    hits = scene.cast(rays_world (N,6) float32)          # t_hit (N,), geometry ids (N,)
    scene.board_id                                       # geometry id of the board
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry import R_from_r
from ..types import BoardGeometry


def box_mesh(sx, sy, sz, x, y, z, yaw=0.0):
    """Legacy open3d box of size (sx, sy, sz), centred at (x, y) in xy, bottom at z."""
    import open3d as o3d

    m = o3d.geometry.TriangleMesh.create_box(sx, sy, sz)
    m.translate((-sx / 2, -sy / 2, 0))
    m.rotate(R_from_r(np.array([0.0, 0.0, yaw])), center=(0, 0, 0))
    m.translate((x, y, z))
    return m


def cylinder_mesh(r, h, x, y):
    import open3d as o3d

    m = o3d.geometry.TriangleMesh.create_cylinder(r, h, resolution=16)
    m.translate((x, y, h / 2))
    return m


def static_meshes(rng, *, clutter: bool = True, walls_m=(12.0, 25.0), indoor: bool = False,
                  room_m=(6.0, 9.0)) -> list:
    """Ground, walls and clutter (legacy open3d meshes) of one calibration site. ``indoor``: a hall
    closed all round, walls at ``room_m`` (6-9 m) up to a ceiling 3.4-4 m high: every ray of a
    LIDAR returns (outdoors the sky and the gaps between walls return nothing)."""
    meshes = [box_mesh(200, 200, 0.1, 0, 0, -0.1)]  # ground, top at z = 0
    ceiling = rng.uniform(3.4, 4.0) if indoor else None
    if indoor:
        meshes.append(box_mesh(200, 200, 0.1, 0, 0, ceiling))
        walls_m = tuple(room_m)
    if not clutter and not indoor:
        return meshes
    n_walls = 8
    for k in range(n_walls):  # an irregular room of walls at 12-25 m (indoors: meeting at the corners)
        az = 2 * np.pi * (k + rng.uniform(-0.2, 0.2)) / n_walls
        d = rng.uniform(*walls_m)
        w = 2 * d * np.tan(np.pi / n_walls) + (2 * walls_m[1] if indoor else 2.0)
        meshes.append(box_mesh(0.3, w, ceiling + 0.1 if indoor else rng.uniform(3, 8), d * np.cos(az), d * np.sin(az),
                               0, az))
    if not clutter:
        return meshes
    for _ in range(3):  # parked cars: body + cabin, 6-11 m away
        az, d = rng.uniform(0, 2 * np.pi), rng.uniform(6, 11)
        x, y, yaw = d * np.cos(az), d * np.sin(az), rng.uniform(0, np.pi)
        meshes += [box_mesh(4.4, 1.8, 0.9, x, y, 0.25, yaw), box_mesh(2.3, 1.6, 0.6, x, y, 1.15, yaw)]
    for _ in range(6):  # poles and posts
        az, d = rng.uniform(0, 2 * np.pi), rng.uniform(3, 12)
        meshes.append(cylinder_mesh(rng.uniform(0.05, 0.15), rng.uniform(1.0, 4.0), d * np.cos(az), d * np.sin(az)))
    for _ in range(6):  # small boxes, bins, crates (faces well below board size)
        az, d = rng.uniform(0, 2 * np.pi), rng.uniform(2.5, 11)
        s = rng.uniform(0.25, 0.55, 3)
        meshes.append(box_mesh(*s, d * np.cos(az), d * np.sin(az), 0, rng.uniform(0, np.pi)))
    return meshes


def board_mesh(board: BoardGeometry, T_world_board: np.ndarray):
    """The board as a box ``board.back_m`` thick: its front face is the board plane z = 0 (facing -z)."""
    import open3d as o3d

    xmin, xmax, ymin, ymax = board.extent()
    m = o3d.geometry.TriangleMesh.create_box(xmax - xmin, ymax - ymin, max(board.back_m, 1e-4))  # a 0-thick box has no back
    m.translate((xmin, ymin, 0.0))  # board frame: z from 0 (front) to +thickness (back)
    m.transform(T_world_board)
    return m


PERSON_PLACES = ("edge", "behind", "beside", "none")
BODY_RADIUS_M = 0.2


def person_mesh(board: BoardGeometry, T_world_board: np.ndarray, rng, *, place: str = "edge", arm: bool = False):
    """Someone holding the board: a 1.75 m body (a 0.2 m radius cylinder, round like a torso),
    ``place``: "edge" half a metre behind one side edge, "behind" 0.35 m behind the board's
    centre (legs and head show below and above it), "beside" next to a side edge in the
    board's plane. ``arm``: an arm (a 4.5 cm radius cylinder) from the shoulder across the
    nearer side edge, 3 cm in front of the board, its end 6 cm onto it (the hand holding it)."""
    xmin, xmax, ymin, ymax = board.extent()
    side = rng.choice([xmin - 0.05, xmax + 0.05])
    R, t = T_world_board[:3, :3], T_world_board[:3, 3]
    behind = R[:, 2] * np.array([1.0, 1.0, 0.0])
    behind = behind / max(np.linalg.norm(behind), 1e-9)
    ymid = (ymin + ymax) / 2
    if place == "behind":
        p = R @ np.array([(xmin + xmax) / 2, ymid, 0.0]) + t + (0.35 + BODY_RADIUS_M) * behind
    elif place == "beside":
        out = np.sign(side - (xmin + xmax) / 2)
        p = R @ np.array([side + out * (BODY_RADIUS_M + 0.05), ymid, 0.0]) + t
    else:
        p = R @ np.array([side, ymid, 0.0]) + t + 0.5 * behind
    meshes = [cylinder_mesh(BODY_RADIUS_M, 1.75, p[0], p[1])]
    if arm:
        edge = xmin if side < xmin else xmax
        inward = 1.0 if side < xmin else -1.0
        hand = R @ np.array([edge + inward * 0.06, ymid + rng.uniform(-0.2, 0.2) * (ymax - ymin), -0.03]) + t
        shoulder = np.array([p[0], p[1], 1.45])
        shoulder[:2] += (hand[:2] - shoulder[:2]) * BODY_RADIUS_M / max(np.linalg.norm(hand[:2] - shoulder[:2]), 1e-9)
        meshes.append(segment_mesh(0.045, shoulder, hand))
    return meshes


def segment_mesh(r: float, a: np.ndarray, b: np.ndarray):
    """A cylinder of radius r from point a to point b."""
    import open3d as o3d

    d = np.asarray(b, float) - np.asarray(a, float)
    L = float(np.linalg.norm(d))
    m = o3d.geometry.TriangleMesh.create_cylinder(r, L, resolution=12)  # along z, centred at 0
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(z, d / L)
    angle = np.arccos(np.clip(z @ d / L, -1, 1))
    if np.linalg.norm(axis) > 1e-9:
        m.rotate(R_from_r(axis / np.linalg.norm(axis) * angle), center=(0, 0, 0))
    m.translate((np.asarray(a) + np.asarray(b)) / 2)
    return m


def random_board_pose(rng, board: BoardGeometry, origin, *, tilt_max_deg: float = 45.0, distance_m=(2.5, 9.0),
                      height_m=(0.9, 1.9), forward=None, vertical: bool = False,
                      tilt_towards_rad: float | None = None) -> np.ndarray:
    """T_world_board: held ``distance_m`` from ``origin`` (toward ``forward``, else a random azimuth),
    facing it, tilted up to ``tilt_max_deg`` about a random in-plane axis and rolled +-20 deg.
    ``vertical``: the board plane exactly vertical (normal horizontal), turned up to
    ``tilt_max_deg`` about the vertical only. ``tilt_towards_rad``: a planned tilt instead (a
    careful person's capture plan, ``planned_tilt``): about the in-plane axis at that angle
    from the board's horizontal one (0, pi: pitched up or down; +-pi/2: turned left or right),
    by half to all of ``tilt_max_deg``."""
    xmin, xmax, ymin, ymax = board.extent()
    centre_b = np.array([(xmin + xmax) / 2, (ymin + ymax) / 2, 0.0])
    o = np.asarray(origin, float)
    if forward is None:
        az = rng.uniform(-np.pi, np.pi)
        forward = np.array([np.cos(az), np.sin(az), 0.0])
    fwd = np.array([forward[0], forward[1], 0.0])
    fwd /= np.linalg.norm(fwd)
    c = o + fwd * rng.uniform(*distance_m)
    c[2] = rng.uniform(*height_m)
    z = c - o  # board normal away from the sensor (mrcal's board convention)
    if vertical:
        z[2] = 0.0
    z /= np.linalg.norm(z)
    y = np.array([0.0, 0.0, -1.0]) - (np.array([0.0, 0.0, -1.0]) @ z) * z
    y /= np.linalg.norm(y)
    R = np.c_[np.cross(y, z), y, z]
    axis = rng.normal(size=3)
    tilt = rng.uniform(0, 1)  # drawn either way: the later draws stay those of the seed
    if vertical:
        axis = np.array([0.0, 0.0, np.sign(axis[2]) or 1.0])
    elif tilt_towards_rad is not None:  # about the board's horizontal (pitch) or vertical (yaw) axis
        axis = np.cos(tilt_towards_rad) * R[:, 0] + np.sin(tilt_towards_rad) * R[:, 1]
        tilt = 0.5 + 0.5 * tilt
    axis -= (axis @ z) * z
    R = R_from_r(axis / np.linalg.norm(axis) * np.radians(tilt * tilt_max_deg)) @ R
    R = R @ R_from_r(np.array([0.0, 0.0, np.radians(rng.uniform(-20, 20))]))
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, c - R @ centre_b
    return T


def planned_tilt(k: int) -> float:
    """The tilt direction (rad, ``random_board_pose``'s ``tilt_towards_rad``) of board pose k of
    a careful capture: each pose turned a golden angle (137.5 deg) from the last, so any few
    consecutive poses hold boards pitched up and down and turned left and right. A LIDAR sees
    only the board's plane, so its height relative to another sensor comes from pitched boards
    alone: a capture of upright boards and one pitched rests that height on one board."""
    return float(np.radians(137.50776405) * k)


@dataclass
class Scene:
    """A RaycastingScene of static meshes + (optionally) the board and a person."""

    raycasting: object
    board_id: int  # -1 without a board
    person_id: int
    board: BoardGeometry | None = None
    T_world_board: np.ndarray | None = None

    def cast(self, rays: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(t_hit (N,) inf where nothing is hit, geometry id (N,)) for rays (N,6) origin+direction."""
        import open3d as o3d

        hit = self.raycasting.cast_rays(o3d.core.Tensor(np.ascontiguousarray(rays, dtype=np.float32)))
        return hit["t_hit"].numpy().astype(float), hit["geometry_ids"].numpy().astype(np.int64)


def make_scene(board: BoardGeometry, T_world_board: np.ndarray | None, rng, *, clutter: bool = True,
               person: bool | str = True, arm: bool = False, walls_m=(12.0, 25.0),
               static: list | None = None) -> Scene:
    """The scene with the board at T_world_board (None: no board). ``static``: reuse meshes
    from static_meshes() (the same site for every board pose). ``person``: True ("edge"), False
    ("none") or a place of ``PERSON_PLACES``; ``arm``: the person's arm across the board's edge
    (``person_mesh``)."""
    import open3d as o3d

    meshes = static if static is not None else static_meshes(rng, clutter=clutter, walls_m=walls_m)
    rc = o3d.t.geometry.RaycastingScene()
    for m in meshes:
        rc.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(m))
    board_id = person_id = -1
    if T_world_board is not None:
        board_id = int(rc.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(board_mesh(board, T_world_board))))
        place = {True: "edge", False: "none"}.get(person, person)
        if place != "none":
            for m in person_mesh(board, T_world_board, rng, place=place, arm=arm):
                person_id = int(rc.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(m)))
    return Scene(rc, board_id, person_id, board, T_world_board)
