"""Recover what a killed recording wrote (``presim recover DIR``).

A recorder writes under ``<name>.partial`` and renames at close; a process killed with SIGKILL (or
a power cut) never renames. What recovery keeps, per output:

* **MCAP** (``recording.mcap.partial``): the recorder finishes a chunk and flushes the file every
  ``McapConfig.flush_every_n_steps`` steps, so the file holds a readable prefix of complete chunks.
  Recovery reads it with ``mcap``'s stream reader up to the first incomplete record and rewrites
  every schema, channel, metadata record and message of the complete chunks into a new file with
  a summary and index (what ``mcap.reader.make_reader`` needs), then renames it to ``recording.mcap``.
* **rerun** (``*.rrd.partial``): an ``.rrd`` is a 12-byte header and length-prefixed messages.
  Recovery truncates the file after the last complete message and appends the end-of-stream
  message (rerun reads it as a file without footer and index: ``RrdReader(...).stream()`` and
  ``rerun FILE`` work); then it renames it to ``*.rrd``.
* **capture folder** (``capture.partial/``, the KinectFusion layout): each per-frame file is
  written atomically and each frame's stamp is appended to ``timestamps.txt`` after its files, so
  the frames with color, depth, pose and a stamp line form a prefix. Recovery keeps that prefix,
  deletes later files and temporary files, rewrites ``timestamps.txt`` and ``trajectory_tum.txt``
  for it and renames the folder to ``capture/`` (``presim import`` reads it).

A recovered file is never written over an existing complete one unless ``overwrite``.
"""

from __future__ import annotations

import os
import re
import shutil
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["Recovered", "recover_mcap", "recover_rrd", "recover_capture", "recover_dir"]

PARTIAL = ".partial"


@dataclass(frozen=True)
class Recovered:
    """One recovered output."""

    path: Path
    """The complete file or folder now under its final name."""
    kind: str
    """``mcap``, ``rrd`` or ``capture``."""
    kept: int
    """Messages (mcap, rrd) or frames (capture) kept."""
    dropped_bytes: int
    """Bytes of the incomplete tail that were left out."""


def _final_name(partial: Path, overwrite: bool) -> Path:
    if not partial.name.endswith(PARTIAL):
        raise ValueError(f"{partial}: not an interrupted output (no {PARTIAL} suffix)")
    final = partial.with_name(partial.name[: -len(PARTIAL)])
    if final.exists() and not overwrite:
        raise FileExistsError(f"{final}: already exists; pass --overwrite to replace it with what "
                              f"{partial.name} holds")
    return final


def recover_mcap(partial: str | os.PathLike, overwrite: bool = False) -> Recovered:
    """Rewrite the complete chunks of ``X.mcap.partial`` as a valid, indexed ``X.mcap``."""
    from mcap import records as R
    from mcap.stream_reader import StreamReader
    from mcap.writer import CompressionType, Writer

    partial = Path(partial)
    final = _final_name(partial, overwrite)
    tmp = final.with_name(f".{final.name}.recover.tmp")
    kept = 0
    good_end = 0
    with open(partial, "rb") as src, open(tmp, "wb") as dst:
        writer = Writer(dst, compression=CompressionType.ZSTD)
        schemas: dict[int, int] = {}
        channels: dict[int, int] = {}
        started = False
        try:
            for rec in StreamReader(src, skip_magic=False).records:
                if isinstance(rec, R.Header):
                    writer.start(profile=rec.profile, library=rec.library)
                    started = True
                elif not started:
                    break
                elif isinstance(rec, R.Schema):
                    if rec.id not in schemas:
                        schemas[rec.id] = writer.register_schema(rec.name, rec.encoding, rec.data)
                elif isinstance(rec, R.Channel):
                    if rec.id not in channels:
                        channels[rec.id] = writer.register_channel(rec.topic, rec.message_encoding,
                                                                   schemas.get(rec.schema_id, 0), rec.metadata)
                elif isinstance(rec, R.Message):
                    if rec.channel_id in channels:
                        writer.add_message(channels[rec.channel_id], log_time=rec.log_time, data=rec.data,
                                           publish_time=rec.publish_time, sequence=rec.sequence)
                        kept += 1
                elif isinstance(rec, R.Metadata):
                    writer.add_metadata(rec.name, rec.metadata)
                elif isinstance(rec, R.Attachment):
                    writer.add_attachment(rec.create_time, rec.log_time, rec.name, rec.media_type, rec.data)
                elif isinstance(rec, (R.DataEnd, R.Footer)):
                    break
                good_end = src.tell()
        except Exception:  # noqa: BLE001 - the first incomplete or corrupt record ends the readable part
            pass
        if not started:
            dst.close()
            tmp.unlink(missing_ok=True)
            raise ValueError(f"{partial}: no MCAP header; nothing to recover")
        writer.finish()
    os.replace(tmp, final)
    size = partial.stat().st_size
    partial.unlink()
    return Recovered(final, "mcap", kept, max(0, size - good_end))


