"""rosbag2 ``metadata.yaml`` beside an MCAP file, so that its folder is a rosbag2 bag
(``ros2 bag info DIR``, ``ros2 bag play DIR``).

The numbers come from the finished MCAP's summary (message counts per channel, first and last log
time), so they are right whatever wrote the file. Format: rosbag2 metadata **version 8** (Jazzy;
Kilted reads it too): ``offered_qos_profiles`` is a YAML string per topic (what the recorder stores
in its channel metadata), ``type_description_hash`` is empty (allowed; the bag carries the full
``ros2msg`` schemas). Fields and their meaning: rosbag2_storage's ``BagMetadata``
(``rosbag2_storage/bag_metadata.hpp``, ``yaml.hpp``).
"""

from __future__ import annotations

import os
from pathlib import Path

import yaml

__all__ = ["METADATA_NAME", "ROSBAG2_VERSION", "rosbag2_metadata", "write_rosbag2_metadata"]

METADATA_NAME = "metadata.yaml"
ROSBAG2_VERSION = 8


def rosbag2_metadata(mcap_path: str | os.PathLike) -> dict:
    """The ``metadata.yaml`` content (a dict) of a bag made of this one finished MCAP file."""
    from mcap.reader import make_reader

    mcap_path = Path(mcap_path)
    with open(mcap_path, "rb") as f:
        summary = make_reader(f).get_summary()
    if summary is None or summary.statistics is None:
        raise ValueError(f"{mcap_path}: MCAP file has no summary (not finished?)")
    stats = summary.statistics
    counts = stats.channel_message_counts
    topics = []
    for cid, ch in sorted(summary.channels.items()):
        schema = summary.schemas.get(ch.schema_id)
        topics.append({"topic_metadata": {"name": ch.topic, "type": schema.name if schema else "",
                                          "serialization_format": ch.message_encoding,
                                          "offered_qos_profiles": ch.metadata.get("offered_qos_profiles", ""),
                                          "type_description_hash": ""},
                       "message_count": int(counts.get(cid, 0))})
    n = int(stats.message_count)
    start = int(stats.message_start_time) if n else 0
    duration = int(stats.message_end_time - stats.message_start_time) if n else 0
    info = {
        "version": ROSBAG2_VERSION,
        "storage_identifier": "mcap",
        "duration": {"nanoseconds": duration},
        "starting_time": {"nanoseconds_since_epoch": start},
        "message_count": n,
        "topics_with_message_count": topics,
        "compression_format": "",
        "compression_mode": "",
        "relative_file_paths": [mcap_path.name],
        "files": [{"path": mcap_path.name, "starting_time": {"nanoseconds_since_epoch": start},
                   "duration": {"nanoseconds": duration}, "message_count": n}],
        "custom_data": {},
        "ros_distro": "",
    }
    return {"rosbag2_bagfile_information": info}


def write_rosbag2_metadata(mcap_path: str | os.PathLike) -> Path:
    """Write ``metadata.yaml`` beside ``mcap_path`` (atomically: temp file + rename). Returns its path."""
    mcap_path = Path(mcap_path)
    dst = mcap_path.with_name(METADATA_NAME)
    text = yaml.safe_dump(rosbag2_metadata(mcap_path), sort_keys=False, default_flow_style=False)
    tmp = dst.with_name(dst.name + ".partial")
    tmp.write_text(text)
    os.replace(tmp, dst)
    return dst
