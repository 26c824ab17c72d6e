"""Record a drive as a plain capture folder in the KinectFusion / 7-Scenes layout.

``presim import DIR/capture`` reads it back as a capture (round trip). Files::

    frame-XXXXXX.color.png    uint8 RGB
    frame-XXXXXX.depth.png    uint16 millimetres, 0 = invalid (depths above 65.534 m also 0)
    frame-XXXXXX.pose.txt     4x4 T_world_cam (camera OPTICAL frame -> world), metres
    camera-intrinsics.txt     3x3 K
    timestamps.txt            lines "frame-XXXXXX <stamp_s>" (sim time)
    trajectory_tum.txt        "stamp x y z qx qy qz qw" of T_world_cam (TUM format)

The folder is built as ``<dir>.partial`` and renamed when the recorder closes, so an existing
``capture/`` is always complete. One camera is recorded (the first one seen unless named).
"""

from __future__ import annotations

import os
import shutil
import threading
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from presim.geometry import pose_to_tum
from presim.io_utils import atomic_write_bytes, atomic_write_text
from presim.sim.types import CameraObservation, SimInfo, StepResult

__all__ = ["FolderConfig", "FolderRecorder", "depth_to_mm_u16"]


@dataclass(frozen=True)
class FolderConfig:
    """Capture-folder recorder settings."""

    sensor_name: str | None = None
    """Camera to record; None = the first camera seen."""
    png_compression: int = 1
    """OpenCV PNG compression level 0-9; 1 is ~3x faster than the default 3 for ~10 % larger files."""
    overwrite: bool = False
    """Replace an existing folder (only when the new one is complete)."""


def depth_to_mm_u16(depth_m: np.ndarray) -> np.ndarray:
    """float32 metres (0 = invalid) -> uint16 millimetres (0 = invalid; unrepresentable -> 0)."""
    d = np.asarray(depth_m, dtype=np.float32)
    mm = np.rint(d * 1000.0)
    mm[~np.isfinite(mm) | (mm <= 0) | (mm > 65534)] = 0
    return mm.astype(np.uint16)


def _png(image: np.ndarray, level: int) -> bytes:
    img = cv2.cvtColor(image, cv2.COLOR_RGB2BGR) if image.ndim == 3 else image
    ok, buf = cv2.imencode(".png", img, [cv2.IMWRITE_PNG_COMPRESSION, int(level)])
    if not ok:
        raise OSError("PNG encoding failed")
    return buf.tobytes()


class FolderRecorder:
    """A synchronous :class:`~presim.sim.types.Sink` writing a KinectFusion-layout capture folder."""

    def __init__(self, dst: str | os.PathLike, config: FolderConfig = FolderConfig()):
        self.dst = Path(dst)
        self.config = config
        self.partial = self.dst.with_name(self.dst.name + ".partial")
        self._lock = threading.Lock()
        self._open = False
        self._K = None
        self._sensor = config.sensor_name
        self._stamps: list[str] = []
        self._tum: list[str] = []
        self.frames_written = 0

    def open(self, info: SimInfo) -> None:
        if self.dst.exists() and not self.config.overwrite:
            raise FileExistsError(f"{self.dst}: already exists (choose another --record folder)")
        if self.partial.exists():
            shutil.rmtree(self.partial)
        self.partial.mkdir(parents=True)
        self._open = True

    def on_step(self, result: StepResult) -> None:
        with self._lock:
            if not self._open:
                raise RuntimeError(f"{self.dst}: recorder is closed")
            for cam in result.cameras:
                if self._sensor is None:
                    self._sensor = cam.sensor_name
                if cam.sensor_name == self._sensor:
                    self._write_frame(cam)

    def _write_frame(self, cam: CameraObservation) -> None:
        K = cam.K.K
        if self._K is None:
            self._K = K
            atomic_write_text(self.partial / "camera-intrinsics.txt",
                              "\n".join(" ".join(f"{v:.10g}" for v in row) for row in K) + "\n")
        elif not np.allclose(self._K, K):
            raise ValueError(f"{self.dst}: camera {cam.sensor_name} changed intrinsics mid-recording; "
                             "the capture layout holds one K")
        name = f"frame-{self.frames_written:06d}"
        lvl = self.config.png_compression
        atomic_write_bytes(self.partial / f"{name}.color.png", _png(np.ascontiguousarray(cam.color), lvl))
        atomic_write_bytes(self.partial / f"{name}.depth.png", _png(depth_to_mm_u16(cam.depth_m), lvl))
        T = np.asarray(cam.T_world_cam, dtype=np.float64)
        atomic_write_text(self.partial / f"{name}.pose.txt",
                          "\n".join(" ".join(f"{v:.10f}" for v in row) for row in T) + "\n")
        self._stamps.append(f"{name} {cam.stamp_s:.9f}")
        self._tum.append(f"{cam.stamp_s:.9f} " + " ".join(f"{v:.9f}" for v in pose_to_tum(T)))
        self.frames_written += 1

    def close(self) -> None:
        with self._lock:
            if not self._open:
                return
            self._open = False
            atomic_write_text(self.partial / "timestamps.txt", "".join(s + "\n" for s in self._stamps))
            atomic_write_text(self.partial / "trajectory_tum.txt",
                              "# stamp_s x y z qx qy qz qw (T_world_cam, camera optical frame)\n"
                              + "".join(s + "\n" for s in self._tum))
            if self.dst.exists():
                shutil.rmtree(self.dst)
            os.replace(self.partial, self.dst)
