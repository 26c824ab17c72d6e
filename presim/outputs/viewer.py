"""Global 3D visualizer with rerun (thesis Fig. 4.16): scene cloud, input camera frusta, the live
robot and its camera, the whole trajectory and the RGB-D images on the ``sim_time`` timeline.

Entity paths mirror the frame tree (``map`` is rerun's ``world``)::

    world                                   RIGHT_HAND_Z_UP (gravity -z)
    world/scene                             Points3D, static
    world/inputs/view_0000                  Transform3D (T_world_cam) + Pinhole, static
    world/trajectory/base, .../camera       LineStrips3D (whole path so far)
    world/robot/base_link                   Transform3D (exact T_world_base) + Boxes3D body
    world/robot/base_link/<link>/...        Transform3D T_parent_child along the URDF chain
    .../camera_optical_frame                Pinhole (OpenCV RDF)
    .../camera_optical_frame/color          Image (RGB)
    .../camera_optical_frame/depth          DepthImage (meter = 1.0: values are metres)

Modes (all bind 127.0.0.1 only; we start the ``rerun`` binary ourselves because the SDK's
``serve_grpc`` / ``serve_web_viewer`` / ``spawn`` bind 0.0.0.0 in 0.41):

- ``native``: the native viewer (``rerun --bind 127.0.0.1 --port P``), detached so it stays open.
- ``web``: ``rerun --serve-web --bind 127.0.0.1`` (gRPC proxy + web viewer); stopped at close.
- ``rrd``: only an ``.rrd`` file (also written alongside in the other modes when ``rrd_path`` given).
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
import urllib.parse
import uuid
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from presim.outputs.frames import BASE_FRAME, build_frame_tree
from presim.procs import die_with_parent, stop_group
from presim.sim.types import SimInfo, StepResult

__all__ = ["ViewerConfig", "RerunViewer", "LinkVisual", "robot_visuals", "viewer_blueprint", "web_viewer_url",
           "free_port", "rerun_executable", "wait_for_port", "ViewerError", "check_rrd_file", "has_display"]

RRD_MAGIC = (b"RRF0", b"RRF1", b"RRF2")
"""First four bytes of a rerun recording (``.rrd``) file."""


class ViewerError(OSError):
    """The viewer cannot run here (no display, the rerun binary did not start) or the file is not
    a recording. An ``OSError`` so commands report it in one line."""


def has_display() -> bool:
    """True where a native window can open (always outside Linux; X11 or Wayland on Linux)."""
    if not sys.platform.startswith("linux"):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def check_rrd_file(path: str | os.PathLike) -> Path:
    """Refuse a file that is missing or is not a rerun recording (by its magic bytes)."""
    path = Path(path)
    if not path.is_file():
        raise ViewerError(f"{path}: .rrd file not found")
    with open(path, "rb") as f:
        head = f.read(4)
    if head not in RRD_MAGIC:
        raise ViewerError(f"{path}: not a rerun recording (starts with {head!r}, expected one of "
                          f"{', '.join(repr(m) for m in RRD_MAGIC)})")
    return path

MODES = ("native", "web", "rrd")


@dataclass(frozen=True)
class ViewerConfig:
    """rerun viewer settings."""

    host: str = "127.0.0.1"
    """Address the viewer's servers bind to. Loopback unless you mean to share it."""
    grpc_port: int = 0
    """gRPC proxy port; 0 = a free port."""
    web_port: int = 0
    """Web viewer HTTP port (web mode); 0 = a free port."""
    max_scene_points: int = 200_000
    """Scene cloud is randomly subsampled to this many points (keeps the viewer responsive)."""
    image_every_n_steps: int = 1
    """Log camera images every n-th reading (images dominate the .rrd size)."""
    trajectory_every_n_steps: int = 5
    """Re-log the growing trajectory line every n steps (and at close)."""
    jpeg_quality: int | None = None
    """Compress color images with JPEG at this quality (None = raw RGB)."""
    extra_viewer_args: tuple[str, ...] = ()
    """Extra ``rerun`` arguments (e.g. ``--headless`` in tests)."""
    input_image_plane_m: float = 0.15
    """Drawn depth of the input-view frusta, metres."""
    scene_clip_above_floor_m: float | None = 2.0
    """Scene points higher than this above the floor are left out of the 3D view (ceilings and wall
    tops would hide the robot from above); None keeps all. Scenes without a floor keep all."""
    live_max_image_hz: float = 5.0
    """Live viewers (native / web): camera images are logged at most this often per second of wall
    time, newer ones replacing older ones, so the viewer never falls behind the simulation; 0 = all.
    The ``.rrd`` of an ``rrd``-only viewer always gets every image (``image_every_n_steps``)."""
    live_jpeg_quality: int | None = 85
    """Live viewers: JPEG quality of the colour images (a tenth of the bytes to stream); None = raw."""
    keep_open: bool = False
    """Web mode: keep serving the viewer after the run ends (:meth:`RerunViewer.wait_closed` stops it)."""
    blueprint: bool = True
    """Send a layout: 3D view above and behind the robot (following it), colour and depth as separate
    panels."""


