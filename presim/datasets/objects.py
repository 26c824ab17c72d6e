"""Object models for 6D-pose datasets: meshes or point clouds in metres, and BOP ``models_info``.

A model lives in its own object frame (BOP: ``x_cam = R_m2c x_model + t_m2c``). Inside PreSim it is in
metres; BOP files are millimetres, converted only here (:func:`models_info_entry`,
:func:`write_model_ply_mm`, :func:`load_model` with ``unit="mm"``). :class:`ObjectModel` is the one
object-model type of PreSim; PLY files are read and written by :mod:`presim.formats.ply` and BOP
``models_info.json`` rows are read into :class:`presim.formats.bop.ModelInfo`
(:func:`symmetries_of` gives its symmetries in the form :class:`ObjectModel` holds them).

Example:
    >>> m = load_model("lmo/models/obj_000001.ply", obj_id=1, unit="mm")   # doctest: +SKIP
    >>> models_info_entry(m)["diameter"]                                   # doctest: +SKIP
    102.099...
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from presim.formats.bop import M_TO_MM, MM_TO_M, ModelInfo, load_json
from presim.formats.ply import read_ply, write_ply
from presim.io_utils import atomic_write_json

__all__ = ["ObjectModel", "load_model", "model_diameter_m", "models_info_entry", "models_info",
           "write_model_ply_mm", "symmetries_of"]

_UNIT_TO_M = {"m": 1.0, "mm": MM_TO_M, "cm": 1e-2}


@dataclass(frozen=True)
class ObjectModel:
    """A rigid object model in its object frame (metres)."""

    obj_id: int
    """Dataset object id (BOP ``obj_id``, >= 1)."""
    name: str
    """Human-readable name (e.g. ``ape``)."""
    vertices_m: np.ndarray
    """float32 (V, 3) vertex positions, metres, object frame."""
    faces: np.ndarray | None = None
    """int32 (F, 3) triangle vertex indices; None for a point-cloud model."""
    colors: np.ndarray | None = None
    """uint8 (V, 3) per-vertex RGB, or None."""
    normals: np.ndarray | None = None
    """float32 (V, 3) per-vertex unit normals, or None."""
    symmetries_discrete: tuple[np.ndarray, ...] = ()
    """4x4 object-frame transforms (metres) under which the model looks the same (BOP)."""
    symmetries_continuous: tuple[tuple[tuple[float, float, float], tuple[float, float, float]], ...] = ()
    """``(axis, offset_m)`` pairs of continuous rotational symmetries (BOP ``symmetries_continuous``)."""
    source: str = ""
    """Where the model came from (file path)."""
    symmetric_flag: bool = False
    """Marked symmetric by its source without symmetry transforms (e.g. ``SceneObject.symmetric``)."""

    def __post_init__(self) -> None:
        v = np.ascontiguousarray(self.vertices_m, dtype=np.float32)
        if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0:
            raise ValueError(f"model {self.obj_id} ({self.source}): vertices must be (V,3), got {v.shape}")
        if not np.all(np.isfinite(v)):
            raise ValueError(f"model {self.obj_id} ({self.source}): vertices contain NaN/inf")
        object.__setattr__(self, "vertices_m", v)
        if self.faces is not None:
            f = np.ascontiguousarray(self.faces, dtype=np.int32)
            if f.ndim != 2 or f.shape[1] != 3:
                raise ValueError(f"model {self.obj_id} ({self.source}): faces must be (F,3), got {f.shape}")
            if len(f) and (f.min() < 0 or f.max() >= len(v)):
                raise ValueError(f"model {self.obj_id} ({self.source}): face index out of range")
            object.__setattr__(self, "faces", f if len(f) else None)
        if self.colors is not None:
            c = np.ascontiguousarray(self.colors, dtype=np.uint8)
            if c.shape != v.shape:
                raise ValueError(f"model {self.obj_id} ({self.source}): colors must be (V,3) uint8, got {c.shape}")
            object.__setattr__(self, "colors", c)
        if self.normals is not None:
            n = np.ascontiguousarray(self.normals, dtype=np.float32)
            if n.shape != v.shape:
                raise ValueError(f"model {self.obj_id} ({self.source}): normals must be (V,3), got {n.shape}")
            object.__setattr__(self, "normals", n)
        if int(self.obj_id) < 1:
            raise ValueError(f"model {self.source}: BOP object ids start at 1, got {self.obj_id}")
        object.__setattr__(self, "obj_id", int(self.obj_id))

    @property
    def symmetric(self) -> bool:
        """Whether ADD-S applies (any discrete or continuous symmetry)."""
        return bool(self.symmetric_flag or self.symmetries_discrete or self.symmetries_continuous)

    @property
    def radius_m(self) -> float:
        """Radius of the bounding sphere around the bounding-box centre, metres."""
        c = 0.5 * (self.vertices_m.min(0) + self.vertices_m.max(0))
        return float(np.linalg.norm(self.vertices_m - c, axis=1).max())

    @property
    def center_m(self) -> np.ndarray:
        """Bounding-box centre (3,) in the object frame, metres."""
        return 0.5 * (self.vertices_m.min(0) + self.vertices_m.max(0)).astype(np.float64)


def load_model(path: str | Path, obj_id: int, name: str = "", unit: str = "m",
               symmetries_discrete: Sequence[np.ndarray] = (),
               symmetries_continuous: Sequence = ()) -> ObjectModel:
    """Read a mesh (PLY/OBJ/STL...) or a point file (``.xyz``/``.txt``: x y z per line) into metres.

    Args:
        path: model file.
        obj_id: BOP object id (>= 1).
        name: name (defaults to the file stem).
        unit: unit of the file's coordinates: ``"m"``, ``"mm"`` (BOP models) or ``"cm"``.
        symmetries_discrete: 4x4 transforms, already in metres.
        symmetries_continuous: ``(axis, offset_m)`` pairs.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: model file not found")
    if unit not in _UNIT_TO_M:
        raise ValueError(f"{path}: unknown model unit {unit!r} (use one of {sorted(_UNIT_TO_M)})")
    s = _UNIT_TO_M[unit]
    faces = colors = normals = None
    if path.suffix.lower() in (".xyz", ".txt", ".pts"):
        try:
            data = np.loadtxt(path, ndmin=2, dtype=np.float64)
        except ValueError as e:
            raise ValueError(f"{path}: not a point file of 'x y z' lines ({e})") from e
        if data.shape[1] < 3:
            raise ValueError(f"{path}: point file needs at least 3 columns, got {data.shape[1]}")
        verts = data[:, :3]
    elif path.suffix.lower() == ".ply":
        try:
            ply = read_ply(path)  # keeps the file's vertex order (BOP models_eval / symmetries index it)
        except ValueError as e:
            raise ValueError(f"{path}: unreadable model ({e})") from e
        verts, faces, colors = ply.vertices, ply.faces, ply.colors
        if faces is not None:
            normals = _vertex_normals(verts, faces)
    else:  # OBJ, STL, ... through trimesh
        import trimesh

        try:
            # process=False keeps the file's vertex order.
            geom = trimesh.load(path, process=False, force="mesh")
        except Exception as e:  # trimesh raises many types for corrupt files
            raise ValueError(f"{path}: unreadable model ({type(e).__name__}: {e})") from e
        verts = np.asarray(geom.vertices, dtype=np.float64)
        if isinstance(geom, trimesh.Trimesh) and len(geom.faces):
            faces = np.asarray(geom.faces)
        vc = getattr(getattr(geom, "visual", None), "vertex_colors", None)
        if vc is not None and getattr(geom.visual, "kind", None) == "vertex" and len(vc) == len(verts):
            colors = np.asarray(vc)[:, :3]
        if faces is not None:
            normals = _vertex_normals(verts, faces)
    return ObjectModel(
        obj_id=obj_id, name=name or path.stem, vertices_m=verts * s, faces=faces, colors=colors,
        normals=normals, symmetries_discrete=tuple(np.asarray(T, dtype=np.float64) for T in symmetries_discrete),
        symmetries_continuous=tuple((tuple(map(float, a)), tuple(map(float, o))) for a, o in symmetries_continuous),
        source=str(path),
    )


