"""The sample room's layout (parts, materials, objects, lights) and the hand-held capture trajectory.

Both are pure, deterministic functions of the seed (and :class:`SampleSceneConfig`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from presim.capture.procedural import (
    Material, Mesh, box_mesh, cylinder_mesh, ellipsoid_mesh, merge_meshes, rock_mesh,
)
from presim.capture.sample_scene.config import SampleSceneConfig
from presim.geometry import compose, look_at, make_pose, rotation_z

__all__ = ["LayoutPart", "SampleLayout", "sample_layout", "capture_trajectory"]


@dataclass(frozen=True)
class LayoutPart:
    """One part of the room before ray casting: mesh in its own frame, world pose, material."""

    name: str
    kind: str
    mesh: Mesh                  # in the part frame
    T_world_part: np.ndarray
    material: Material
    obj_id: int = 0


@dataclass
class SampleLayout:
    """The room of one seed: its parts, the table and objects, and the lights."""

    parts: list[LayoutPart]
    table_top_z_m: float
    table_centre_xy: np.ndarray
    objects_centre: np.ndarray
    lights: list[dict] = field(default_factory=list)
    ambient: float = 0.3


def _hsv(h: float, s: float, v: float) -> tuple[float, float, float]:
    i = int(h * 6) % 6
    f = h * 6 - np.floor(h * 6)
    p, q, t = v * (1 - s), v * (1 - f * s), v * (1 - (1 - f) * s)
    return [(v, t, p), (q, v, p), (p, v, t), (p, q, v), (t, p, v), (v, p, q)][i]


def sample_layout(seed: int, config: SampleSceneConfig = SampleSceneConfig()) -> SampleLayout:
    """The room for ``seed``: parts with meshes, world poses and materials (pure, deterministic)."""
    rng = np.random.default_rng([seed, 1])
    I = np.eye(4)
    parts: list[LayoutPart] = []

    def add(name, kind, mesh, mat, T=I, obj_id=0):
        parts.append(LayoutPart(name, kind, mesh, np.asarray(T, dtype=np.float64), mat, obj_id))

    X, Y, H, t = 2.5, 2.0, 2.6, 0.1  # interior half-sizes, height, wall thickness
    door_x = (1.2, 2.1)
    corr_y = 3.4
    ext_y = corr_y + t if config.door else Y + t
    wall_hue = rng.uniform(0, 1)
    plaster = Material("plaster", _hsv(wall_hue, 0.12, 0.75), _hsv(wall_hue + 0.05, 0.2, 0.6), 0.4, 1.0)
    plaster2 = Material("wallpaper", _hsv(wall_hue + 0.5, 0.2, 0.75), _hsv(wall_hue + 0.45, 0.45, 0.5), 0.16, 2.0)
    brick = Material("brick", _hsv(0.03 + 0.03 * rng.uniform(), 0.65, 0.55), (0.7, 0.68, 0.62), 0.22, 3.0)
    floor_mat = Material("planks", _hsv(0.08, 0.55, 0.55), _hsv(0.07, 0.6, 0.3), 0.14, 4.0)
    add("floor", "floor", box_mesh([-X - t, -Y - t, -0.05], [X + t, ext_y, 0.0]), floor_mat)
    if config.ceiling:
        add("ceiling", "ceiling", box_mesh([-X - t, -Y - t, H], [X + t, ext_y, H + 0.05]),
            Material("plaster", (0.8, 0.8, 0.78), (0.7, 0.7, 0.68), 0.5, 5.0))
    add("wall_south", "wall", box_mesh([-X - t, -Y - t, 0], [X + t, -Y, H]), brick)
    add("wall_west", "wall", box_mesh([-X - t, -Y - t, 0], [-X, Y + t, H]), plaster)
    add("wall_east", "wall", box_mesh([X, -Y - t, 0], [X + t, Y + t, H]), plaster)
    if config.door:
        add("wall_north_a", "wall", box_mesh([-X - t, Y, 0], [door_x[0], Y + t, H]), plaster2)
        add("wall_north_b", "wall", box_mesh([door_x[1], Y, 0], [X + t, Y + t, H]), plaster2)
        add("wall_north_lintel", "wall", box_mesh([door_x[0], Y, 2.05], [door_x[1], Y + t, H]), plaster2)
        cx0, cx1 = door_x[0] - 0.05, door_x[1] + 0.05
        add("corridor_west", "wall", box_mesh([cx0 - t, Y + t, 0], [cx0, ext_y, H]), plaster)
        add("corridor_east", "wall", box_mesh([cx1, Y + t, 0], [cx1 + t, ext_y, H]), plaster)
        add("corridor_end", "wall", box_mesh([cx0 - t, corr_y, 0], [cx1 + t, ext_y, H]), brick)
    else:
        add("wall_north", "wall", box_mesh([-X - t, Y, 0], [X + t, Y + t, H]), plaster2)

    # Decor on the walls.
    add("poster", "decor", box_mesh([X - 0.012, -0.7, 1.0], [X, 0.4, 1.75]),
        Material("poster", (0.9, 0.85, 0.8), scale_m=0.35, salt=6.0 + rng.uniform(0, 50)))
    add("tv", "decor", box_mesh([-X, -0.55, 0.95], [-X + 0.05, 0.55, 1.6]),
        Material("dark", (0.025, 0.025, 0.03), scale_m=0.3, salt=7.0))

    # Table (jittered), rug under it.
    tc = np.array([0.3, -0.25]) + rng.uniform(-0.15, 0.15, 2)
    top_z = 0.75
    tl, tw, th = 1.2, 0.8, 0.04
    wood = Material("wood", _hsv(0.07, 0.55, 0.6), _hsv(0.06, 0.65, 0.35), 0.08, 8.0)
    add("rug", "decor", box_mesh([tc[0] - 1.0, tc[1] - 0.7, 0.0], [tc[0] + 1.0, tc[1] + 0.7, 0.008]),
        Material("checker", _hsv(rng.uniform(), 0.5, 0.5), (0.75, 0.72, 0.65), 0.12, 9.0))
    add("table_top", "furniture", box_mesh([tc[0] - tl / 2, tc[1] - tw / 2, top_z - th],
                                           [tc[0] + tl / 2, tc[1] + tw / 2, top_z]), wood)
    leg = Material("painted", (0.08, 0.08, 0.09), scale_m=0.05, salt=10.0)
    for i, (sx, sy) in enumerate(((-1, -1), (1, -1), (1, 1), (-1, 1))):
        x = tc[0] + sx * (tl / 2 - 0.06)
        y = tc[1] + sy * (tw / 2 - 0.06)
        add(f"table_leg_{i}", "furniture",
            box_mesh([x - 0.025, y - 0.025, 0.0], [x + 0.025, y + 0.025, top_z - th]), leg)

    # Bookshelf against the north wall (open front: non-convex furniture).
    sx0, sx1, sy0, sy1, sh = -2.1, -1.2, Y - 0.35, Y, 1.8
    shelf_wood = Material("wood", _hsv(0.09, 0.35, 0.75), _hsv(0.08, 0.45, 0.5), 0.06, 11.0)
    panels = [box_mesh([sx0, sy0, 0], [sx0 + 0.02, sy1, sh]), box_mesh([sx1 - 0.02, sy0, 0], [sx1, sy1, sh]),
              box_mesh([sx0, sy1 - 0.01, 0], [sx1, sy1, sh])]
    for z in (0.0, 0.45, 0.9, 1.35, sh - 0.02):
        panels.append(box_mesh([sx0 + 0.02, sy0, z], [sx1 - 0.02, sy1 - 0.01, z + 0.02]))
    add("shelf", "furniture", merge_meshes(panels), shelf_wood)
    books = []
    for z in (0.02, 0.47, 0.92, 1.37):
        x = sx0 + 0.03
        while x < sx1 - 0.12:
            w = rng.uniform(0.025, 0.05)
            hb = rng.uniform(0.2, 0.32)
            books.append(box_mesh([x, sy0 + 0.06, z], [x + w, sy1 - 0.03, z + hb]))
            x += w + 0.003
    add("books", "furniture", merge_meshes(books), Material("books", (0.5, 0.5, 0.5), scale_m=0.035, salt=12.0))

    # Sideboard against the east wall.
    add("sideboard", "furniture", box_mesh([X - 0.45, -1.85, 0.0], [X, -0.85, 0.8]),
        Material("painted", _hsv(rng.uniform(), 0.45, 0.55), scale_m=0.2, salt=13.0))

    # Obstacles on the floor: cardboard boxes and a bin, near walls and corners.
    card = Material("cardboard", (0.55, 0.38, 0.2), (0.45, 0.3, 0.15), 0.1, 14.0)
    for i, (bx, by, size) in enumerate(((-2.05, -1.55, 0.45), (-1.45, -1.7, 0.32), (1.1, 1.55, 0.38))):
        bx += rng.uniform(-0.05, 0.05)
        by += rng.uniform(-0.05, 0.05)
        hgt = size * rng.uniform(0.7, 1.0)
        yaw = rng.uniform(-0.4, 0.4)
        T = make_pose(rotation_z(yaw), [bx, by, 0.0])
        add(f"box_{i}", "obstacle", box_mesh([-size / 2, -size / 2.4, 0], [size / 2, size / 2.4, hgt]), card, T)
    add("bin", "obstacle", cylinder_mesh(0.16, 0.42, 40),
        Material("bands", (0.2, 0.35, 0.25), (0.15, 0.25, 0.2), 0.25, 15.0),
        make_pose(np.eye(3), [-2.1, 0.9 + rng.uniform(-0.1, 0.1), 0.0]))

    # Objects on the table.
    specs = _object_specs(rng)[: config.num_objects]
    placed: list[tuple[np.ndarray, float]] = []
    for obj_id, (name, mesh, mat, r_bound) in enumerate(specs, start=1):
        for _ in range(1000):
            xy = tc + rng.uniform([-tl / 2 + 0.15, -tw / 2 + 0.12], [tl / 2 - 0.15, tw / 2 - 0.12])
            if all(np.linalg.norm(xy - q) > r_bound + rq + 0.03 for q, rq in placed):
                break
        placed.append((xy, r_bound))
        T = make_pose(rotation_z(rng.uniform(-np.pi, np.pi)), [xy[0], xy[1], top_z])
        add(name, "object", mesh, mat, T, obj_id)

    objects_centre = np.array([*np.mean([q for q, _ in placed], axis=0), top_z + 0.08])
    lights = [
        {"pos": [0.0, 0.0, 2.4], "intensity": 1.7, "shadow": True},
        {"pos": [-1.8, 1.2, 2.35], "intensity": 0.5, "shadow": False},
        {"pos": [1.8, -1.5, 2.35], "intensity": 0.4, "shadow": False},
    ]
    return SampleLayout(parts, top_z, tc, objects_centre, lights, ambient=0.28)


def _object_specs(rng: np.random.Generator) -> list[tuple[str, Mesh, Material, float]]:
    """(name, mesh in object frame with the bottom on z = 0, material, bounding radius in xy)."""
    hues = (rng.uniform() + np.arange(5) / 5.0 + rng.uniform(-0.05, 0.05, 5)) % 1.0
    box = box_mesh([-0.08, -0.03, 0.0], [0.08, 0.03, 0.22])
    can = cylinder_mesh(0.034, 0.115, 48)
    # Non-convex "U" bracket: a base with two uprights (non-overlapping boxes).
    bracket = merge_meshes([box_mesh([-0.09, -0.03, 0.0], [0.09, 0.03, 0.03]),
                            box_mesh([-0.09, -0.03, 0.03], [-0.06, 0.03, 0.11]),
                            box_mesh([0.06, -0.03, 0.03], [0.09, 0.03, 0.11])])
    ball = ellipsoid_mesh([0.055, 0.055, 0.052], 3)
    rock = rock_mesh(0.06, rng, 3)
    return [
        ("cereal_box", box, Material("label", _hsv(hues[0], 0.8, 0.75), _hsv(hues[0] + 0.1, 0.6, 0.35), 0.09, 20.0),
         float(np.hypot(0.08, 0.03))),
        ("soup_can", can, Material("bands", _hsv(hues[1], 0.8, 0.7), _hsv(hues[1] + 0.5, 0.5, 0.8), 0.04, 21.0), 0.034),
        ("bracket", bracket, Material("checker", _hsv(hues[2], 0.85, 0.75), (0.85, 0.85, 0.82), 0.02, 22.0),
         float(np.hypot(0.09, 0.03))),
        ("ball", ball,
         Material("beachball", _hsv(hues[3], 0.85, 0.8), _hsv(hues[3] + 0.33, 0.8, 0.7), 0.05, 23.0), 0.055),
        ("rock", rock, Material("stone", _hsv(hues[4], 0.3, 0.45), _hsv(hues[4], 0.2, 0.25), 0.03, 24.0),
         float(np.linalg.norm(rock.vertices[:, :2], axis=1).max())),
    ]


# ---- trajectory ---------------------------------------------------------------------------------

def capture_trajectory(layout: SampleLayout, num_frames: int, seed: int) -> np.ndarray:
    """(N, 4, 4) T_world_cam of a hand-held walk: a loop around the room looking at the walls, turning
    to look at the table, then a spiral in for close views of the objects. Equal steps along the path."""
    if num_frames < 2:
        raise ValueError(f"num_frames must be >= 2, got {num_frames}")
    rng = np.random.default_rng([seed, 2])
    s = np.linspace(0.0, 1.0, 4001)
    theta0 = rng.uniform(0, 2 * np.pi)
    theta = theta0 + 2 * np.pi * 1.05 * s
    w = np.clip((s - 0.55) / 0.3, 0, 1)
    w = w * w * (3 - 2 * w)
    room_c = np.array([0.0, 0.0])
    tc = layout.objects_centre[:2]
    centre = (1 - w)[:, None] * room_c + w[:, None] * tc
    rx = (1 - w) * 1.45 + w * 0.8
    ry = (1 - w) * 1.05 + w * 0.8
    xy = centre + np.stack([rx * np.cos(theta), ry * np.sin(theta)], 1)
    ph = rng.uniform(0, 2 * np.pi, 4)
    z = (1 - w) * 1.4 + w * 1.15 + 0.03 * np.sin(2 * np.pi * 3 * s + ph[0])
    pos = np.concatenate([xy, z[:, None]], 1)
    # Equal arc-length steps.
    seg = np.linalg.norm(np.diff(pos, axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(seg)])
    targets = np.linspace(0, arc[-1], num_frames)
    idx = np.searchsorted(arc, targets).clip(0, len(s) - 1)
    s_f, theta_f, pos_f = s[idx], theta[idx], pos[idx]

    # Look direction: yaw from "outward + a bit forward" (walls) to "at the objects" (a = 1),
    # turning through the walking direction so the rotation is continuous.
    ramp = np.clip((s_f - 0.3) / 0.5, 0, 1)
    a = 0.4 + 0.6 * ramp * ramp * (3 - 2 * ramp)
    to_obj = layout.objects_centre[None, :] - pos_f
    yaw_obj = np.arctan2(to_obj[:, 1], to_obj[:, 0])
    d = np.mod(yaw_obj - theta_f, 2 * np.pi)
    yaw = theta_f + a * d
    pitch_out = np.arctan2(1.0 - pos_f[:, 2], 2.0)
    pitch_in = np.arctan2(to_obj[:, 2], np.linalg.norm(to_obj[:, :2], axis=1))
    pitch = (1 - a) * pitch_out + a * pitch_in
    pitch += np.radians(2.0) * np.sin(2 * np.pi * 2 * s_f + ph[1])
    roll = np.radians(2.0) * np.sin(2 * np.pi * 2.5 * s_f + ph[2])
    out = np.empty((num_frames, 4, 4))
    for i in range(num_frames):
        f = np.array([np.cos(pitch[i]) * np.cos(yaw[i]), np.cos(pitch[i]) * np.sin(yaw[i]), np.sin(pitch[i])])
        T = look_at(pos_f[i], pos_f[i] + f)
        out[i] = compose(T, make_pose(rotation_z(roll[i]), np.zeros(3)))
    return out
