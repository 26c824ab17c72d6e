"""The scene a user names on the command line: a saved scene folder or, when allowed, a capture folder
imported in memory. Sits above the store and the importers (it uses both).
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

from presim.capture.importers.registry import import_capture
from presim.capture.scene import Scene, SceneError
from presim.capture.store import is_scene_dir, load_scene

__all__ = ["open_scene"]


def open_scene(path: str | Path, allow_capture: bool = False,
               on_import: Callable[[str], None] | None = None, poses: str = "auto",
               estimate_poses: Callable[[Scene], Scene] | None = None) -> Scene:
    """The scene a user names on the command line: a saved scene folder, or with ``allow_capture``
    a capture folder any importer reads (imported in memory, not saved; ``on_import`` gets a
    one-line note first). Every refusal is a :class:`SceneError` (a ValueError) naming the path:
    missing, an interrupted save (``.partial``), not a saved scene, or what the loader / importer found.
    ``poses`` picks a saved scene's camera poses (:data:`presim.capture.store.POSE_CHOICES`, see
    :func:`~presim.capture.store.load_scene`); ``estimate_poses`` gives a capture without poses its
    poses (:func:`~presim.capture.importers.import_capture`; e.g. ``presim.align.sfm.estimate_poses``).
    """
    path = Path(path)
    if is_scene_dir(path) or path.with_name(path.name + ".partial").exists():
        return load_scene(path, poses=poses)  # an interrupted save gets load_scene's own message
    if not path.exists():
        raise SceneError(f"{path}: scene folder not found")
    if not allow_capture:
        raise SceneError(f"{path}: not a saved scene (no scene.json); import a capture first: presim import SRC DST")
    if on_import is not None:
        on_import(f"{path}: not a saved scene; importing it on the fly (save it with `presim import` to skip this)")
    try:
        return import_capture(path, estimate_poses=estimate_poses)
    except SceneError:
        raise
    except (OSError, ValueError) as e:  # the registry's "no importer recognises this", a missing file
        raise SceneError(str(e)) from e