@dataclass(frozen=True)
class LinkVisual:
    """One URDF ``<visual>``: a primitive (or a mesh file) fixed to a link."""

    link: str
    T_link_geom: np.ndarray
    """4x4 pose of the geometry in the link frame."""
    kind: str
    """``box`` | ``cylinder`` (along z, centred) | ``sphere`` | ``mesh``."""
    size: tuple[float, ...]
    """box: (x, y, z) full sizes; cylinder: (radius, length); sphere: (radius,); mesh: scale (x, y, z)."""
    mesh_path: str | None = None
    rgba: tuple[float, float, float, float] | None = None


def robot_visuals(urdf_xml: str) -> list[LinkVisual]:
    """The robot's visual geometry from its URDF text (yourdfpy parses; no meshes are loaded)."""
    import io

    import yourdfpy

    urdf = yourdfpy.URDF.load(io.StringIO(urdf_xml), load_meshes=False, build_scene_graph=False,
                              build_collision_scene_graph=False)
    out = []
    for link in urdf.robot.links:
        for v in link.visuals:
            T = np.asarray(v.origin, dtype=np.float64) if v.origin is not None else np.eye(4)
            g = v.geometry
            rgba = None
            if v.material is not None and v.material.color is not None:
                rgba = tuple(float(c) for c in v.material.color.rgba)
            if g.box is not None:
                out.append(LinkVisual(link.name, T, "box", tuple(float(x) for x in g.box.size), rgba=rgba))
            elif g.cylinder is not None:
                out.append(LinkVisual(link.name, T, "cylinder", (float(g.cylinder.radius), float(g.cylinder.length)),
                                      rgba=rgba))
            elif g.sphere is not None:
                out.append(LinkVisual(link.name, T, "sphere", (float(g.sphere.radius),), rgba=rgba))
            elif g.mesh is not None:
                scale = g.mesh.scale if g.mesh.scale is not None else (1.0, 1.0, 1.0)
                scale = np.broadcast_to(np.asarray(scale, dtype=np.float64), (3,))
                out.append(LinkVisual(link.name, T, "mesh", tuple(float(x) for x in scale),
                                      mesh_path=g.mesh.filename, rgba=rgba))
    return out


def viewer_blueprint(base_entity: str, T_world_base: np.ndarray, camera_entity: str | None):
    """rerun layout: a 3D view whose eye starts 2.5 m behind and 2.5 m above the robot looking at it
    (and follows it), plus the camera's colour and depth as two separate 2D panels."""
    import rerun.blueprint as rrb

    p = np.asarray(T_world_base, dtype=np.float64)[:3, 3]
    fwd = np.asarray(T_world_base, dtype=np.float64)[:3, 0]
    fwd = fwd / max(np.linalg.norm(fwd[:2]), 1e-9)
    eye = p - 2.5 * np.array([fwd[0], fwd[1], 0.0]) + np.array([0.0, 0.0, 2.5])
    view3d = rrb.Spatial3DView(
        name="3D (follows the robot)", origin="world",
        eye_controls=rrb.EyeControls3D(position=eye.tolist(), look_target=(p + [0, 0, 0.5]).tolist(),
                                       eye_up=[0.0, 0.0, 1.0], tracking_entity=base_entity))
    if camera_entity is None:
        return rrb.Blueprint(view3d, collapse_panels=True)
    images = rrb.Vertical(
        rrb.Spatial2DView(name="colour", origin=camera_entity, contents=f"{camera_entity}/color"),
        rrb.Spatial2DView(name="depth", origin=camera_entity, contents=f"{camera_entity}/depth"))
    return rrb.Blueprint(rrb.Horizontal(view3d, images, column_shares=[2, 1]), collapse_panels=True)


