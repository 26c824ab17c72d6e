"""The KinectFusion / 7-Scenes capture folder: the one writer (``presim drive --record``'s
``capture/`` and ``presim render``), read back by the ``kinfu`` importer (``presim import``).

Files::

    frame-XXXXXX.color.png    uint8 RGB
    frame-XXXXXX.depth.png    uint16 millimetres, 0 = invalid (rule: presim.formats.depth_png)
    frame-XXXXXX.pose.txt     4x4 T_world_cam (camera OPTICAL frame -> world), metres
    frame-XXXXXX.<name>.png   optional extra images per frame (``presim render``: ``valid``)
    camera-intrinsics.txt     3x3 K (one camera for the whole folder)
    timestamps.txt            lines "frame-XXXXXX <stamp_s>"
    trajectory_tum.txt        TUM lines of T_world_cam (presim.formats.tum)

Frames are numbered from 0 in the order written. Per-frame files are written atomically as they
come, then the frame's line is appended to ``timestamps.txt``; :meth:`KinfuFolderWriter.close`
rewrites ``timestamps.txt`` and writes ``trajectory_tum.txt``. Making the folder itself
appear atomically (``capture.partial`` renamed at the end) is the caller's job.
"""

from __future__ import annotations

from pathlib import Path
from typing import Mapping

import numpy as np

from presim.formats.depth_png import encode_depth_png
from presim.formats.png import encode_png
from presim.formats.tum import write_tum
from presim.geometry import Intrinsics
from presim.io_utils import atomic_write_bytes, atomic_write_text

__all__ = ["INTRINSICS_FILE", "TIMESTAMPS_FILE", "TRAJECTORY_FILE", "frame_name", "KinfuFolderWriter"]

INTRINSICS_FILE = "camera-intrinsics.txt"
TIMESTAMPS_FILE = "timestamps.txt"
TRAJECTORY_FILE = "trajectory_tum.txt"


def frame_name(idx: int) -> str:
    """``frame-000012`` for frame position 12."""
    return f"frame-{int(idx):06d}"


class KinfuFolderWriter:
    """Writes frames into an existing folder in the capture layout above.

    Example:
        >>> w = KinfuFolderWriter(folder)                                  # doctest: +SKIP
        >>> w.write_frame(color, depth_m, T_world_cam, K, stamp_s=0.0)     # doctest: +SKIP
        >>> w.close()                                                      # doctest: +SKIP
    """

    def __init__(self, folder: str | Path, png_compression: int | None = None):
        """``png_compression``: OpenCV PNG level 0-9 for every PNG (None = OpenCV's default)."""
        self.folder = Path(folder)
        self.png_compression = png_compression
        self.frames_written = 0
        self.depth_clipped_px = 0
        """Pixels beyond the 16-bit depth range, written as 0 (see presim.formats.depth_png)."""
        self._K: np.ndarray | None = None
        self._stamps: list[float] = []
        self._poses: list[np.ndarray] = []

    def write_frame(self, color: np.ndarray, depth_m: np.ndarray, T_world_cam: np.ndarray, K: Intrinsics,
                    stamp_s: float, extra_images: Mapping[str, np.ndarray] | None = None) -> int:
        """Write one frame's files; returns the number of its depth pixels clipped (written 0).

        ``color`` uint8 (H, W, 3) RGB, ``depth_m`` float (H, W) metres (0 = invalid), ``K`` the
        camera's intrinsics (the same for every frame), ``extra_images`` name -> image written as
        ``frame-XXXXXX.<name>.png``.
        """
        Kmat = np.asarray(K.K, dtype=np.float64)
        if self._K is None:
            self._K = Kmat
            atomic_write_text(self.folder / INTRINSICS_FILE,
                              "\n".join(" ".join(f"{v:.10g}" for v in row) for row in Kmat) + "\n")
        elif not np.allclose(self._K, Kmat):
            raise ValueError(f"{self.folder}: intrinsics changed at frame {self.frames_written}; "
                             "the capture layout holds one K")
        name = frame_name(self.frames_written)
        lvl = self.png_compression
        atomic_write_bytes(self.folder / f"{name}.color.png", encode_png(color, lvl))
        depth_png, n_clipped = encode_depth_png(depth_m, 1.0, lvl)
        atomic_write_bytes(self.folder / f"{name}.depth.png", depth_png)
        for key, image in (extra_images or {}).items():
            atomic_write_bytes(self.folder / f"{name}.{key}.png", encode_png(image, lvl))
        T = np.asarray(T_world_cam, dtype=np.float64)
        atomic_write_text(self.folder / f"{name}.pose.txt",
                          "\n".join(" ".join(f"{v:.10f}" for v in row) for row in T) + "\n")
        # The frame's stamp line last, appended: a killed writer leaves a folder whose frames with
        # a stamp line are complete (presim.outputs.recover); close() rewrites the file atomically.
        with open(self.folder / TIMESTAMPS_FILE, "a") as f:
            f.write(f"{name} {float(stamp_s):.9f}\n")
        self._stamps.append(float(stamp_s))
        self._poses.append(T)
        self.frames_written += 1
        self.depth_clipped_px += n_clipped
        return n_clipped

    def close(self) -> None:
        """Write ``timestamps.txt`` and ``trajectory_tum.txt`` for the frames written so far."""
        atomic_write_text(self.folder / TIMESTAMPS_FILE,
                          "".join(f"{frame_name(i)} {s:.9f}\n" for i, s in enumerate(self._stamps)))
        write_tum(self.folder / TRAJECTORY_FILE, np.array(self._stamps), np.array(self._poses))
