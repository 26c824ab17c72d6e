"""The teleop session: one :class:`~presim.sim.simulator.Simulator` stepped in real time by a thread,
commands from the page applied between steps, the newest frame published (older ones are dropped).

The page's messages arrive already validated (:mod:`presim.outputs.teleop.protocol`); what needs the
simulator (teleport into a wall, recording twice) is checked here and refused with a message to the
client that sent it. Messages that only read (``pose``) or collect poses (``path``) are served to every
client, like snapshots. One client drives at a time (the first to send a command, or the one that pressed
"take control"); every client sees the frames. With no client connected the loop pauses (no CPU
spent on frames nobody sees) unless a recording runs.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from presim.formats.depth_png import encode_depth_png
from presim.formats.tum import tum_line, write_tum
from presim.geometry import make_pose, pose_to_tum
from presim.io_utils import atomic_write_bytes, atomic_write_json
from presim.outputs.teleop.frames import (MapImage, colorize_depth, depth_range_m, encode_jpeg, encode_png,
                                          hole_fraction, top_down_map)
from presim.outputs.teleop.protocol import (CmdVel, JointTarget, PathCommand, ProtocolSpec, Record, Simple,
                                            Teleport)
from presim.sim.controllers import Action
from presim.sim.simulator import Simulator
from presim.sim.types import Sink, StepResult

__all__ = ["TeleopConfig", "Frame", "TeleopSession", "dofs_of"]

_AXIS_NAMES = {"vx": "forward/backward", "vy": "strafe (Q/E)", "wz": "turn", "vz": "up/down (R/F)",
               "wy": "tilt (I/K)", "wx": "roll (U/O)"}


def dofs_of(drive: str) -> tuple[str, ...]:
    """The ``cmd_vel`` fields a robot with this drive acts on (the others are ignored)."""
    if drive == "free":
        return ("vx", "vy", "vz", "wx", "wy", "wz")
    return ("vx", "vy", "wz") if drive == "holonomic" else ("vx", "wz")


@dataclass(frozen=True)
class TeleopConfig:
    """Teleop session settings."""

    out_dir: Path = Path("presim_teleop")
    """Recordings (``rec_NNN/``: MCAP + capture folder) and snapshots (``snapshots/``) go here."""
    seed: int = 0
    """Seed of the start pose (and reset)."""
    realtime: bool = True
    """Pace steps to wall time (``dt`` of sim time per step); False = as fast as it renders."""
    command_timeout_s: float = 0.5
    """A velocity command older than this is dropped (the robot stops if the page goes quiet)."""
    jpeg_quality: int = 80
    """JPEG quality of the colour and depth images sent to the page."""
    map_resolution_m: float | None = None
    """Top-down map cell size for scenes without an occupancy map (free camera rig), metres; None:
    the points' extent / 400, between 1 cm and 5 cm (a 1.5 m tabletop capture gets ~4 mm cells
    clamped to 1 cm, a 10 m room 2.5 cm)."""
    depth_max_m: float | None = None
    """Far end of the depth colour bar, metres (None: from the first frame, rounded up to 0.5 m)."""
    trajectory_max_points: int = 20000
    """Trajectory points kept for pages that join later."""
    pause_without_clients: bool = True
    """Stop stepping while no page is connected (and nothing records)."""
    start_pitch_rad: float = 0.0
    """Free camera rig only: pitch added to the captured view it starts at (and resets to), radians,
    positive looks down (``--tilt-deg``; a mobile robot tilts its ``head_tilt_joint`` instead)."""
    path_max_poses: int = 100_000
    """Camera poses a recorded path keeps at most (recording stops there with a message)."""
    pause_at_rest: bool = True
    """Stop stepping while the robot is at rest (no command, base and joints still, nothing records):
    the image would not change. A command wakes the loop at once (so key-to-motion is one step, not
    one and a half); sim time does not advance while paused."""


@dataclass(frozen=True)
class Frame:
    """The newest published state; images are those of the newest camera reading."""

    seq: int
    state: dict
    image_seq: int
    color_jpeg: bytes | None
    depth_jpeg: bytes | None


@dataclass
class _Command:
    client_id: int
    msg: object
    stamp: float = field(default_factory=time.monotonic)


class TeleopSession:
    """Runs the simulator for the server. ``notify(client_id | None, message_dict)`` sends a message to
    one client (None = all); ``on_frame()`` is called (from the sim thread) after each publish."""

    def __init__(self, sim: Simulator, config: TeleopConfig = TeleopConfig(),
                 make_recorder: Callable[[Path], list[Sink]] | None = None):
        self.sim, self.config = sim, config
        self.make_recorder = make_recorder
        self.notify: Callable[[int | None, dict], None] = lambda cid, msg: None
        self.on_frame: Callable[[], None] = lambda: None
        robot = sim.robot
        self.dofs = dofs_of(robot.drive)
        self.R_map_world = self._map_rotation()
        self.map = self._build_map()
        self.spec = ProtocolSpec(
            map_min_xy=self.map.origin_xy, map_max_xy=self.map.max_xy,
            joint_limits={n: (float(lo), float(hi)) for n, lo, hi in zip(robot.joint_names, robot.lower, robot.upper)})
        self.hfov_deg = float(np.degrees(2 * np.arctan(sim.camera_intrinsics[0].width / (2 * sim.camera_intrinsics[0].fx)))) \
            if sim.camera_intrinsics else 60.0
        self._lock = threading.Lock()
        self._commands: deque[_Command] = deque(maxlen=256)
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.clients: set[int] = set()
        self.driver: int | None = None
        self.latest: Frame | None = None
        self.trajectory: deque[tuple[float, float]] = deque(maxlen=config.trajectory_max_points)
        self.error: BaseException | None = None
        # control state (sim thread only)
        self._cmd = CmdVel(0.0, 0.0, 0.0)
        self._cmd_stamp = 0.0
        self._joint_targets: dict[str, float] = {}
        self._recorder: list[Sink] = []
        self.recording_dir: Path | None = None
        self._n_snapshots = 0
        self._last: StepResult | None = None
        self._last_cam = None
        self._seq = self._image_seq = 0
        self._contacts = 0
        self._step_times: deque[float] = deque(maxlen=20)
        self._render_ms = 0.0
        self._holes = 0.0
        self._depth_max = config.depth_max_m if config.depth_max_m is not None else self._scene_depth_range()
        self._warned: set[tuple[int, str]] = set()
        # camera path (sim thread; the lock guards what other threads read)
        self._path_stamps: list[float] = []
        self._path_poses: list[np.ndarray] = []
        self.path_recording = False
        self._clock_s = 0.0  # sim time of the session, continued across resets and teleports
        self._n_paths = 0

    # ---- set-up ----------------------------------------------------------------------------------
    def _scene_depth_range(self) -> float | None:
        """Depth colour range from up to 8 captured depth maps (None: decided by the first frame)."""
        scene = self.sim.scene
        n = len(scene)
        if n == 0:
            return None
        idx = np.unique(np.linspace(0, n - 1, min(n, 8)).astype(int))
        try:
            d = np.concatenate([np.asarray(scene.depth(int(i), refined=False))[::4, ::4].ravel() for i in idx])
        except (OSError, ValueError, IndexError):
            return None
        return depth_range_m(d)

    def _map_rotation(self) -> np.ndarray:
        """(3, 3) rotation from world to the map frame, whose z is up (against ``gravity_world``):
        identity for a scene with a floor (gravity -z after import); for a capture without a floor
        the map looks along its gravity, x = the first camera's view direction made level."""
        g = np.asarray(getattr(self.sim.scene, "gravity_world", (0.0, 0.0, -1.0)), dtype=np.float64)
        up = -g / max(np.linalg.norm(g), 1e-12)
        if self.sim.occupancy is not None or up[2] > 1.0 - 1e-9:
            return np.eye(3)
        T = np.asarray(self.sim.scene.T_world_cam)
        x = T[0, :3, 2] if len(T) else np.array([1.0, 0.0, 0.0])
        x = x - (x @ up) * up
        if np.linalg.norm(x) < 1e-6:  # the first camera looks straight down: any level axis
            x = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
        x /= np.linalg.norm(x)
        return np.stack([x, np.cross(up, x), up])

    def to_map(self, p_world: np.ndarray) -> np.ndarray:
        """(..., 3) world points -> (..., 3) map frame (x, y on the map, z = height)."""
        return np.asarray(p_world, dtype=np.float64) @ self.R_map_world.T

    def _map_yaw(self, d_world: np.ndarray) -> float:
        d = self.R_map_world @ d_world
        return float(np.arctan2(d[1], d[0]))

    def _build_map(self) -> MapImage:
        sim = self.sim
        pts = sim.points
        occ = sim.occupancy
        if occ is not None:
            return top_down_map(pts.xyz, pts.rgb, occupied=occ.occupied, known=occ.known,
                                origin_xy=tuple(occ.origin_xy), resolution_m=occ.resolution_m,
                                z_max_m=float(sim.robot.height_m) + 0.3)
        xyz = self.to_map(np.asarray(pts.xyz))
        res = self.config.map_resolution_m
        if res is None:
            xy = xyz[:, :2]
            extent = float((xy.max(0) - xy.min(0)).max()) if len(xy) else 1.0
            res = float(np.clip(extent / 400.0, 0.01, 0.05))
        else:
            extent = 5.0
        return top_down_map(xyz, pts.rgb, resolution_m=res, footprint=True, pad_m=min(0.5, max(0.1, 0.1 * extent)))

    def _captures_xy_yaw(self, max_n: int = 2000) -> list[list[float]]:
        """Captured camera positions and viewing yaw (world x, y, rad), at most ``max_n`` (evenly
        sub-sampled) -- drawn on the page's map."""
        T = np.asarray(self.sim.scene.T_world_cam)
        if len(T) > max_n:
            T = T[np.linspace(0, len(T) - 1, max_n).astype(int)]
        xy = self.to_map(T[:, :3, 3])[:, :2]
        fwd = self.to_map(T[:, :3, 2])
        yaw = np.arctan2(fwd[:, 1], fwd[:, 0])
        return [[round(float(x), 3), round(float(y), 3), round(float(a), 3)] for (x, y), a in zip(xy, yaw)]

    def init_message(self, client_id: int) -> dict:
        """What a page needs once: its id, the map's geometry, joints, drive, depth range, the trajectory."""
        robot = self.sim.robot
        h, w = self.map.rgb.shape[:2]
        with self._lock:
            traj = list(self.trajectory)
        return {
            "type": "init", "client_id": client_id, "scene": self.sim.scene_name,
            "robot": robot.urdf_path.name, "drive": robot.drive, "dt_s": self.sim.config.dt_s,
            "map": {"width": w, "height": h, "origin_xy": list(self.map.origin_xy),
                    "resolution_m": self.map.resolution_m},
            "joints": [{"name": n, "lower": float(lo), "upper": float(hi)}
                       for n, lo, hi in zip(robot.joint_names, robot.lower, robot.upper)],
            "hfov_deg": self.hfov_deg, "depth_max_m": self._depth_max,
            "trajectory": [[round(x, 3), round(y, 3)] for x, y in traj],
            "out_dir": str(self.config.out_dir), "dofs": list(self.dofs),
            "captures": self._captures_xy_yaw(), "free": bool(self.sim.is_free),
            # drawing sizes on the map: the base's footprint, the camera frustum's length
            "robot_radius_m": 0.03 if self.sim.is_free else float(robot.footprint_radius_m),
            "frustum_m": 1.5 if not self.sim.is_free else float(
                max(0.1, 0.2 * min(np.subtract(self.map.max_xy, self.map.origin_xy)))),
        }

    # ---- clients (any thread) --------------------------------------------------------------------
    def add_client(self, client_id: int) -> None:
        with self._lock:
            self.clients.add(client_id)
        self._wake.set()

    def remove_client(self, client_id: int) -> None:
        with self._lock:
            self.clients.discard(client_id)
            self._warned = {w for w in self._warned if w[0] != client_id}
            if self.driver == client_id:
                self.driver = None
                self._commands.append(_Command(-1, CmdVel(0.0, 0.0, 0.0)))  # the robot stops

    def _warn_inactive(self, client_id: int, cmd: CmdVel) -> None:
        """Once per tab and axis: say that this robot ignores a velocity component it was sent."""
        for axis in ("vy", "vz", "wy", "wx"):
            if getattr(cmd, axis) and axis not in self.dofs and (client_id, axis) not in self._warned:
                self._warned.add((client_id, axis))
                self.notify(client_id, {"type": "info", "message": (
                    f"{_AXIS_NAMES[axis]} does nothing on this robot ({self.sim.robot.urdf_path.name}, "
                    f"drive {self.sim.robot.drive}): '{axis}' is ignored")})

    def submit(self, client_id: int, msg) -> None:
        """Queue a validated message from ``client_id`` (applied before the next step); refusals go back
        through ``notify``."""
        with self._lock:
            if isinstance(msg, Simple) and msg.type == "take_control":
                self.driver = client_id
                self.notify(None, {"type": "info", "message": f"tab {client_id} drives now"})
                return
            if isinstance(msg, CmdVel):
                self._warn_inactive(client_id, msg)
            if not (isinstance(msg, Simple) and msg.type in ("snapshot", "pose") or isinstance(msg, PathCommand)):
                if self.driver is None:
                    self.driver = client_id
                elif self.driver != client_id:
                    self.notify(client_id, {"type": "error", "message": f"tab {self.driver} drives; "
                                            "press 'Take control' to drive from this tab"})
                    return
            self._commands.append(_Command(client_id, msg))
        self._wake.set()

    # ---- thread ----------------------------------------------------------------------------------
    def start(self) -> None:
        self._after_step(self._reset_start(), time.perf_counter())
        self._thread = threading.Thread(target=self._run, name="presim-teleop-sim", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(30)
        try:
            self._stop_recording(None)
        finally:
            self.sim.close()

    def _reset_start(self, joints: dict[str, float] | None = None) -> StepResult:
        """``sim.reset`` at the seeded start; the free rig then pitches by ``start_pitch_rad``."""
        result = self.sim.reset(self.config.seed, joint_positions=joints)
        pitch = self.config.start_pitch_rad
        if self.sim.is_free and pitch:
            c, s = np.cos(pitch), np.sin(pitch)
            # base frame x forward, y left, z up: +pitch about +y turns x (the view) down
            R_y = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
            T = self.sim.T_world_base @ make_pose(R_y, np.zeros(3))
            result = self.sim.reset(self.config.seed, start=T, joint_positions=joints)
        return result

    def _idle(self) -> bool:
        with self._lock:
            return self.config.pause_without_clients and not self.clients and not self._recorder

    def _run(self) -> None:
        dt = self.sim.config.dt_s
        next_t = time.perf_counter()
        try:
            while not self._stop.is_set():
                if self._idle():
                    self._wake.wait(0.2)
                    self._wake.clear()
                    next_t = time.perf_counter()
                    continue
                self._apply_commands()
                now = time.monotonic()
                cmd = self._cmd if now - self._cmd_stamp <= self.config.command_timeout_s else CmdVel(0.0, 0.0, 0.0)
                if self._at_rest(cmd):
                    self._publish_rest()
                    self._wake.wait(0.5)
                    self._wake.clear()
                    next_t = time.perf_counter()
                    continue
                if self.sim.is_free:
                    twist = np.array([cmd.vx, cmd.vy, cmd.vz, cmd.wx, cmd.wy, cmd.wz])
                else:
                    twist = np.array([cmd.vx, cmd.vy, cmd.wz])
                result = self.sim.step(Action(twist=twist, joint_targets=dict(self._joint_targets) or None))
                self._clock_s += dt
                self._applied_seq = cmd.seq
                self._after_step(result, time.perf_counter())
                if self.config.realtime:
                    next_t += dt
                    wait = next_t - time.perf_counter()
                    if wait > 0:
                        self._stop.wait(wait)
                    else:
                        next_t = time.perf_counter()  # behind: no catch-up burst
        except BaseException as e:  # noqa: BLE001 - reported to the pages and the CLI, never silent
            self.error = e
            self.notify(None, {"type": "error", "message": f"simulator stopped: {type(e).__name__}: {e}"})

    def _at_rest(self, cmd: CmdVel) -> bool:
        r = self._last
        if not self.config.pause_at_rest or r is None or self._recorder:
            return False
        if cmd.vx or cmd.vy or cmd.wz or cmd.vz or cmd.wy or cmd.wx:
            return False
        with self._lock:
            if self._commands:
                return False
        target = self.sim.q_target.copy()
        for name, value in self._joint_targets.items():  # slider moves not applied by a step yet
            target[self.sim.robot.joint_index(name)] = value
        q_goal = np.clip(target, self.sim.robot.lower, self.sim.robot.upper)
        return (not np.any(r.applied_command) and not np.any(r.odometry.twist_base)
                and np.allclose(self.sim.joint_positions, q_goal, atol=1e-9))

    def _publish_rest(self) -> None:
        """Once per pause: republish the newest state flagged ``at_rest`` (pages show it)."""
        f = self.latest
        if f is None or f.state.get("at_rest"):
            return
        self._seq += 1
        self.latest = Frame(self._seq, dict(f.state, seq=self._seq, at_rest=True, steps_per_s=0.0,
                                            wall_time_s=time.time()),
                            f.image_seq, f.color_jpeg, f.depth_jpeg)
        self._step_times.clear()
        self.on_frame()

    # ---- commands (sim thread) -------------------------------------------------------------------
    def _apply_commands(self) -> None:
        while True:
            with self._lock:
                if not self._commands:
                    return
                c = self._commands.popleft()
            try:
                self._apply(c)
            except (OSError, ValueError) as e:
                self.notify(c.client_id, {"type": "error", "message": str(e)})

    def _apply(self, c: _Command) -> None:
        m, sim = c.msg, self.sim
        if isinstance(m, CmdVel):
            self._cmd, self._cmd_stamp = m, c.stamp
        elif isinstance(m, JointTarget):
            self._joint_targets[m.name] = m.value
        elif isinstance(m, Teleport):
            if self._recorder:
                raise ValueError("stop the recording before teleporting (a recording is one continuous path)")
            yaw = sim.yaw if m.yaw is None else m.yaw
            if sim.occupancy is not None:
                if sim.occupancy.is_blocked(m.x, m.y):
                    raise ValueError(f"teleport: ({m.x:.2f}, {m.y:.2f}) is inside an obstacle")
                start = np.array([m.x, m.y, yaw])
            else:  # the free rig: move on the map plane, keep height and orientation
                T = sim.T_world_base
                p = self.to_map(T[:3, 3])
                p[0], p[1] = m.x, m.y
                T[:3, 3] = self.R_map_world.T @ p
                start = T
            self._restart(start)
            self.notify(c.client_id, {"type": "info", "message": f"teleported to ({m.x:.2f}, {m.y:.2f})"})
        elif isinstance(m, Simple) and m.type == "reset":
            if self._recorder:
                raise ValueError("stop the recording before resetting")
            self._restart(None)
            with self._lock:
                self.trajectory.clear()
            self.notify(None, {"type": "reset"})
        elif isinstance(m, Simple) and m.type == "snapshot":
            path, n_far = self._snapshot()
            far = f" ({n_far} pixels beyond 65.535 m stored as 0 = invalid)" if n_far else ""
            self.notify(c.client_id, {"type": "info", "message": f"snapshot saved: {path}{far}"})
        elif isinstance(m, Simple) and m.type == "pose":
            T = self.T_world_cam()
            self.notify(c.client_id, {"type": "pose", "T_world_cam": T.tolist(),
                                      "tum": tum_line(self._clock_s, T),
                                      "pose_arg": " ".join(f"{v:.6f}" for v in pose_to_tum(T))})
        elif isinstance(m, PathCommand):
            self._path(c.client_id, m.action)
            self._refresh_state()
        elif isinstance(m, Record):
            if m.on:
                self._start_recording(c.client_id)
            else:
                self._stop_recording(c.client_id)

    def _restart(self, start) -> None:
        joints = dict(zip(self.sim.robot.joint_names, self.sim.joint_positions))
        self._cmd = CmdVel(0.0, 0.0, 0.0)
        self._clock_s += self.sim.config.dt_s  # path stamps keep increasing across restarts
        if start is None:
            result = self._reset_start(joints)
        else:
            result = self.sim.reset(self.config.seed, start=start, joint_positions=joints)
        self._after_step(result, time.perf_counter())

    # ---- camera path (sim thread) ----------------------------------------------------------------
    def T_world_cam(self) -> np.ndarray:
        """The robot camera's pose now (4x4, OpenCV optical frame)."""
        return self.sim.T_world_base @ self.sim.T_base_cam()

    def _path_append(self, T: np.ndarray, force: bool) -> None:
        poses, stamps = self._path_poses, self._path_stamps
        if poses and not force and np.allclose(poses[-1], T, atol=1e-9):
            return  # the camera did not move: no duplicate pose
        if len(poses) >= self.config.path_max_poses:
            if self.path_recording:
                self.path_recording = False
                self.notify(None, {"type": "info", "message": f"camera path full ({len(poses)} poses): "
                                   "recording stopped; save it"})
            return
        # TUM stamps must increase: the session clock, nudged by 1 ms for poses added at one instant
        stamp = self._clock_s if not stamps or self._clock_s > stamps[-1] else stamps[-1] + 1e-3
        with self._lock:
            stamps.append(float(stamp))
            poses.append(np.array(T, dtype=np.float64))

    def _refresh_state(self) -> None:
        """Republish the newest state with the path and recording status of now (a command applied
        at rest changes them without a step)."""
        f = self.latest
        if f is None:
            return
        with self._lock:
            rec = str(self.recording_dir) if self.recording_dir is not None else None
        self._seq += 1
        self.latest = Frame(self._seq, dict(f.state, seq=self._seq, recording=rec, wall_time_s=time.time(),
                                            path={"recording": self.path_recording,
                                                  "poses": len(self._path_poses)}),
                            f.image_seq, f.color_jpeg, f.depth_jpeg)
        self.on_frame()

    def _path(self, client_id: int, action: str) -> None:
        if action == "start":
            self.path_recording = True
            self._path_append(self.T_world_cam(), force=False)
            self.notify(None, {"type": "info", "message": "recording the camera path (every rendered frame)"})
        elif action == "stop":
            self.path_recording = False
            self.notify(None, {"type": "info", "message": f"camera path: {len(self._path_poses)} poses"})
        elif action == "add":
            self._path_append(self.T_world_cam(), force=True)
            self.notify(client_id, {"type": "info", "message": f"pose added: the path has {len(self._path_poses)}"})
        elif action == "clear":
            with self._lock:
                self._path_poses, self._path_stamps = [], []
            self.notify(None, {"type": "info", "message": "camera path cleared"})
        elif action == "save":
            if not self._path_poses:
                raise ValueError("camera path is empty: press 'Add pose' or 'Record path' first")
            root = Path(self.config.out_dir) / "paths"
            root.mkdir(parents=True, exist_ok=True)
            k = self._n_paths
            while (root / f"path_{k:03d}.tum").exists():
                k += 1
            self._n_paths = k + 1
            path = root / f"path_{k:03d}.tum"
            write_tum(path, np.array(self._path_stamps), np.stack(self._path_poses))  # atomic (temp + rename)
            self.notify(client_id, {"type": "path_saved", "path": str(path), "poses": len(self._path_poses),
                                    "name": path.name, "tum": path.read_text()})

    def _next_dir(self, prefix: str) -> Path:
        root = Path(self.config.out_dir)
        k = 0
        while (root / f"{prefix}{k:03d}").exists() or list(root.glob(f"{prefix}{k:03d}_*")):
            k += 1
        return root / f"{prefix}{k:03d}"

    def _start_recording(self, client_id: int) -> None:
        if self._recorder:
            raise ValueError(f"already recording to {self.recording_dir}")
        if self.make_recorder is None:
            raise ValueError("recording is not available (the recorder's optional dependencies are missing)")
        d = self._next_dir("rec_")
        sinks = self.make_recorder(d)
        for s in sinks:
            self.sim.add_sink(s)
        with self._lock:
            self._recorder, self.recording_dir = sinks, d
        self.notify(None, {"type": "info", "message": f"recording to {d}"})

    def _stop_recording(self, client_id: int | None) -> None:
        if not self._recorder:
            if client_id is not None:
                raise ValueError("not recording")
            return
        sinks, d = self._recorder, self.recording_dir
        with self._lock:
            self._recorder, self.recording_dir = [], None
        errors = []
        for s in sinks:
            self.sim.sinks.remove(s)
            try:
                s.close()
            except Exception as e:  # noqa: BLE001 - every sink gets closed, the first error is reported
                errors.append(e)
        if errors:
            raise ValueError(f"recording {d} closed with an error: {errors[0]}")
        self.notify(None, {"type": "info", "message": f"recording saved: {d}"})

    def _snapshot(self) -> tuple[Path, int]:
        cam = self._last_cam
        if cam is None:
            raise ValueError("snapshot: no camera image yet")
        base = self._next_dir("snapshots/snap_")
        base.parent.mkdir(parents=True, exist_ok=True)
        depth_png, n_far = encode_depth_png(cam.depth_m, 1.0)  # out of range -> 0 (invalid), never clipped
        atomic_write_bytes(f"{base}_color.png", encode_png(cam.color))
        atomic_write_bytes(f"{base}_depth.png", depth_png)
        K = cam.K
        atomic_write_json(f"{base}.json", {
            "sim_time_s": cam.stamp_s, "depth_scale_m": 0.001, "T_world_cam": np.asarray(cam.T_world_cam).tolist(),
            "K": {"fx": K.fx, "fy": K.fy, "cx": K.cx, "cy": K.cy, "width": K.width, "height": K.height},
            "n_depth_beyond_range": n_far})
        return Path(f"{base}_color.png"), n_far

    # ---- publishing (sim thread) -----------------------------------------------------------------
    def _after_step(self, r: StepResult, now: float) -> None:
        self._last = r
        self._step_times.append(now)
        self._contacts += int(r.contact)
        p = self.to_map(r.T_world_base[:3, 3])
        with self._lock:
            self.trajectory.append((float(p[0]), float(p[1])))
        color_jpeg = depth_jpeg = None
        if r.cameras:
            cam = r.cameras[0]
            self._last_cam = cam
            if self._depth_max is None:
                self._depth_max = depth_range_m(cam.depth_m)
            self._render_ms = float(r.timings_ms.get("render", 0.0))
            self._holes = hole_fraction(cam.valid, cam.depth_m)
            color_jpeg = encode_jpeg(cam.color, self.config.jpeg_quality)
            depth_jpeg = encode_jpeg(colorize_depth(cam.depth_m, self._depth_max), self.config.jpeg_quality)
            self._image_seq += 1
            if self.path_recording:
                self._path_append(cam.T_world_cam, force=False)
        self._seq += 1
        prev = self.latest
        if color_jpeg is None and prev is not None:
            color_jpeg, depth_jpeg = prev.color_jpeg, prev.depth_jpeg
        frame = Frame(self._seq, self._state(r), self._image_seq, color_jpeg, depth_jpeg)
        self.latest = frame
        self.on_frame()

    def _state(self, r: StepResult) -> dict:
        """``pose`` (base) and ``camera`` are in the map frame (:meth:`to_map`: world x, y for a scene
        with a floor), ``z`` the height, camera ``pitch`` positive looking down."""
        T = r.T_world_base
        pos = self.to_map(T[:3, 3])
        yaw = self._map_yaw(T[:3, 0])
        cam_T = self._last_cam.T_world_cam if self._last_cam is not None else self.sim.T_world_base @ self.sim.T_base_cam()
        cam_p, fwd = self.to_map(cam_T[:3, 3]), self.R_map_world @ cam_T[:3, 2]
        times = self._step_times
        rate = (len(times) - 1) / (times[-1] - times[0]) if len(times) > 1 and times[-1] > times[0] else 0.0
        with self._lock:
            driver, n_clients = self.driver, len(self.clients)
            rec = str(self.recording_dir) if self.recording_dir is not None else None
        return {
            "type": "state", "seq": self._seq, "image_seq": self._image_seq, "step": r.step_idx,
            "sim_time_s": round(r.sim_time_s, 3),
            "pose": {"x": float(pos[0]), "y": float(pos[1]), "z": float(pos[2]), "yaw": yaw},
            "camera": {"x": float(cam_p[0]), "y": float(cam_p[1]), "z": float(cam_p[2]),
                       "yaw": float(np.arctan2(fwd[1], fwd[0])),
                       "pitch": float(np.arcsin(np.clip(-fwd[2], -1.0, 1.0))), "hfov_deg": self.hfov_deg},
            "path": {"recording": self.path_recording, "poses": len(self._path_poses)},
            "joints": {n: float(q) for n, q in zip(r.joint_states.names, r.joint_states.position)},
            "applied": [float(v) for v in r.applied_command],
            "cmd_seq": getattr(self, "_applied_seq", None),
            "steps_per_s": round(rate, 2), "render_ms": round(self._render_ms, 1),
            "hole_fraction": round(self._holes, 4), "collisions": self._contacts, "contact": bool(r.contact),
            "outside": bool(r.outside_captured_area), "recording": rec, "driver": driver, "clients": n_clients,
            "depth_max_m": self._depth_max, "wall_time_s": time.time(), "at_rest": False,
        }
