"""The robot's frame tree in ROS terms, shared by the MCAP recorder, the ROS bridge and the viewer.

Frames (REP-105 / REP-103): ``map`` (= the scene's world frame) -> ``odom`` -> ``base_link`` ->
URDF links ... -> ``camera_optical_frame`` (OpenCV optical frame, REP-103 ``*_optical_frame``).
``map -> odom`` absorbs odometry drift so that ``map -> base_link`` is the exact ground truth:
``T_map_odom = T_world_base @ inv(T_odom_base)``.

Edges of fixed URDF joints are static (``/tf_static``); every other edge is dynamic (``/tf``).
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass

import numpy as np

from presim.geometry import compose, invert
from presim.sim.types import SimInfo, StepResult

__all__ = ["MAP_FRAME", "ODOM_FRAME", "BASE_FRAME", "FrameEdge", "FrameTree", "build_frame_tree",
           "urdf_fixed_children", "stamp_ns"]

MAP_FRAME = "map"
ODOM_FRAME = "odom"
BASE_FRAME = "base_link"


def stamp_ns(stamp_s: float) -> int:
    """Sim time in seconds -> integer nanoseconds (ROS/MCAP stamps)."""
    return int(round(float(stamp_s) * 1e9))


@dataclass(frozen=True)
class FrameEdge:
    """One transform of the tree: ``T_parent_child`` maps child-frame points to the parent frame."""

    parent: str
    child: str
    T_parent_child: np.ndarray


def urdf_fixed_children(urdf_xml: str) -> set[str]:
    """Child links of the URDF's ``fixed`` joints (their transforms never change). Empty on bad XML."""
    if not urdf_xml:
        return set()
    try:
        root = ET.fromstring(urdf_xml)
    except ET.ParseError:
        return set()
    out = set()
    for joint in root.iter("joint"):
        child = joint.find("child")
        if joint.get("type") == "fixed" and child is not None and child.get("link"):
            out.add(child.get("link"))
    return out


@dataclass(frozen=True)
class FrameTree:
    """Static description of the tree, built once from :class:`SimInfo`."""

    link_parents: dict[str, str]
    """child link -> parent link (URDF)."""
    static_children: frozenset[str]
    """Links whose edge to their parent is static (fixed joints)."""

    def edges(self, result: StepResult) -> tuple[list[FrameEdge], list[FrameEdge]]:
        """``(dynamic, static)`` edges of one step: map->odom, odom->base_link, URDF links, and any
        camera frame that is not a URDF link (attached to base_link from the camera's exact pose)."""
        T_world_base = np.asarray(result.T_world_base, dtype=np.float64)
        T_odom_base = np.asarray(result.odometry.T_odom_base, dtype=np.float64)
        dynamic = [
            FrameEdge(MAP_FRAME, ODOM_FRAME, compose(T_world_base, invert(T_odom_base))),
            FrameEdge(ODOM_FRAME, BASE_FRAME, T_odom_base),
        ]
        static: list[FrameEdge] = []
        poses = result.link_poses
        for link, T_base_link in poses.items():
            if link == BASE_FRAME:
                continue
            parent = self.link_parents.get(link)
            if parent is None or parent not in poses and parent != BASE_FRAME:
                # A root link other than base_link: hang it under base_link with its base pose.
                parent, T = BASE_FRAME, np.asarray(T_base_link, dtype=np.float64)
            else:
                T_base_parent = np.eye(4) if parent == BASE_FRAME and parent not in poses else poses[parent]
                T = compose(invert(T_base_parent), T_base_link)
            (static if link in self.static_children else dynamic).append(FrameEdge(parent, link, T))
        for cam in result.cameras:
            if cam.frame_id != BASE_FRAME and cam.frame_id not in poses:
                T_base_cam = compose(invert(T_world_base), cam.T_world_cam)
                dynamic.append(FrameEdge(BASE_FRAME, cam.frame_id, T_base_cam))
        return dynamic, static


def build_frame_tree(info: SimInfo) -> FrameTree:
    return FrameTree(link_parents=dict(info.link_parents),
                     static_children=frozenset(urdf_fixed_children(info.urdf_xml)))
