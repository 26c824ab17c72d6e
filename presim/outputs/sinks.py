"""Build the sinks the ``drive`` command attaches: recorder (MCAP + capture folder) and viewer.

Every sink is wrapped in a :class:`~presim.outputs.queue.QueuedSink`: the step loop only appends to a
bounded drop-oldest queue, a worker thread writes, and drops are counted and reported at close.
"""

from __future__ import annotations

from pathlib import Path

from presim.outputs.folder_recorder import FolderConfig, FolderRecorder
from presim.outputs.mcap_recorder import McapConfig, McapRecorder
from presim.outputs.queue import QueuedSink
from presim.outputs.viewer import RerunViewer, ViewerConfig
from presim.sim.types import Sink

__all__ = ["build_sinks", "RECORDING_NAME", "CAPTURE_DIR", "VIEWER_MODES"]

RECORDING_NAME = "recording.mcap"
CAPTURE_DIR = "capture"
VIEWER_MODES = ("native", "web", "rrd")

# Queue lengths: recorders keep more (every frame matters in a file); a live viewer wants the newest.
# An ``rrd``-only viewer writes a file and nothing else: it is a recorder.
RECORDER_QUEUE = 64
VIEWER_QUEUE = 16


def build_sinks(record_dir: Path | None, viewer: str | None, rrd_path: Path | None, *,
                overwrite: bool = False, mcap: McapConfig = McapConfig(),
                folder: FolderConfig | None = None, viewer_config: ViewerConfig = ViewerConfig()) -> list[Sink]:
    """Sinks for ``presim drive --record DIR --viewer MODE --rrd PATH``.

    Args:
        record_dir: writes ``DIR/recording.mcap`` (ROS 2 MCAP) and ``DIR/capture/`` (KinectFusion
            layout that ``presim import`` reads). None = no recording.
        viewer: ``native`` (spawn the native viewer), ``web`` (web viewer on 127.0.0.1), ``rrd``
            (file only) or None.
        rrd_path: also save the viewer stream to this ``.rrd`` file. With ``viewer=None`` and a path,
            an ``rrd`` viewer is added; with ``viewer='rrd'`` and no path, ``DIR/recording.rrd``.
        overwrite: replace existing recordings in ``record_dir`` (else FileExistsError).
    """
    sinks: list[Sink] = []
    if viewer is not None and viewer not in VIEWER_MODES:
        raise ValueError(f"unknown viewer {viewer!r}; choose one of {', '.join(VIEWER_MODES)}")
    if record_dir is not None:
        record_dir = Path(record_dir)
        if record_dir.exists() and not record_dir.is_dir():
            raise ValueError(f"{record_dir}: --record needs a folder, this is a file")
        if not overwrite:
            for name in (RECORDING_NAME, CAPTURE_DIR):
                if (record_dir / name).exists():
                    raise FileExistsError(f"{record_dir / name}: already exists (choose another --record "
                                          "folder or pass --overwrite)")
                if (record_dir / (name + ".partial")).exists():
                    raise FileExistsError(f"{record_dir / (name + '.partial')}: an interrupted recording; "
                                          f"`presim recover {record_dir}` keeps what it holds, --overwrite "
                                          "discards it")
        record_dir.mkdir(parents=True, exist_ok=True)
        sinks.append(QueuedSink(McapRecorder(record_dir / RECORDING_NAME, mcap), "mcap", RECORDER_QUEUE))
        fcfg = folder if folder is not None else FolderConfig(overwrite=overwrite)
        sinks.append(QueuedSink(FolderRecorder(record_dir / CAPTURE_DIR, fcfg), "capture", RECORDER_QUEUE))
    if viewer == "rrd" and rrd_path is None:
        if record_dir is None:
            raise ValueError("--viewer rrd needs --rrd PATH or --record DIR")
        rrd_path = record_dir / "recording.rrd"
    if viewer is None and rrd_path is not None:
        viewer = "rrd"
    if viewer is not None:
        queue = RECORDER_QUEUE if viewer == "rrd" else VIEWER_QUEUE
        sinks.append(QueuedSink(RerunViewer(viewer, rrd_path, viewer_config), f"viewer-{viewer}", queue))
    return sinks
