"""Robots from URDF: links, joints, limits, forward kinematics, footprint and sensors on named links.

A :class:`Robot` is read once from a URDF with yourdfpy (parsing only; no meshes are loaded) and then
answers forward kinematics with its own small, fast tree walk (``T_base_link`` for every link at a
joint configuration). Two robots ship with PreSim (``presim/sim/robots/``):

- ``presim_bot.urdf``: a round mobile base (footprint radius 0.25 m), a pan/tilt head and an RGB-D
  camera whose optical centre is 1.10 m above the floor at zero joint angles;
- ``free_camera.urdf``: a free-flying 6-DoF camera rig for captures without a floor.

Frames (REP-103): ``base_link`` x forward, y left, z up, origin on the floor under the base centre;
``*_optical_frame`` links are OpenCV camera frames.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from presim.geometry import compose

__all__ = [
    "ROBOTS_DIR",
    "DEFAULT_ROBOT_URDF",
    "FREE_CAMERA_URDF",
    "JointInfo",
    "RobotConfig",
    "Robot",
    "load_robot",
    "default_robot",
    "free_camera_rig",
    "robot_for_scene",
]

ROBOTS_DIR = Path(__file__).resolve().parent / "robots"
DEFAULT_ROBOT_URDF = ROBOTS_DIR / "presim_bot.urdf"
FREE_CAMERA_URDF = ROBOTS_DIR / "free_camera.urdf"

_DRIVES = ("diff", "holonomic", "free")


@dataclass(frozen=True)
class JointInfo:
    """One URDF joint, as the simulator uses it."""

    name: str
    type: str
    """URDF type: revolute, continuous, prismatic, fixed (floating/planar are treated as fixed)."""
    parent: str
    child: str
    T_parent_joint: np.ndarray
    """4x4 joint origin in the parent link frame."""
    axis: np.ndarray
    """(3,) unit axis in the joint frame."""
    lower: float
    """Position limit (rad or m); -inf when unlimited (continuous)."""
    upper: float
    velocity_limit: float
    """rad/s or m/s; inf when the URDF gives none (or 0)."""

    @property
    def movable(self) -> bool:
        return self.type in ("revolute", "continuous", "prismatic")


@dataclass(frozen=True)
class RobotConfig:
    """How the simulator treats a URDF."""

    drive: str = "diff"
    """Base motion model: ``diff`` (differential drive: vy is clipped to 0), ``holonomic``
    (vx, vy, wz) or ``free`` (6-DoF flying rig: no floor, no collisions)."""
    camera_link: str = "camera_optical_frame"
    """Link the RGB-D camera is mounted on. Its frame must be an OpenCV optical frame (z forward);
    for a ROS body-frame link (x forward) name it and set ``camera_link_is_optical=False``."""
    camera_link_is_optical: bool = True
    """False: ``camera_link`` is a REP-103 body frame (x forward, z up); the optical rotation is
    appended by the simulator."""
    footprint_radius_m: float | None = None
    """Radius of the circle the base occupies on the floor; None = from the base link's collision
    geometry (cylinder radius, half box diagonal, sphere radius)."""
    height_m: float | None = None
    """Robot height used for the obstacle band; None = top of all collision geometry at zero joints."""
    initial_joint_positions: tuple[tuple[str, float], ...] = ()
    """(joint name, position) pairs applied at reset; other joints start at 0 (clipped to limits)."""


# REP-103 body frame (x fwd, y left, z up) -> OpenCV optical frame (x right, y down, z fwd).
T_BODY_OPTICAL = np.array(
    [[0.0, 0.0, 1.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
)


def _axis_angle(axis: np.ndarray, angle: float) -> np.ndarray:
    x, y, z = axis
    c, s = np.cos(angle), np.sin(angle)
    C = 1.0 - c
    return np.array([
        [c + x * x * C, x * y * C - z * s, x * z * C + y * s],
        [y * x * C + z * s, c + y * y * C, y * z * C - x * s],
        [z * x * C - y * s, z * y * C + x * s, c + z * z * C],
    ])


class Robot:
    """A URDF robot: kinematic tree, joint limits, footprint, camera mount.

    Example:
        >>> robot = default_robot()
        >>> robot.fk()["camera_optical_frame"][:3, 3]      # doctest: +SKIP
        array([0.08, 0.  , 1.1 ])
    """

    def __init__(self, urdf_path: Path, urdf_xml: str, joints: list[JointInfo], links: list[str],
                 root: str, config: RobotConfig, footprint_radius_m: float, height_m: float):
        self.urdf_path = urdf_path
        self.urdf_xml = urdf_xml
        self.joints = joints
        self.links = links
        self.root = root
        self.config = config
        self.footprint_radius_m = float(footprint_radius_m)
        self.height_m = float(height_m)
        self.movable_joints = [j for j in joints if j.movable]
        self.joint_names = tuple(j.name for j in self.movable_joints)
        self._joint_idx = {n: i for i, n in enumerate(self.joint_names)}
        self._fk_last: tuple[bytes, dict[str, np.ndarray]] | None = None  # fk's last (q, poses)
        self.lower = np.array([j.lower for j in self.movable_joints], dtype=np.float64)
        self.upper = np.array([j.upper for j in self.movable_joints], dtype=np.float64)
        self.velocity_limits = np.array([j.velocity_limit for j in self.movable_joints], dtype=np.float64)
        # Topological order (parents before children) for the FK walk.
        children: dict[str, list[JointInfo]] = {}
        for j in joints:
            children.setdefault(j.parent, []).append(j)
        order: list[JointInfo] = []
        stack = [root]
        while stack:
            link = stack.pop()
            for j in children.get(link, []):
                order.append(j)
                stack.append(j.child)
        self._fk_order = order
        self.link_parents = {j.child: j.parent for j in joints}
        if config.camera_link not in self.links:
            raise ValueError(
                f"{urdf_path}: camera link '{config.camera_link}' is not a link of this URDF "
                f"(links: {', '.join(self.links)})"
            )

    # ---- names ---------------------------------------------------------------------------------
    @property
    def drive(self) -> str:
        return self.config.drive

    @property
    def camera_link(self) -> str:
        return self.config.camera_link

    def joint_index(self, name: str) -> int:
        """Position of movable joint ``name`` in joint vectors; ValueError for unknown names."""
        if name not in self._joint_idx:
            raise ValueError(
                f"{self.urdf_path.name}: unknown or fixed joint '{name}' "
                f"(movable joints: {', '.join(self.joint_names) or 'none'})"
            )
        return self._joint_idx[name]

    def check_link(self, name: str) -> str:
        if name not in self.links:
            raise ValueError(f"{self.urdf_path.name}: unknown link '{name}' (links: {', '.join(self.links)})")
        return name

    def initial_joint_positions(self) -> np.ndarray:
        q = np.zeros(len(self.joint_names))
        for name, value in self.config.initial_joint_positions:
            q[self.joint_index(name)] = value
        return self.clip_joints(q)

    def clip_joints(self, q: np.ndarray) -> np.ndarray:
        return np.clip(q, self.lower, self.upper)

    # ---- kinematics ----------------------------------------------------------------------------
    def fk(self, q: np.ndarray | None = None) -> dict[str, np.ndarray]:
        """``T_base_link`` (4x4) of every link at joint positions ``q`` ((J,) in ``joint_names``
        order; None = zeros). The root link maps to the identity."""
        if q is None:
            q = np.zeros(len(self.joint_names))
        q = np.asarray(q, dtype=np.float64)
        if q.shape != (len(self.joint_names),):
            raise ValueError(f"expected {len(self.joint_names)} joint positions {self.joint_names}, got {q.shape}")
        # A robot that does not move its joints asks for the same q every step: the last result,
        # as fresh copies (the caller owns what it gets).
        key = q.tobytes()
        last = self._fk_last
        if last is not None and last[0] == key:
            return {name: T.copy() for name, T in last[1].items()}
        out = {self.root: np.eye(4)}
        for j in self._fk_order:
            T = out[j.parent] @ j.T_parent_joint
            if j.movable:
                motion = np.eye(4)
                qi = q[self._joint_idx[j.name]]
                if j.type == "prismatic":
                    motion[:3, 3] = j.axis * qi
                else:
                    motion[:3, :3] = _axis_angle(j.axis, qi)
                T = T @ motion
            out[j.child] = T
        self._fk_last = (key, {name: T.copy() for name, T in out.items()})
        return out

    def T_base_camera(self, q: np.ndarray | None = None, link_poses: dict[str, np.ndarray] | None = None) -> np.ndarray:
        """4x4 pose of the camera's OpenCV optical frame in the base frame."""
        poses = link_poses if link_poses is not None else self.fk(q)
        T = poses[self.camera_link]
        return T if self.config.camera_link_is_optical else compose(T, T_BODY_OPTICAL)


