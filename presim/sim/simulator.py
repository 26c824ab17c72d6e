"""The step loop: a robot in a captured scene, seeing it through the view synthesis engine.

``Simulator(scene, robot, config)``; ``reset(seed) -> StepResult``; ``step(action) -> StepResult``
with a fixed ``dt``. Each step: control (limits, joints) -> collision (occupancy map, floor) ->
forward kinematics -> RGB-D cameras due at their rate (``Renderer``) -> noise -> odometry -> sinks.
Ground truth (``T_world_base``, link poses, each image's ``T_world_cam``) is exact; odometry may drift.
A seed fixes the start pose, the noise and the drift, so the same seed and actions give the same
trajectory and images.

Example:
    >>> from presim.capture.store import load_scene                      # doctest: +SKIP
    >>> sim = Simulator(load_scene("out/sample"))                        # doctest: +SKIP
    >>> r = sim.reset(seed=0); r = sim.step(np.array([0.3, 0.0, 0.2]))   # doctest: +SKIP
    >>> r.cameras[0].color.shape, r.T_world_base[:3, 3]                  # doctest: +SKIP
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from presim.capture.scene import Scene
from presim.capture.store import fuse_point_cloud
from presim.geometry import Intrinsics, check_rigid, compose, invert, make_pose, rotation_z
from presim.sensors.camera import CameraSpec
from presim.sensors.noise import apply_depth_noise
from presim.sensors.odometry import OdometryConfig, WheelOdometry, integrate_planar
from presim.sim.controllers import Action, BaseLimits, joint_position_step, limit_base_command, limit_free_twist, wrap_angle
from presim.sim.occupancy import OccupancyConfig, OccupancyMap, build_occupancy_map, move_base
from presim.sim.robot import Robot, default_robot, free_camera_rig
from presim.sim.types import CameraObservation, JointStates, Odometry, SimInfo, Sink, StepResult, deliver
from presim.synthesis.renderer import PerfConfig, RenderConfig, Renderer

__all__ = ["SIM_RENDER_CACHE_MB", "SimConfig", "Simulator", "Action"]

SIM_RENDER_CACHE_MB = 160.0
"""Default bound of the simulator renderer's per-view point cache (MiB; ``PerfConfig.cache_mb``,
1024 elsewhere). A robot's camera needs a few nearby views per frame; an evicted view is prepared
again in ~9 ms (640x480), so a small bound keeps a 100-frame VGA capture's simulator near 400 MB
(benchmarks/bench_sim.py memory, docs/simulator.md "Memory") at little cost. The images do not depend
on it."""


@dataclass(frozen=True)
class SimConfig:
    """Step loop configuration."""

    dt_s: float = 0.1
    """Fixed step of sim time, seconds."""
    cameras: tuple[CameraSpec, ...] = (CameraSpec(),)
    """RGB-D cameras (default: one 640x480 camera at 10 Hz on the robot's camera link); empty = no
    rendering (kinematics, collisions and odometry only)."""
    limits: BaseLimits = field(default_factory=BaseLimits)
    """Base speed / acceleration limits."""
    occupancy: OccupancyConfig = field(default_factory=OccupancyConfig)
    """Occupancy map (collision) parameters."""
    odometry: OdometryConfig = field(default_factory=OdometryConfig)
    """Odometry drift model (off by default)."""
    render: RenderConfig = field(default_factory=RenderConfig)
    """View synthesis algorithm (what the images look like)."""
    perf: PerfConfig = field(default_factory=lambda: PerfConfig(cache_mb=SIM_RENDER_CACHE_MB))
    """How the renderer runs (default: the per-view point cache bounded at :data:`SIM_RENDER_CACHE_MB`)."""
    start_clearance_m: float = 0.10
    """Random start poses keep at least this much space around the footprint."""
    max_view_distance_m: float = 1.0
    """Free rig: farther than this from every captured camera counts as outside the captured area."""


def _planar_pose(x: float, y: float, yaw: float, z: float = 0.0) -> np.ndarray:
    return make_pose(rotation_z(yaw), [x, y, z])


def _yaw_of(T: np.ndarray) -> float:
    return float(np.arctan2(T[1, 0], T[0, 0]))


class Simulator:
    """A robot in a captured scene. See the module docstring."""

    def __init__(self, scene: Scene, robot: Robot | None = None, config: SimConfig = SimConfig(),
                 renderer: Renderer | None = None):
        if robot is None:
            robot = default_robot() if scene.floor is not None else free_camera_rig()
        self.scene, self.robot, self.config = scene, robot, config
        self.is_free = robot.drive == "free"
        self._q_limits = (robot.lower.tolist(), robot.upper.tolist())
        name = scene.path.name if scene.path is not None else scene.meta.source
        self.scene_name = str(name)
        if not self.is_free and scene.floor is None:
            raise ValueError(
                f"scene '{self.scene_name}' has no floor (a tabletop capture): a mobile base cannot stand "
                f"in it; use the free camera rig (free_camera_rig(); CLI: --robot free)"
            )
        if not config.dt_s > 0:
            raise ValueError(f"dt_s must be > 0, got {config.dt_s}")
        if scene.points is None or len(scene.points) == 0:

            # In-memory scenes may come without a cloud: fuse one (the obstacles and the viewer need it).
            self.points = fuse_point_cloud(scene)
        else:
            self.points = scene.points
        self.renderer = renderer if renderer is not None else Renderer(scene, config.render, config.perf)
        self.occupancy: OccupancyMap | None = None
        if not self.is_free:
            self.occupancy = build_occupancy_map(self.points.xyz, scene.floor, robot.height_m,
                                                 robot.footprint_radius_m, config.occupancy,
                                                 view_xy=scene.camera_centres[:, :2])
        capture_K = scene.intrinsics[0]
        self._cams: list[tuple[CameraSpec, str, Intrinsics]] = []
        names = set()
        for spec in config.cameras:
            link = robot.check_link(spec.link or robot.camera_link)
            if spec.name in names:
                raise ValueError(f"two cameras are named '{spec.name}'")
            names.add(spec.name)
            self._cams.append((spec, link, spec.intrinsics(capture_K)))
        self.sinks: list[Sink] = []
        self._sinks_open = False
        self.odometry = WheelOdometry(config.odometry)
        self._reset_state(np.random.default_rng(0))

    # ---- public API ----------------------------------------------------------------------------
    def add_sink(self, sink: Sink) -> None:
        """Attach a recorder / viewer / bridge; it is opened at the next reset (or now if running)."""
        self.sinks.append(sink)
        if self._sinks_open:
            sink.open(self.info())

    def info(self) -> SimInfo:
        return SimInfo(
            scene_name=self.scene_name,
            points_xyz=self.points.xyz,
            points_rgb=self.points.rgb,
            input_T_world_cam=self.scene.T_world_cam,
            input_intrinsics=tuple(self.scene.intrinsics),
            urdf_xml=self.robot.urdf_xml,
            link_parents=dict(self.robot.link_parents),
            dt_s=self.config.dt_s,
            floor_z_m=self._floor_z(0.0, 0.0) if self.scene.floor is not None else None,
        )

    @property
    def sim_time_s(self) -> float:
        return self.step_idx * self.config.dt_s

    @property
    def T_world_base(self) -> np.ndarray:
        return self._T_world_base.copy()

    @property
    def joint_positions(self) -> np.ndarray:
        return self.q.copy()

    @property
    def camera_intrinsics(self) -> list[Intrinsics]:
        return [K for _, _, K in self._cams]

    def initial_joints(self, joint_positions: dict[str, float] | None = None) -> np.ndarray:
        """(J,) joint vector ``reset`` would start from with these ``joint_positions``."""
        q = self.robot.initial_joint_positions()
        for name, value in (joint_positions or {}).items():
            q[self.robot.joint_index(name)] = float(value)
        return self.robot.clip_joints(q)

    def predict_joints(self, joint_targets: dict[str, float] | None = None) -> np.ndarray:
        """(J,) joint positions after the next step with these extra ``joint_targets``."""
        target = self.q_target.copy()
        for name, value in (joint_targets or {}).items():
            target[self.robot.joint_index(name)] = float(value)
        if not len(self.q):
            return self.q.copy()
        return joint_position_step(self.q, target, self.robot.lower, self.robot.upper,
                                   self.robot.velocity_limits, self.config.dt_s)[0]

    def T_base_cam(self, camera_idx: int = 0, q: np.ndarray | None = None) -> np.ndarray:
        """Pose of camera ``camera_idx``'s optical frame in the base frame at joint positions ``q``
        (None = now); with no camera configured, the robot's camera link."""
        return self._T_base_cam(self.robot.fk(self.q if q is None else q), camera_idx)

    def reset(self, seed: int | None = None, start: np.ndarray | None = None,
              joint_positions: dict[str, float] | None = None) -> StepResult:
        """Start an episode. ``seed`` fixes the random start pose, noise and drift (None = fresh
        entropy). ``start``: (3,) [x, y, yaw] for a mobile base or a 4x4 ``T_world_base`` (either
        robot; a mobile base keeps its planar part); None = drawn from the seed near a captured view.
        ``joint_positions``: start joint positions (also the initial targets) instead of the robot's
        ``initial_joint_positions``."""
        rng = np.random.default_rng(seed)
        self._reset_state(rng)
        if joint_positions:
            self.q = self.initial_joints(joint_positions)
            self.q_target = self.q.copy()
        t0 = time.perf_counter()
        if start is None:
            T = self._random_start(self._start_rng)
        else:
            start = np.asarray(start, dtype=np.float64)
            if start.shape == (3,):
                T = _planar_pose(*start)
            else:
                T = check_rigid(start, "start pose")
        self._set_base(T)
        if not self._sinks_open:
            info = self.info()
            for s in self.sinks:
                s.open(info)
            self._sinks_open = True
        timings = {"control": (time.perf_counter() - t0) * 1e3}
        contact = False
        if self.occupancy is not None and self.occupancy.is_blocked(self.x, self.y):
            contact = True
        return self._finish(np.zeros(3), np.zeros(6), contact, timings)

    def step(self, action: Action | np.ndarray) -> StepResult:
        """Advance one ``dt``. ``action``: an :class:`Action` or a bare twist array."""
        if not isinstance(action, Action):
            action = Action(twist=np.asarray(action, dtype=np.float64))
        dt = self.config.dt_s
        t0 = time.perf_counter()
        # Joints: persistent position targets, moved at the joints' velocity limits.
        if action.joint_targets:
            for name, value in action.joint_targets.items():
                self.q_target[self.robot.joint_index(name)] = float(value)
        if len(self.q):
            q = self.q.tolist()
            if q != self.q_target.tolist() or not all(lo <= x <= hi for x, lo, hi in zip(q, *self._q_limits)):
                self.q, self.qd = joint_position_step(self.q, self.q_target, self.robot.lower, self.robot.upper,
                                                      self.robot.velocity_limits, dt)
            elif self.qd.any():  # at a target within the limits: the joints stand still (the same as a step of 0)
                self.qd = np.zeros_like(self.q)
        self.step_idx += 1
        t1 = time.perf_counter()
        if self.is_free:
            applied, twist6, contact = self._step_free(action, dt)
        else:
            applied, twist6, contact = self._step_ground(action, dt)
        t2 = time.perf_counter()
        return self._finish(applied, twist6, contact, {"control": (t1 - t0) * 1e3, "collision": (t2 - t1) * 1e3})

    def close(self) -> None:
        """Close the sinks (once)."""
        if self._sinks_open:
            self._sinks_open = False
            errors = []
            for s in self.sinks:  # every sink gets closed (files finished) even if one fails
                try:
                    s.close()
                except Exception as e:  # noqa: BLE001 - re-raised below, after the other sinks
                    errors.append(e)
            if errors:
                raise errors[0]

    def __enter__(self) -> "Simulator":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ---- internals -----------------------------------------------------------------------------
    def _reset_state(self, rng: np.random.Generator) -> None:
        # Independent streams so that e.g. turning noise on does not change the start pose.
        self._start_rng, self._noise_rng, odo_rng = rng.spawn(3)
        self.odometry.reset(odo_rng)
        self.step_idx = 0
        self.q = self.robot.initial_joint_positions()
        self.q_target = self.q.copy()
        self.qd = np.zeros_like(self.q)
        self._prev_cmd = np.zeros(6 if self.is_free else 3)
        self._last_tick = [-1] * len(self._cams)
        self._set_base(np.eye(4))

    def _set_base(self, T_world_base: np.ndarray) -> None:
        if self.is_free:
            self._T_world_base = np.asarray(T_world_base, dtype=np.float64).copy()
            self.x, self.y, self.yaw = T_world_base[0, 3], T_world_base[1, 3], _yaw_of(T_world_base)
        else:
            self.x, self.y, self.yaw = float(T_world_base[0, 3]), float(T_world_base[1, 3]), _yaw_of(T_world_base)
            self._T_world_base = _planar_pose(self.x, self.y, self.yaw, self._floor_z(self.x, self.y))

    def _floor_z(self, x: float, y: float) -> float:
        f = self.scene.floor
        if f is None:
            return 0.0
        n = f.normal
        return float(-(n[0] * x + n[1] * y + f.offset) / n[2])

    def _T_base_cam(self, link_poses: dict[str, np.ndarray], idx: int) -> np.ndarray:
        link = self._cams[idx][1] if self._cams else self.robot.camera_link
        if link == self.robot.camera_link:
            return self.robot.T_base_camera(link_poses=link_poses)
        return link_poses[link]

    def _random_start(self, rng: np.random.Generator) -> np.ndarray:
        """Start where a captured camera stood (so the robot sees what the capture saw)."""
        order = rng.permutation(len(self.scene))
        T_base_cam = self._T_base_cam(self.robot.fk(self.q), 0)
        if self.is_free:
            return compose(self.scene.T_world_cam[order[0]], invert(T_base_cam))
        occ = self.occupancy
        free = occ.free_mask(self.config.start_clearance_m)
        if not free.any():
            free = occ.free_mask(0.0)
        if not free.any():
            raise ValueError(f"scene '{self.scene_name}': no free floor cell fits the robot "
                             f"(footprint radius {self.robot.footprint_radius_m:.2f} m)")
        ii, jj = np.nonzero(free)
        cx = occ.origin_xy[0] + (jj + 0.5) * occ.resolution_m
        cy = occ.origin_xy[1] + (ii + 0.5) * occ.resolution_m
        for k in order[: min(len(order), 20)]:
            T = self.scene.T_world_cam[k]
            d = np.hypot(cx - T[0, 3], cy - T[1, 3])
            m = int(np.argmin(d))
            if d[m] < 1.0:
                fwd = T[:3, 2]
                yaw = float(np.arctan2(fwd[1], fwd[0])) if np.hypot(fwd[0], fwd[1]) > 1e-3 else 0.0
                return _planar_pose(cx[m], cy[m], yaw)
        m = int(rng.integers(len(cx)))
        return _planar_pose(cx[m], cy[m], float(rng.uniform(-np.pi, np.pi)))

    def _step_ground(self, action: Action, dt: float) -> tuple[np.ndarray, np.ndarray, bool]:
        x, y, yaw = self.x, self.y, self.yaw
        if action.T_world_base is not None:
            T = check_rigid(action.T_world_base, "Action.T_world_base")
            x1, y1, yaw1 = T[0, 3], T[1, 3], _yaw_of(T)
            c, s = np.cos(yaw), np.sin(yaw)
            dx, dy = x1 - x, y1 - y
            applied = np.array([(c * dx + s * dy) / dt, (-s * dx + c * dy) / dt, wrap_angle(yaw1 - yaw) / dt])
        else:
            twist = np.asarray(action.twist, dtype=np.float64)
            if twist.shape == (6,):
                twist = twist[[0, 1, 5]]
            applied = limit_base_command(twist, self._prev_cmd, self.config.limits, self.robot.drive, dt)
            x1, y1, yaw1 = integrate_planar(x, y, yaw, *applied, dt)
        self._prev_cmd = applied
        xn, yn, contact = move_base(self.occupancy, x, y, x1, y1)
        self.x, self.y, self.yaw = xn, yn, float(wrap_angle(yaw1))
        self._T_world_base = _planar_pose(xn, yn, self.yaw, self._floor_z(xn, yn))
        # The realized motion as the constant twist whose arc ends where the base did (equals
        # `applied` without contact), so odometry integrates exactly what happened.
        c, s = np.cos(yaw), np.sin(yaw)
        d = np.array([c * (xn - x) + s * (yn - y), -s * (xn - x) + c * (yn - y)])
        wz = float(wrap_angle(self.yaw - yaw)) / dt
        a = wz * dt
        if abs(a) < 1e-9:
            v = d / dt
        else:
            A = np.array([[np.sin(a), np.cos(a) - 1.0], [1.0 - np.cos(a), np.sin(a)]]) / wz
            v = np.linalg.solve(A, d)
        realized = np.array([v[0], v[1], 0.0, 0.0, 0.0, wz])
        return applied, realized, contact

    def _step_free(self, action: Action, dt: float) -> tuple[np.ndarray, np.ndarray, bool]:
        T = self._T_world_base
        if action.T_world_base is not None:
            T1 = check_rigid(action.T_world_base, "Action.T_world_base")
            T_rel = compose(invert(T), T1)
            twist6 = np.concatenate([T_rel[:3, 3], Rotation.from_matrix(T_rel[:3, :3]).as_rotvec()]) / dt
        else:
            twist6 = limit_free_twist(action.twist, self._prev_cmd, self.config.limits, dt)
            T_rel = make_pose(Rotation.from_rotvec(twist6[3:] * dt).as_matrix(), twist6[:3] * dt)
            T1 = compose(T, T_rel)
        self._prev_cmd = twist6
        self._set_base(T1)
        return twist6[[0, 1, 5]], twist6, False

    def _outside(self) -> bool:
        if self.occupancy is not None:
            return not self.occupancy.is_known(self.x, self.y)
        T_cam = compose(self._T_world_base, self._T_base_cam(self.robot.fk(self.q), 0))
        d = np.linalg.norm(self.scene.camera_centres - T_cam[:3, 3], axis=1).min()
        return bool(d > self.config.max_view_distance_m)

    def _finish(self, applied: np.ndarray, twist6: np.ndarray, contact: bool, timings: dict[str, float]) -> StepResult:
        t0 = time.perf_counter()
        link_poses = self.robot.fk(self.q)
        T_world_base = self._T_world_base.copy()
        t = self.sim_time_s
        t1 = time.perf_counter()
        cams = []
        render_ms = noise_ms = 0.0
        for idx, (spec, link, K) in enumerate(self._cams):
            tick = int(np.floor(t * spec.rate_hz + 1e-6))
            if tick <= self._last_tick[idx]:
                continue
            self._last_tick[idx] = tick
            ta = time.perf_counter()
            T_world_cam = compose(T_world_base, self._T_base_cam(link_poses, idx))
            rgbd = self.renderer.render(T_world_cam, K)
            tb = time.perf_counter()
            depth = rgbd.depth_m.astype(np.float32, copy=False)
            if spec.noise is not None:
                depth = apply_depth_noise(depth, self._noise_rng, spec.noise)
            noise_ms += (time.perf_counter() - tb) * 1e3
            render_ms += (tb - ta) * 1e3
            cams.append(CameraObservation(spec.name, link, t, rgbd.color, depth, rgbd.valid, K, T_world_cam))
        t2 = time.perf_counter()
        T_odom_base = self.odometry.update(twist6[[0, 1, 5]], self.config.dt_s) if self.step_idx > 0 else self.odometry.pose()
        timings.update({"fk": (t1 - t0) * 1e3, "render": render_ms, "noise": noise_ms,
                        "odometry": (time.perf_counter() - t2) * 1e3})
        result = StepResult(
            step_idx=self.step_idx,
            sim_time_s=t,
            T_world_base=T_world_base,
            link_poses=link_poses,
            joint_states=JointStates(self.robot.joint_names, self.q.copy(), self.qd.copy()),
            odometry=Odometry(T_odom_base, np.asarray(twist6, dtype=np.float64).copy()),
            cameras=tuple(cams),
            applied_command=np.asarray(applied, dtype=np.float64).copy(),
            contact=bool(contact),
            outside_captured_area=self._outside(),
            timings_ms=timings,
        )
        t3 = time.perf_counter()
        deliver(self.sinks, result)  # to every sink or to none on Ctrl-C
        timings["sinks"] = (time.perf_counter() - t3) * 1e3
        timings["total"] = sum(v for k, v in timings.items() if k != "total")
        return result