_RRD_HEADER = 12  # b"RRF2" + version (4 bytes) + encoding options (4 bytes)
_RRD_MSG = struct.Struct("<QQ")  # message kind, payload length
_RRD_END = 0


def recover_rrd(partial: str | os.PathLike, overwrite: bool = False) -> Recovered:
    """Cut ``X.rrd.partial`` after its last complete message, end the stream, rename to ``X.rrd``."""
    partial = Path(partial)
    final = _final_name(partial, overwrite)
    size = partial.stat().st_size
    with open(partial, "rb") as f:
        head = f.read(_RRD_HEADER)
        if len(head) < _RRD_HEADER or head[:4] != b"RRF2":
            raise ValueError(f"{partial}: no rerun RRF2 header; nothing to recover")
        off, kept = _RRD_HEADER, 0
        while off + _RRD_MSG.size <= size:
            f.seek(off)
            kind, length = _RRD_MSG.unpack(f.read(_RRD_MSG.size))
            if kind == _RRD_END or off + _RRD_MSG.size + length > size:
                break
            off += _RRD_MSG.size + length
            kept += 1
    with open(partial, "r+b") as f:
        f.truncate(off)
        f.seek(off)
        f.write(_RRD_MSG.pack(_RRD_END, 0))
    os.replace(partial, final)
    return Recovered(final, "rrd", kept, size - off)


def recover_capture(partial: str | os.PathLike, overwrite: bool = False) -> Recovered:
    """Keep the complete frames of a ``capture.partial/`` folder and rename it to ``capture/``."""
    from presim.formats.kinfu_folder import INTRINSICS_FILE, TIMESTAMPS_FILE, TRAJECTORY_FILE, frame_name
    from presim.formats.tum import write_tum
    from presim.io_utils import atomic_write_text

    partial = Path(partial)
    final = _final_name(partial, overwrite)
    if not (partial / INTRINSICS_FILE).is_file():
        raise ValueError(f"{partial}: no {INTRINSICS_FILE} (no frame was written); nothing to recover")
    stamps: dict[str, float] = {}
    ts = partial / TIMESTAMPS_FILE
    if ts.is_file():
        for line in ts.read_text(errors="replace").split("\n")[:-1]:  # complete lines only
            parts = line.split()
            if len(parts) == 2:
                try:
                    stamps[parts[0]] = float(parts[1])
                except ValueError:
                    pass
    poses, times = [], []
    n = 0
    while True:
        name = frame_name(n)
        if not all((partial / f"{name}.{k}").is_file() for k in ("color.png", "depth.png", "pose.txt")) \
                or name not in stamps:
            break
        try:
            T = np.loadtxt(partial / f"{name}.pose.txt").reshape(4, 4)
        except ValueError:
            break
        poses.append(T)
        times.append(stamps[name])
        n += 1
    if n == 0:
        raise ValueError(f"{partial}: no complete frame; nothing to recover")
    dropped = 0
    frame_re = re.compile(r"frame-(\d{6})\.")
    for p in partial.iterdir():
        m = frame_re.match(p.name)
        if p.name.startswith(".") or (m and int(m.group(1)) >= n):  # temporary files, incomplete frames
            dropped += p.stat().st_size if p.is_file() else 0
            p.unlink() if p.is_file() else shutil.rmtree(p)
    atomic_write_text(ts, "".join(f"{frame_name(i)} {s:.9f}\n" for i, s in enumerate(times)))
    write_tum(partial / TRAJECTORY_FILE, np.array(times), np.array(poses))
    if final.exists():
        shutil.rmtree(final)
    os.replace(partial, final)
    return Recovered(final, "capture", n, dropped)


def recover_dir(folder: str | os.PathLike, overwrite: bool = False, log=None) -> list[Recovered]:
    """Recover every interrupted output in ``folder`` (a ``presim drive --record`` / ``--rrd``
    folder): ``*.mcap.partial``, ``*.rrd.partial`` and capture folders ``*.partial/``. ``folder``
    may also be one such partial file or folder."""
    folder = Path(folder)
    if not folder.exists():
        raise FileNotFoundError(f"{folder}: not found")
    cands = [folder] if folder.name.endswith(PARTIAL) else sorted(p for p in folder.iterdir()
                                                                  if p.name.endswith(PARTIAL))
    out, errors = [], []
    for p in cands:
        try:
            if p.is_dir():
                out.append(recover_capture(p, overwrite))
            elif p.name.endswith(".mcap" + PARTIAL):
                out.append(recover_mcap(p, overwrite))
            elif p.name.endswith(".rrd" + PARTIAL):
                out.append(recover_rrd(p, overwrite))
            elif log is not None:
                log(f"{p}: not a recording; left as it is")
        except (OSError, ValueError) as e:  # one damaged output does not stop the others
            errors.append(str(e))
    if errors:
        raise ValueError("; ".join(errors) + (f" (recovered: {', '.join(str(r.path) for r in out)})" if out else ""))
    return out
