"""``presim drive --record DIR`` leaves a rosbag2 bag: ``DIR/metadata.yaml`` beside the MCAP, checked
against the rosbag2 metadata format (version 8, rosbag2_storage's ``BagMetadata`` fields and types)
and opened with an independent rosbag2 reader (rosbags: its own metadata.yaml parser, MCAP reader
and CDR deserialiser), which must find every message the metadata announces."""

from __future__ import annotations

from pathlib import Path

import yaml

from presim.outputs.mcap_recorder import McapRecorder
from presim.outputs.rosbag2 import METADATA_NAME, ROSBAG2_VERSION, rosbag2_metadata
from presim.outputs.sinks import RECORDING_NAME, build_sinks
from presim.testing.steps import synthetic_info, synthetic_steps

# rosbag2_storage/yaml.hpp, BagMetadata (version 8): key -> type; nested dicts describe sub-keys.
_TIME = {"nanoseconds": int}
SPEC_V8 = {
    "version": int, "storage_identifier": str, "duration": _TIME,
    "starting_time": {"nanoseconds_since_epoch": int}, "message_count": int,
    "topics_with_message_count": list, "compression_format": str, "compression_mode": str,
    "relative_file_paths": list, "files": list, "custom_data": dict, "ros_distro": str,
}
TOPIC_SPEC = {"topic_metadata": {"name": str, "type": str, "serialization_format": str,
                                 "offered_qos_profiles": str, "type_description_hash": str},
              "message_count": int}
FILE_SPEC = {"path": str, "starting_time": {"nanoseconds_since_epoch": int}, "duration": _TIME,
             "message_count": int}
QOS_KEYS = {"history", "depth", "reliability", "durability", "deadline", "lifespan", "liveliness",
            "liveliness_lease_duration", "avoid_ros_namespace_conventions"}


def _check(d: dict, spec: dict, where: str) -> None:
    assert set(d) == set(spec), f"{where}: keys {sorted(d)} != {sorted(spec)}"
    for k, t in spec.items():
        if isinstance(t, dict):
            _check(d[k], t, f"{where}.{k}")
        else:
            assert isinstance(d[k], t) and not isinstance(d[k], bool), f"{where}.{k}: {d[k]!r} is not {t.__name__}"


def _record(tmp_path: Path, n_steps: int = 12) -> Path:
    bag = tmp_path / "bag"
    sinks = build_sinks(bag, None, None)
    info = synthetic_info()
    for s in sinks:
        s.open(info)
    for r in synthetic_steps(n_steps):
        for s in sinks:
            s.on_step(r)
    for s in sinks:
        s.close()
    return bag


def test_drive_record_folder_is_a_rosbag2_bag_by_the_format(tmp_path):
    bag = _record(tmp_path)
    text = (bag / METADATA_NAME).read_text()
    info = yaml.safe_load(text)["rosbag2_bagfile_information"]
    _check(info, SPEC_V8, "rosbag2_bagfile_information")
    assert info["version"] == ROSBAG2_VERSION == 8 and info["storage_identifier"] == "mcap"
    assert info["relative_file_paths"] == [RECORDING_NAME] and (bag / RECORDING_NAME).is_file()
    assert not list(bag.glob("*.partial"))
    for t in info["topics_with_message_count"]:
        _check(t, TOPIC_SPEC, t["topic_metadata"]["name"])
        assert t["topic_metadata"]["serialization_format"] == "cdr"
        assert t["topic_metadata"]["type"].count("/") == 2  # pkg/msg/Name
        q = t["topic_metadata"]["offered_qos_profiles"]
        if q:  # a YAML list of QoS profiles, as ros2 bag record writes them
            profiles = yaml.safe_load(q)
            assert isinstance(profiles, list) and all(set(p) == QOS_KEYS for p in profiles)
    (f,) = info["files"]
    _check(f, FILE_SPEC, "files[0]")
    counts = {t["topic_metadata"]["name"]: t["message_count"] for t in info["topics_with_message_count"]}
    assert info["message_count"] == f["message_count"] == sum(counts.values())
    assert counts["/clock"] == 12 and counts["/tf_static"] == 1
    assert info["duration"]["nanoseconds"] == f["duration"]["nanoseconds"] > 0
    latched = {t["topic_metadata"]["name"] for t in info["topics_with_message_count"]
               if "durability: 1" in t["topic_metadata"]["offered_qos_profiles"]}
    assert {"/tf_static", "/map_cloud", "/robot_description"} <= latched


def test_rosbag2_reader_opens_the_folder_and_reads_every_message(tmp_path):
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import Stores, get_typestore

    bag = _record(tmp_path)
    meta = yaml.safe_load((bag / METADATA_NAME).read_text())["rosbag2_bagfile_information"]
    ts = get_typestore(Stores.ROS2_HUMBLE)
    with Reader(bag) as reader:  # parses metadata.yaml, then the MCAP it names
        assert reader.message_count == meta["message_count"]
        assert reader.duration == meta["duration"]["nanoseconds"] + 1  # rosbags counts both ends
        by_topic = {c.topic: c for c in reader.connections}
        assert by_topic["/tf_static"].ext.offered_qos_profiles[0].durability.value == 1  # transient local
        seen: dict[str, int] = {}
        for conn, _t, raw in reader.messages():
            msg = ts.deserialize_cdr(raw, conn.msgtype)
            seen[conn.topic] = seen.get(conn.topic, 0) + 1
            if conn.msgtype == "sensor_msgs/msg/Image":
                assert len(msg.data) == msg.step * msg.height
        assert seen == {c.topic: c.msgcount for c in reader.connections}


def test_metadata_is_rebuilt_from_the_file_not_the_recorder(tmp_path):
    """The numbers come from the MCAP summary: a second look at the same file gives the same dict,
    and a recorder used without build_sinks writes it too."""
    rec = McapRecorder(tmp_path / "solo" / "x.mcap")
    rec.open(synthetic_info())
    for r in synthetic_steps(3):
        rec.on_step(r)
    rec.close()
    on_disk = yaml.safe_load((tmp_path / "solo" / METADATA_NAME).read_text())
    assert on_disk == rosbag2_metadata(tmp_path / "solo" / "x.mcap")
    assert on_disk["rosbag2_bagfile_information"]["relative_file_paths"] == ["x.mcap"]
