"""Record a drive as a plain capture folder in the KinectFusion / 7-Scenes layout.

``presim import DIR/capture`` reads it back as a capture (round trip). The files and their rules
belong to :mod:`presim.formats.kinfu_folder` (the one capture-folder writer, also used by
``presim render``): color / depth (uint16 mm, 0 = invalid; depths that do not fit 1..65535 mm are
written 0 and counted) / pose PNG and text files per frame, ``camera-intrinsics.txt``,
``timestamps.txt`` and ``trajectory_tum.txt``.

The folder is built as ``<dir>.partial`` and renamed when the recorder closes, so an existing
``capture/`` is always complete. One camera is recorded (the first one seen unless named). Depth
pixels lost to the 16-bit range are counted in ``depth_clipped_px`` and logged as a warning at close.
"""

from __future__ import annotations

import logging
import os
import shutil
import threading
from dataclasses import dataclass
from pathlib import Path

from presim.formats.kinfu_folder import KinfuFolderWriter
from presim.sim.types import CameraObservation, SimInfo, StepResult

__all__ = ["FolderConfig", "FolderRecorder"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FolderConfig:
    """Capture-folder recorder settings."""

    sensor_name: str | None = None
    """Camera to record; None = the first camera seen."""
    png_compression: int = 1
    """OpenCV PNG compression level 0-9; 1 is ~3x faster than the default 3 for ~10 % larger files."""
    overwrite: bool = False
    """Replace an existing folder (only when the new one is complete)."""


class FolderRecorder:
    """A synchronous :class:`~presim.sim.types.Sink` writing a KinectFusion-layout capture folder."""

    def __init__(self, dst: str | os.PathLike, config: FolderConfig = FolderConfig()):
        self.dst = Path(dst)
        self.config = config
        self.partial = self.dst.with_name(self.dst.name + ".partial")
        self._lock = threading.Lock()
        self._open = False
        self._sensor = config.sensor_name
        self._writer: KinfuFolderWriter | None = None

    @property
    def frames_written(self) -> int:
        return 0 if self._writer is None else self._writer.frames_written

    @property
    def depth_clipped_px(self) -> int:
        """Depth pixels beyond 65.535 m, written as 0 (presim.formats.depth_png)."""
        return 0 if self._writer is None else self._writer.depth_clipped_px

    def open(self, info: SimInfo) -> None:
        if self.dst.exists() and not self.config.overwrite:
            raise FileExistsError(f"{self.dst}: already exists (choose another --record folder)")
        if self.partial.exists():
            shutil.rmtree(self.partial)
        self.partial.mkdir(parents=True)
        self._writer = KinfuFolderWriter(self.partial, png_compression=self.config.png_compression)
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
        self._writer.write_frame(cam.color, cam.depth_m, cam.T_world_cam, cam.K, cam.stamp_s)

    def close(self) -> None:
        with self._lock:
            if not self._open:
                return
            self._open = False
            self._writer.close()
            if self.depth_clipped_px:
                log.warning("%s: %d depth pixels beyond 65.535 m written as 0 (invalid)", self.dst,
                            self.depth_clipped_px)
            if self.dst.exists():
                shutil.rmtree(self.dst)
            os.replace(self.partial, self.dst)