def _geometry_extent(geom, T_link_geom: np.ndarray) -> tuple[float, float]:
    """(horizontal radius about the link's z axis, top z) of a primitive collision geometry."""
    c = T_link_geom[:3, 3]
    if geom.cylinder is not None:
        r, h = geom.cylinder.radius, geom.cylinder.length
        a = T_link_geom[:3, 2]  # cylinder axis in the link frame
        top = c[2] + abs(a[2]) * h / 2 + r * np.sqrt(max(0.0, 1.0 - a[2] ** 2))
        horiz = np.hypot(*c[:2]) + r + np.hypot(*a[:2]) * h / 2
        return float(horiz), float(top)
    if geom.sphere is not None:
        r = geom.sphere.radius
        return float(np.hypot(*c[:2]) + r), float(c[2] + r)
    if geom.box is not None:
        s = np.asarray(geom.box.size) / 2.0
        corners = np.array([[x, y, z] for x in (-s[0], s[0]) for y in (-s[1], s[1]) for z in (-s[2], s[2])])
        p = corners @ T_link_geom[:3, :3].T + c
        return float(np.hypot(p[:, 0], p[:, 1]).max()), float(p[:, 2].max())
    return 0.0, -np.inf  # meshes: not measured here (set footprint/height in RobotConfig)


