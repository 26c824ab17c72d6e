"""The built-in sample scene: a procedural, textured room captured along a hand-held trajectory.

:func:`build_sample_scene` builds, deterministically from a seed, a ~5 x 4 m room (floor, four walls
with a door to a short corridor, ceiling, a rug, a table, a bookshelf, a sideboard, a poster, a dark TV,
cardboard boxes and a bin on the floor) and 3-5 textured objects standing on the table (box, can,
non-convex bracket, ball, irregular rock; 5-25 cm). It ray casts every pixel of every frame with
Open3D's ``RaycastingScene``: color = procedural albedo(material, hit point) x Lambertian shading
of fixed point lights with hard shadows -- nothing depends on the viewing direction, so a pixel's color
is a property of the surface point alone and reprojection with exact depth and poses is near-exact.

The saved scene's ``depth.npy`` is a *realistically corrupted* copy of the exact depth
(:func:`corrupt_depth`: noise growing with z^2, holes on dark / grazing / out-of-range surfaces and
behind depth edges, a few pixels of color/depth misregistration); the exact depth and the rest of the
ground truth are in ``DST/ground_truth/`` (see docs/sample-scene.md)::

    ground_truth/
      depth_clean.npy   float32 (N, H, W) exact z-depth, metres (0 = no surface)
      object_id.npy     uint8   (N, H, W) obj_id of the visible object, 0 = background
      room.ply          the whole scene (room + furniture + objects) in world metres, per-vertex colors
      parts.json        every part: name, kind, obj_id, world AABB, triangle range in room.ply
      sample.json       seed + SampleSceneConfig + lights: enough to re-render any view exactly

Modules: :mod:`.config` (:class:`SampleSceneConfig`), :mod:`.layout` (room parts and the capture
trajectory), :mod:`.render` (Open3D + numba ray caster), :mod:`.corrupt` (the depth sensor; its
noise law is :class:`presim.sensors.noise.QuadraticNoiseConfig`), :mod:`.store` (build / load).
Everything public is importable from ``presim.capture.sample_scene``.

Example:
    >>> from presim.capture.sample_scene import build_sample_scene, render_ground_truth
    >>> dst = build_sample_scene("out/sample", seed=0)                     # doctest: +SKIP
    >>> from presim.capture.store import load_scene
    >>> scene = load_scene(dst)                                            # doctest: +SKIP
    >>> color, depth_m, obj = render_ground_truth(dst, scene.T_world_cam[0], scene.intrinsics[0])  # doctest: +SKIP
"""

from presim.capture.sample_scene.config import SampleSceneConfig
from presim.capture.sample_scene.corrupt import corrupt_depth
from presim.capture.sample_scene.layout import capture_trajectory, sample_layout
from presim.capture.sample_scene.render import RenderedView, render_view
from presim.capture.sample_scene.store import (
    SampleGroundTruth, SamplePart, build_sample_scene, clean_scene, load_sample_ground_truth,
    render_ground_truth, render_object_silhouettes,
)

__all__ = [
    "SampleSceneConfig", "SamplePart", "SampleGroundTruth", "RenderedView",
    "build_sample_scene", "load_sample_ground_truth", "clean_scene", "render_ground_truth",
    "render_object_silhouettes",
    "render_view", "corrupt_depth", "capture_trajectory", "sample_layout",
]