def free_port(host: str = "127.0.0.1") -> int:
    with socket.socket() as s:
        s.bind((host, 0))
        return s.getsockname()[1]


def wait_for_port(host: str, port: int, timeout_s: float = 20.0, process: subprocess.Popen | None = None) -> None:
    """Wait until something accepts connections on ``host:port`` (fail early if ``process`` exits)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if process is not None and process.poll() is not None:
            raise TimeoutError(f"the process exited with code {process.returncode} before listening on "
                               f"{host}:{port}")
        try:
            with socket.create_connection((host, port), timeout=0.5):
                return
        except OSError:
            time.sleep(0.1)
    raise TimeoutError(f"nothing listens on {host}:{port} after {timeout_s:.0f} s")


def rerun_executable() -> list[str]:
    """Command that starts the ``rerun`` binary shipped with rerun-sdk (same version as the SDK).
    The binary itself when found: ``python -m rerun`` runs it as a child, which a plain terminate
    would leave behind."""
    try:
        import rerun_cli

        exe = Path(rerun_cli.__file__).parent / "rerun"
        if exe.is_file() and os.access(exe, os.X_OK):
            return [str(exe)]
    except ImportError:
        pass
    return [sys.executable, "-m", "rerun"]


def web_viewer_url(host: str, web_port: int, grpc_port: int) -> str:
    proxy = f"rerun+http://{host}:{grpc_port}/proxy"
    return f"http://{host}:{web_port}/?url={urllib.parse.quote(proxy, safe='')}"


def _viewer_env() -> dict[str, str]:
    env = dict(os.environ)
    env.setdefault("RERUN_ANALYTICS", "0")  # no usage reports from a simulator run
    return env


class RerunViewer:
    """A synchronous :class:`~presim.sim.types.Sink` logging to rerun (wrap it in ``QueuedSink``)."""

    def __init__(self, mode: str, rrd_path: str | os.PathLike | None = None,
                 config: ViewerConfig = ViewerConfig()):
        if mode not in MODES:
            raise ValueError(f"unknown viewer mode {mode!r}; choose one of {', '.join(MODES)}")
        if mode == "rrd" and rrd_path is None:
            raise ValueError("viewer mode 'rrd' needs an .rrd path")
        if mode == "native" and "--headless" not in config.extra_viewer_args and not has_display():
            raise ViewerError("--viewer native: no display (DISPLAY and WAYLAND_DISPLAY are unset); use "
                              "--viewer web (browser on 127.0.0.1) or --viewer rrd with --rrd FILE")
        self.mode = mode
        self.rrd_path = Path(rrd_path) if rrd_path is not None else None
        if self.rrd_path is not None and self.rrd_path.suffix != ".rrd":
            raise ValueError(f"{self.rrd_path}: a rerun recording must end in .rrd")
        # Written as <name>.rrd.partial, renamed when closed: a killed run leaves no .rrd that
        # looks complete.
        self._rrd_partial = self.rrd_path.with_name(self.rrd_path.name + ".partial") if self.rrd_path else None
        self.config = config
        self.process: subprocess.Popen | None = None
        self.url: str | None = None
        self.grpc_url: str | None = None
        self.rec = None
        self._base_xy: list[np.ndarray] = []
        self._cam_xyz: list[np.ndarray] = []
        self._steps = 0
        self._readings: dict[str, int] = {}
        self._static_logged: set[str] = set()
        self._last_image_wall: dict[str, float] = {}
        self._visuals: list[LinkVisual] = []
        self._blueprint_sent = False

    # -- connection ----------------------------------------------------------------------------
    def _start_viewer(self) -> None:
        import rerun as rr

        cfg = self.config
        grpc_port = cfg.grpc_port or free_port(cfg.host)
        cmd = rerun_executable() + ["--bind", cfg.host, "--port", str(grpc_port)]
        if self.mode == "web":
            web_port = cfg.web_port or free_port(cfg.host)
            cmd += ["--serve-web", "--web-viewer-port", str(web_port)]
            self.url = web_viewer_url(cfg.host, web_port, grpc_port)
        cmd += list(cfg.extra_viewer_args)
        # The web viewer ends with this process even when it is killed (the native window outlives
        # the run on purpose, like rr.spawn).
        self.process = subprocess.Popen(
            cmd, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
            env=_viewer_env(), start_new_session=True,
            preexec_fn=die_with_parent() if self.mode == "web" else None)
        try:
            wait_for_port(cfg.host, grpc_port, process=self.process)
            if self.mode == "web":
                wait_for_port(cfg.host, web_port, process=self.process)
        except TimeoutError as e:
            self._stop_viewer(force=True)
            hint = " (no display? try --viewer web or --viewer rrd)" if self.mode == "native" else ""
            raise ViewerError(f"rerun viewer did not start ({' '.join(cmd)}): {e}{hint}") from None
        self.grpc_url = f"rerun+http://{cfg.host}:{grpc_port}/proxy"
        sinks = [rr.GrpcSink(self.grpc_url)]
        if self.rrd_path is not None:
            sinks.append(rr.FileSink(str(self._rrd_partial)))
        self.rec.set_sinks(*sinks)
        if self.mode == "web":
            print(f"presim: web viewer at {self.url}", file=sys.stderr)

    def _stop_viewer(self, force: bool = False) -> None:
        p, self.process = self.process, None
        if p is None or (self.mode == "native" and not force):  # the window outlives the run, like rr.spawn
            return
        stop_group(p)  # own process group (start_new_session): the server and anything it started

    # -- Sink ----------------------------------------------------------------------------------
    def open(self, info: SimInfo) -> None:
        import rerun as rr

        self.rec = rr.RecordingStream("presim", recording_id=str(uuid.uuid4()))
        if self.mode == "rrd":
            self.rrd_path.parent.mkdir(parents=True, exist_ok=True)
            self.rec.save(str(self._rrd_partial))
        else:
            if self.rrd_path is not None:
                self.rrd_path.parent.mkdir(parents=True, exist_ok=True)
            self._start_viewer()
        self._tree = build_frame_tree(info)
        self._log_static(info)

    def _log_static(self, info: SimInfo) -> None:
        import rerun as rr

        rec, cfg = self.rec, self.config
        rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        pts, rgb = np.asarray(info.points_xyz, np.float32), np.asarray(info.points_rgb, np.uint8)
        floor_z = getattr(info, "floor_z_m", None)
        if floor_z is not None and cfg.scene_clip_above_floor_m is not None and len(pts):
            keep = pts[:, 2] <= floor_z + cfg.scene_clip_above_floor_m
            pts, rgb = pts[keep], rgb[keep]
        if len(pts) > cfg.max_scene_points:
            keep = np.random.default_rng(0).choice(len(pts), cfg.max_scene_points, replace=False)
            pts, rgb = pts[np.sort(keep)], rgb[np.sort(keep)]
        if len(pts):
            rec.log("world/scene", rr.Points3D(pts, colors=rgb, radii=0.01), static=True)
        for i, (T, K) in enumerate(zip(info.input_T_world_cam, info.input_intrinsics)):
            path = f"world/inputs/view_{i:04d}"
            T = np.asarray(T, dtype=np.float64)
            rec.log(path, rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]), static=True)
            rec.log(path, rr.Pinhole(image_from_camera=K.K, resolution=[K.width, K.height],
                                     camera_xyz=rr.ViewCoordinates.RDF,
                                     image_plane_distance=cfg.input_image_plane_m,
                                     color=[120, 160, 255]), static=True)
        self._entity = self._entity_paths(info)
        try:
            self._visuals = robot_visuals(info.urdf_xml)
        except Exception as e:  # noqa: BLE001 - a URDF yourdfpy cannot read still gets the box body
            print(f"presim: viewer: robot visuals not read from the URDF ({e}); drawing a box", file=sys.stderr)
            self._visuals = []

    def _entity_paths(self, info: SimInfo) -> dict[str, str]:
        """Link name -> entity path under world/robot, following the URDF parent chain."""
        parents = dict(info.link_parents)
        out: dict[str, str] = {BASE_FRAME: f"world/robot/{BASE_FRAME}"}

        def path(link: str, depth: int = 0) -> str:
            if link in out:
                return out[link]
            parent = parents.get(link)
            if parent is None or depth > 64:
                out[link] = f"{out[BASE_FRAME]}/{link}"
            else:
                out[link] = f"{path(parent, depth + 1)}/{link}"
            return out[link]

        for link in list(parents) + list(parents.values()):
            path(link)
        return out

    def _link_path(self, link: str) -> str:
        if link not in self._entity:  # a camera frame outside the URDF: hang it off base_link
            self._entity[link] = f"{self._entity[BASE_FRAME]}/{link}"
        return self._entity[link]

    def on_step(self, r: StepResult) -> None:
        import rerun as rr

        rec, cfg = self.rec, self.config
        rec.set_time("sim_time", duration=float(r.sim_time_s))
        rec.set_time("step", sequence=int(r.step_idx))
        T = np.asarray(r.T_world_base, dtype=np.float64)
        base = self._entity[BASE_FRAME]
        rec.log(base, rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]))
        if "body" not in self._static_logged:
            self._static_logged.add("body")
            self._log_robot_body(base)
        if not self._blueprint_sent and self.config.blueprint:
            self._blueprint_sent = True
            cam_path = self._link_path(r.cameras[0].frame_id) if r.cameras else None
            rr.send_blueprint(viewer_blueprint(base, T, cam_path), recording=rec)
        dynamic, static = self._tree.edges(r)
        # map->odom->base_link are replaced by the exact base pose.
        for e, is_static in [(e, False) for e in dynamic[2:]] + [(e, True) for e in static]:
            p = self._link_path(e.child)
            Tpc = e.T_parent_child
            if is_static and p in self._static_logged:
                continue
            rec.log(p, rr.Transform3D(translation=Tpc[:3, 3], mat3x3=Tpc[:3, :3]), static=is_static)
            if is_static:
                self._static_logged.add(p)
        for cam in r.cameras:
            p = self._link_path(cam.frame_id)
            n = self._readings.get(cam.sensor_name, 0)
            self._readings[cam.sensor_name] = n + 1
            K = cam.K
            if f"pinhole:{p}" not in self._static_logged:
                self._static_logged.add(f"pinhole:{p}")
                rec.log(p, rr.Pinhole(image_from_camera=K.K, resolution=[K.width, K.height],
                                      camera_xyz=rr.ViewCoordinates.RDF, image_plane_distance=0.4,
                                      color=[255, 200, 0]), static=True)
            self._cam_xyz.append(np.asarray(cam.T_world_cam, dtype=np.float64)[:3, 3])
            if n % cfg.image_every_n_steps == 0 and self._image_due(cam.sensor_name):
                img = rr.Image(np.ascontiguousarray(cam.color))
                quality = cfg.jpeg_quality if self.mode == "rrd" or cfg.live_jpeg_quality is None else cfg.live_jpeg_quality
                if quality is not None:
                    img = img.compress(jpeg_quality=quality)
                rec.log(f"{p}/color", img)
                rec.log(f"{p}/depth", rr.DepthImage(np.asarray(cam.depth_m, dtype=np.float32), meter=1.0))
        self._base_xy.append(T[:3, 3].copy())
        self._steps += 1
        if self._steps % cfg.trajectory_every_n_steps == 0 or self._steps == 1:
            self._log_trajectory()

    def _image_due(self, sensor: str) -> bool:
        """Live viewers: at most ``live_max_image_hz`` images per wall second (the rest are dropped)."""
        hz = self.config.live_max_image_hz
        if self.mode == "rrd" or hz <= 0:
            return True
        now = time.monotonic()
        if now - self._last_image_wall.get(sensor, -np.inf) < 1.0 / hz:
            return False
        self._last_image_wall[sensor] = now
        return True

    def _log_robot_body(self, base: str) -> None:
        """The URDF's visual geometry on each link's entity (static; the links' transforms move it);
        a box when the URDF has no visuals."""
        import rerun as rr

        rec = self.rec
        rec.log(f"{base}/heading", rr.Arrows3D(origins=[[0, 0, 0.02]], vectors=[[0.4, 0, 0]],
                                              colors=[[255, 60, 60]]), static=True)
        if not self._visuals:
            rec.log(f"{base}/body", rr.Boxes3D(centers=[[0, 0, 0.15]], half_sizes=[[0.25, 0.25, 0.15]],
                                               colors=[[200, 120, 40]], labels=["robot"]), static=True)
            return
        palette = {"box": [90, 90, 110], "cylinder": [200, 120, 40], "sphere": [160, 160, 160], "mesh": [180, 180, 190]}
        for k, v in enumerate(self._visuals):
            p = f"{self._link_path(v.link)}/visual_{k}"
            color = [int(255 * c) for c in v.rgba] if v.rgba is not None else palette[v.kind]
            rec.log(p, rr.Transform3D(translation=v.T_link_geom[:3, 3], mat3x3=v.T_link_geom[:3, :3]), static=True)
            if v.kind == "box":
                rec.log(p, rr.Boxes3D(half_sizes=[[x / 2 for x in v.size]], colors=[color],
                                      fill_mode="solid"), static=True)
            elif v.kind == "cylinder":
                rec.log(p, rr.Cylinders3D(radii=[v.size[0]], lengths=[v.size[1]], colors=[color],
                                          fill_mode="solid"), static=True)
            elif v.kind == "sphere":
                rec.log(p, rr.Ellipsoids3D(half_sizes=[[v.size[0]] * 3], colors=[color], fill_mode="solid"),
                        static=True)
            elif v.mesh_path is not None and Path(v.mesh_path).is_file():
                import trimesh

                mesh = trimesh.load(v.mesh_path, force="mesh")
                rec.log(p, rr.Mesh3D(vertex_positions=np.asarray(mesh.vertices) * np.asarray(v.size),
                                     triangle_indices=np.asarray(mesh.faces), albedo_factor=color), static=True)

    def _log_trajectory(self) -> None:
        import rerun as rr

        if len(self._base_xy) >= 1:
            self.rec.log("world/trajectory/base",
                         rr.LineStrips3D([np.asarray(self._base_xy)], colors=[[255, 80, 80]], radii=0.01))
        if len(self._cam_xyz) >= 1:
            self.rec.log("world/trajectory/camera",
                         rr.LineStrips3D([np.asarray(self._cam_xyz)], colors=[[255, 200, 0]], radii=0.006))

    def flush(self, timeout_s: float = 30.0) -> None:
        if self.rec is not None:
            self.rec.flush(timeout_sec=timeout_s)

    def close(self) -> None:
        if self.rec is None:
            return
        rec = self.rec
        try:
            if self._steps % self.config.trajectory_every_n_steps != 0:
                self._log_trajectory()
            rec.flush(timeout_sec=30.0)
        finally:
            rec.disconnect()  # drops the sinks: the .rrd gets its footer and is closed
            self.rec = None
            if not (self.config.keep_open and self.mode == "web"):
                self._stop_viewer()
            if self.rrd_path is not None and self._rrd_partial.exists():
                os.replace(self._rrd_partial, self.rrd_path)  # complete: under its final name

    @property
    def kept_open(self) -> bool:
        """True after ``close`` when the web viewer keeps serving (``keep_open``)."""
        return self.rec is None and self.process is not None and self.mode == "web"

    def wait_closed(self) -> None:
        """Block until Ctrl-C / SIGTERM (or the viewer exits), then stop a kept-open web viewer."""
        try:
            while self.process is not None and self.process.poll() is None:
                time.sleep(0.5)
        except KeyboardInterrupt:
            pass
        finally:
            self._stop_viewer(force=True)