def load_robot(urdf_path: str | Path = DEFAULT_ROBOT_URDF, config: RobotConfig = RobotConfig()) -> Robot:
    """Read a URDF file into a :class:`Robot`.

    Raises FileNotFoundError for a missing file and ValueError naming the file for bad URDFs:
    unparsable XML, xacro files (``$(...)`` substitutions: run ``xacro`` first), an unknown drive,
    an unknown camera link or unknown joints in ``initial_joint_positions``.
    """
    import yourdfpy

    path = Path(urdf_path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: URDF file not found")
    if config.drive not in _DRIVES:
        raise ValueError(f"unknown drive '{config.drive}' (choose from {', '.join(_DRIVES)})")
    xml = path.read_text(encoding="utf-8", errors="replace")
    if "$(" in xml or "xacro:" in xml:
        raise ValueError(
            f"{path}: this is a xacro file ($(...) substitutions / xacro: tags), which URDF readers do "
            f"not expand; convert it first: `xacro {path.name} > robot.urdf`"
        )
    try:
        urdf = yourdfpy.URDF.load(str(path), build_scene_graph=False, load_meshes=False,
                                  load_collision_meshes=False)
    except Exception as e:  # yourdfpy raises lxml / assertion / key errors for broken files
        raise ValueError(f"{path}: not a valid URDF ({type(e).__name__}: {e})") from e
    rob = urdf.robot
    links = [lk.name for lk in rob.links]
    if not links:
        raise ValueError(f"{path}: URDF has no links")
    joints: list[JointInfo] = []
    for j in rob.joints:
        if j.parent not in links or j.child not in links:
            raise ValueError(f"{path}: joint '{j.name}' connects unknown links '{j.parent}' -> '{j.child}'")
        T = np.asarray(j.origin if j.origin is not None else np.eye(4), dtype=np.float64)
        axis = np.asarray(j.axis if j.axis is not None else [1.0, 0.0, 0.0], dtype=np.float64)
        axis = axis / max(np.linalg.norm(axis), 1e-12)
        jtype = j.type if j.type in ("revolute", "continuous", "prismatic") else "fixed"
        lo, hi, vel = -np.inf, np.inf, np.inf
        if j.limit is not None:
            if jtype != "continuous" and j.limit.lower is not None and j.limit.upper is not None:
                lo, hi = float(j.limit.lower), float(j.limit.upper)
            if j.limit.velocity:
                vel = float(j.limit.velocity)
        joints.append(JointInfo(j.name, jtype, j.parent, j.child, T, axis, lo, hi, vel))
    child_links = {j.child for j in joints}
    roots = [lk for lk in links if lk not in child_links]
    if len(roots) != 1:
        raise ValueError(f"{path}: a URDF needs exactly one root link, found {roots}")
    root = roots[0]

    # Footprint and height from primitive collision geometry at zero joints.
    tmp = Robot(path, xml, joints, links, root, RobotConfig(drive=config.drive, camera_link=links[0]), 0.0, 0.0)
    poses = tmp.fk()
    radius, top = 0.0, -np.inf
    for lk in rob.links:
        for col in lk.collisions or []:
            T = poses[lk.name] @ np.asarray(col.origin if col.origin is not None else np.eye(4))
            r, z = _geometry_extent(col.geometry, T)
            if lk.name == root:
                radius = max(radius, r)
            top = max(top, z)
    if config.footprint_radius_m is not None:
        radius = config.footprint_radius_m
    height = config.height_m if config.height_m is not None else (top if np.isfinite(top) else 0.0)
    if config.drive != "free" and radius <= 0.0:
        raise ValueError(
            f"{path}: could not measure the base footprint from primitive collision geometry of "
            f"'{root}'; set RobotConfig.footprint_radius_m (and height_m)"
        )
    robot = Robot(path, xml, joints, links, root, config, radius, height)
    robot.initial_joint_positions()  # validates joint names early
    return robot


def default_robot(drive: str = "diff", initial_tilt_rad: float = 0.0) -> Robot:
    """The shipped ``presim_bot`` (camera optical centre 1.10 m above the floor at zero joints)."""
    cfg = RobotConfig(drive=drive, initial_joint_positions=(("head_tilt_joint", initial_tilt_rad),))
    return load_robot(DEFAULT_ROBOT_URDF, cfg)


def free_camera_rig() -> Robot:
    """The shipped 6-DoF free-flying camera rig (no floor, no collisions)."""
    return load_robot(FREE_CAMERA_URDF, RobotConfig(drive="free"))


def robot_for_scene(name: str | None, has_floor: bool, drive: str = "diff", camera_link: str | None = None,
                    camera_link_is_optical: bool = True, head_tilt_rad: float | None = None) -> Robot:
    """The robot a user names: ``'default'`` (presim_bot), ``'free'`` (the free camera rig) or a
    URDF path; None picks presim_bot for a scene with a floor and the free rig for one without.

    ``drive``, ``camera_link`` and ``camera_link_is_optical`` go to :class:`RobotConfig` (the free rig
    ignores them); ``head_tilt_rad`` starts a robot that has a ``head_tilt_joint`` at that tilt
    (positive looks down). Missing files raise FileNotFoundError, bad URDFs ValueError.
    """
    if name is None:
        name = "default" if has_floor else "free"
    if name == "free":
        return free_camera_rig()
    urdf = DEFAULT_ROBOT_URDF if name == "default" else Path(name)
    cfg = RobotConfig(drive=drive, camera_link=camera_link or RobotConfig.camera_link,
                      camera_link_is_optical=camera_link_is_optical if camera_link else True)
    robot = load_robot(urdf, cfg)
    if head_tilt_rad is not None and "head_tilt_joint" in robot.joint_names:
        robot = load_robot(urdf, replace(cfg, initial_joint_positions=(("head_tilt_joint", float(head_tilt_rad)),)))
    return robot