def _vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals of a triangle mesh (trimesh's rule). A PLY's own ``nx ny nz``
    are not used: the models PreSim writes carry these normals, so reading them back is exact."""
    import trimesh

    return np.asarray(trimesh.Trimesh(vertices, faces, process=False).vertex_normals)


def model_diameter_m(vertices_m: np.ndarray) -> float:
    """Largest distance between two model points (BOP ``diameter``), metres.

    Exact: the two farthest points are vertices of the convex hull, so only hull vertices are
    compared (bop_toolkit compares all pairs, which is quadratic in the vertex count).
    """
    from scipy.spatial import ConvexHull, QhullError
    from scipy.spatial.distance import pdist

    p = np.asarray(vertices_m, dtype=np.float64)
    if len(p) < 2:
        return 0.0
    try:
        p = p[ConvexHull(p).vertices]
    except (QhullError, ValueError):
        pass  # flat or degenerate point sets: fall back to all points
    if len(p) > 20000:  # bounded memory: a sub-sample of a huge hull (never hit by real models)
        p = p[np.random.default_rng(0).choice(len(p), 20000, replace=False)]
    return float(pdist(p).max())


def models_info_entry(model: ObjectModel) -> dict:
    """BOP ``models_info.json`` entry (millimetres): diameter, min_*, size_*, symmetries when given."""
    v_mm = model.vertices_m.astype(np.float64) * M_TO_MM  # BOP border: metres -> millimetres
    lo, hi = v_mm.min(0), v_mm.max(0)
    out = {
        "diameter": round(model_diameter_m(model.vertices_m) * M_TO_MM, 4),
        "min_x": round(float(lo[0]), 4), "min_y": round(float(lo[1]), 4), "min_z": round(float(lo[2]), 4),
        "size_x": round(float(hi[0] - lo[0]), 4), "size_y": round(float(hi[1] - lo[1]), 4),
        "size_z": round(float(hi[2] - lo[2]), 4),
    }
    if model.symmetries_discrete:
        syms = []
        for T in model.symmetries_discrete:
            T = np.asarray(T, dtype=np.float64).copy()
            T[:3, 3] *= M_TO_MM
            syms.append([round(float(x), 9) for x in T.ravel()])
        out["symmetries_discrete"] = syms
    if model.symmetries_continuous:
        out["symmetries_continuous"] = [
            {"axis": [float(a) for a in axis], "offset": [float(o) * M_TO_MM for o in off]}
            for axis, off in model.symmetries_continuous
        ]
    return out


def models_info(models: Sequence[ObjectModel]) -> dict:
    """``{str(obj_id): models_info_entry}`` for a list of models (sorted by id)."""
    return {str(m.obj_id): models_info_entry(m) for m in sorted(models, key=lambda m: m.obj_id)}


def symmetries_of(info: ModelInfo | None) -> tuple[tuple[np.ndarray, ...], tuple]:
    """``(symmetries_discrete, symmetries_continuous)`` of a ``models_info`` record in the form
    :class:`ObjectModel` holds them (metres; ``()`` when ``info`` is None)."""
    if info is None:
        return (), ()
    cont = tuple((tuple(map(float, axis)), tuple(map(float, off))) for axis, off in info.symmetries_continuous)
    return tuple(np.asarray(T, dtype=np.float64) for T in info.symmetries_discrete), cont


def write_model_ply_mm(model: ObjectModel, path: str | Path) -> None:
    """Write the model as a binary little-endian PLY in millimetres (the BOP ``models/`` format).

    Properties: x y z [nx ny nz] [red green blue]; faces as ``vertex_indices`` (uchar count, int).
    The bytes depend only on the model (no timestamps), so reruns write identical files.
    """
    v = model.vertices_m.astype(np.float32) * np.float32(M_TO_MM)  # BOP border: metres -> millimetres
    write_ply(path, v, model.faces, colors=model.colors, normals=model.normals,
              comment="PreSim BOP model, millimetres")


def merge_models_dir(out: str | Path, objects, hint: str = "") -> None:
    """Write ``out/models/`` (mm PLYs + ``models_info.json``) for ``objects`` (each with ``obj_id`` and
    ``model``), merged with what the folder already holds: the same id must have the same
    ``models_info`` entry, else ``ValueError`` (``hint`` is appended to its message). Shared by every
    split written into one BOP dataset (synthesized and real)."""
    info_path = Path(out) / "models" / "models_info.json"
    merged = dict(load_json(info_path)) if info_path.is_file() else {}
    for o in objects:
        entry = models_info_entry(o.model)
        key = str(o.obj_id)
        if key in merged and merged[key] != entry:
            raise ValueError(f"{info_path}: object {o.obj_id} already exists with a different model{hint}")
        merged[key] = entry
    for o in objects:
        write_model_ply_mm(o.model, Path(out) / "models" / f"obj_{o.obj_id:06d}.ply")
    atomic_write_json(info_path, {k: merged[k] for k in sorted(merged, key=int)})
