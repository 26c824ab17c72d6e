"""The one PLY reader and writer of PreSim (meshes and point clouds, ASCII or binary).

:func:`read_ply` returns a :class:`PlyMesh`: the file's contents in the **file's units** (BOP models
are millimetres; :meth:`PlyMesh.scaled` converts). It is not an object model: the object model of
the 6D-pose datasets is :class:`presim.datasets.objects.ObjectModel` (metres, id, symmetries), built
from a ``PlyMesh`` by :func:`presim.datasets.objects.load_model`.

:func:`write_ply` writes vertices ``x y z`` (float32), optional ``nx ny nz`` (float32) and
``red green blue`` (uchar), and triangles as ``vertex_indices`` (uchar count, int32 indices); binary
little-endian by default, ASCII on request. The bytes depend only on the arrays (no timestamps).

Why a reader of our own although trimesh reads PLY: it keeps the file's vertex order and values
exactly (BOP ``models_eval`` points and symmetries index them), reads normals, colours and texture
coordinates together, fan-triangulates polygons, and names the file in every error; it is tested
against trimesh on the real LM-O models (``tests/test_bop_reader.py``).

Example:
    >>> write_ply("tri.ply", np.eye(3), np.array([[0, 1, 2]]))           # doctest: +SKIP
    >>> read_ply("tri.ply").faces                                         # doctest: +SKIP
    array([[0, 1, 2]])
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from presim.io_utils import atomic_write_bytes

__all__ = ["PlyMesh", "read_ply", "write_ply"]


@dataclass(frozen=True)
class PlyMesh:
    """A mesh or point cloud as stored in a PLY file, in the file's units (BOP: mm)."""

    vertices: np.ndarray
    """(N, 3) float64 vertex positions."""
    faces: np.ndarray | None = None
    """(F, 3) int64 triangle vertex indices (polygons are fan-triangulated), or None."""
    normals: np.ndarray | None = None
    """(N, 3) float64 vertex normals, or None."""
    colors: np.ndarray | None = None
    """(N, 3) uint8 RGB vertex colours, or None."""
    texture_uv: np.ndarray | None = None
    """(N, 2) float64 per-vertex texture coordinates, or None."""

    def scaled(self, factor: float) -> "PlyMesh":
        """Same mesh with positions multiplied by ``factor`` (e.g. ``MM_TO_M``)."""
        return PlyMesh(self.vertices * factor, self.faces, self.normals, self.colors, self.texture_uv)


# ---- reader -------------------------------------------------------------------------------------

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}


@dataclass
class _PlyElement:
    name: str
    count: int
    props: list = field(default_factory=list)  # (name, dtype) or (name, ("list", count_dtype, item_dtype))


def _parse_ply_header(path: Path, f) -> tuple[str, list[_PlyElement]]:
    if f.readline().strip() != b"ply":
        raise ValueError(f"{path}: not a PLY file (missing 'ply' magic)")
    fmt = None
    elements: list[_PlyElement] = []
    while True:
        line = f.readline()
        if not line:
            raise ValueError(f"{path}: PLY header has no 'end_header'")
        parts = line.decode("ascii", errors="replace").split()
        if not parts or parts[0] in ("comment", "obj_info"):
            continue
        if parts[0] == "end_header":
            break
        if parts[0] == "format":
            fmt = parts[1]
        elif parts[0] == "element":
            elements.append(_PlyElement(parts[1], int(parts[2])))
        elif parts[0] == "property":
            if not elements:
                raise ValueError(f"{path}: PLY property before any element")
            if parts[1] == "list":
                if parts[2] not in _PLY_TYPES or parts[3] not in _PLY_TYPES:
                    raise ValueError(f"{path}: unknown PLY list types {parts[2:4]}")
                elements[-1].props.append((parts[4], ("list", _PLY_TYPES[parts[2]], _PLY_TYPES[parts[3]])))
            else:
                if parts[1] not in _PLY_TYPES:
                    raise ValueError(f"{path}: unknown PLY property type {parts[1]!r}")
                elements[-1].props.append((parts[2], _PLY_TYPES[parts[1]]))
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise ValueError(f"{path}: unsupported PLY format {fmt!r}")
    return fmt, elements


def _triangulate(path: Path, polys: list[np.ndarray] | np.ndarray) -> np.ndarray:
    if isinstance(polys, np.ndarray):  # all polygons have the same size
        n = polys.shape[1]
        if n < 3:
            raise ValueError(f"{path}: faces with fewer than 3 vertices")
        return np.concatenate([polys[:, [0, i, i + 1]] for i in range(1, n - 1)], axis=0).astype(np.int64)
    tris = [p[[0, i, i + 1]] for p in polys for i in range(1, len(p) - 1)]
    return np.asarray(tris, dtype=np.int64).reshape(-1, 3)


def read_ply(path: str | Path) -> PlyMesh:
    """Load a PLY mesh/point cloud (ASCII, binary little- or big-endian) in the file's units.

    Reads vertex ``x y z`` (required), ``nx ny nz``, ``red green blue``, ``texture_u texture_v``
    and ``face vertex_indices`` (or ``vertex_index``). Other elements/properties are skipped.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: file not found")
    with open(path, "rb") as f:
        fmt, elements = _parse_ply_header(path, f)
        data = f.read()
    arrays: dict[str, dict[str, np.ndarray]] = {}
    faces_polys = None
    if fmt == "ascii":
        tokens = data.split()
        pos = 0
        for el in elements:
            has_list = any(isinstance(t, tuple) for _, t in el.props)
            if not has_list:
                n_props = len(el.props)
                chunk = tokens[pos: pos + el.count * n_props]
                if len(chunk) != el.count * n_props:
                    raise ValueError(f"{path}: truncated PLY ({el.name}: expected {el.count} rows)")
                vals = np.array(chunk, dtype=np.float64).reshape(el.count, n_props)
                pos += el.count * n_props
                arrays[el.name] = {name: vals[:, i] for i, (name, _) in enumerate(el.props)}
            else:
                rows_lists = []
                for _ in range(el.count):
                    for name, t in el.props:
                        if pos >= len(tokens):
                            raise ValueError(f"{path}: truncated PLY in element {el.name}")
                        if isinstance(t, tuple):
                            n = int(tokens[pos])
                            items = np.array(tokens[pos + 1: pos + 1 + n], dtype=np.int64)
                            if len(items) != n:
                                raise ValueError(f"{path}: truncated PLY in element {el.name}")
                            pos += 1 + n
                            if el.name == "face" and name in ("vertex_indices", "vertex_index"):
                                rows_lists.append(items)
                        else:
                            pos += 1
                if el.name == "face":
                    lens = {len(r) for r in rows_lists}
                    faces_polys = np.stack(rows_lists) if len(lens) == 1 else rows_lists
    else:
        end = "<" if fmt == "binary_little_endian" else ">"
        pos = 0
        for el in elements:
            has_list = any(isinstance(t, tuple) for _, t in el.props)
            if not has_list:
                dt = np.dtype([(name, end + t) for name, t in el.props])
                nbytes = dt.itemsize * el.count
                if pos + nbytes > len(data):
                    raise ValueError(f"{path}: truncated PLY ({el.name}: expected {el.count} rows)")
                rec = np.frombuffer(data, dtype=dt, count=el.count, offset=pos)
                pos += nbytes
                arrays[el.name] = {name: rec[name].astype(np.float64) for name, _ in el.props}
                continue
            # Fast path: one list property whose length is the same for every row (triangle meshes).
            if len(el.props) == 1 and el.count > 0:
                name, (_, cdt, idt) = el.props[0]
                cdt, idt = np.dtype(end + cdt), np.dtype(end + idt)
                n0 = int(np.frombuffer(data, dtype=cdt, count=1, offset=pos)[0])
                row = np.dtype([("n", cdt), ("v", idt, (n0,))])
                if pos + row.itemsize * el.count <= len(data):
                    rec = np.frombuffer(data, dtype=row, count=el.count, offset=pos)
                    if np.all(rec["n"] == n0):
                        pos += row.itemsize * el.count
                        if el.name == "face":
                            faces_polys = rec["v"].astype(np.int64)
                        continue
            polys = []
            for _ in range(el.count):
                for name, t in el.props:
                    if isinstance(t, tuple):
                        cdt, idt = np.dtype(end + t[1]), np.dtype(end + t[2])
                        n = int(np.frombuffer(data, dtype=cdt, count=1, offset=pos)[0])
                        pos += cdt.itemsize
                        items = np.frombuffer(data, dtype=idt, count=n, offset=pos).astype(np.int64)
                        pos += idt.itemsize * n
                        if el.name == "face" and name in ("vertex_indices", "vertex_index"):
                            polys.append(items)
                    else:
                        pos += np.dtype(t).itemsize
            if el.name == "face":
                faces_polys = polys
    v = arrays.get("vertex")
    if v is None or not all(k in v for k in ("x", "y", "z")):
        raise ValueError(f"{path}: PLY has no vertex element with x, y, z")
    pts = np.stack([v["x"], v["y"], v["z"]], axis=1)
    if not np.all(np.isfinite(pts)):
        raise ValueError(f"{path}: vertex positions contain non-finite values")
    normals = np.stack([v["nx"], v["ny"], v["nz"]], axis=1) if all(k in v for k in ("nx", "ny", "nz")) else None
    colors = None
    if all(k in v for k in ("red", "green", "blue")):
        colors = np.stack([v["red"], v["green"], v["blue"]], axis=1).clip(0, 255).astype(np.uint8)
    uv = np.stack([v["texture_u"], v["texture_v"]], axis=1) if all(k in v for k in ("texture_u", "texture_v")) else None
    faces = None
    if faces_polys is not None and len(faces_polys):
        faces = _triangulate(path, faces_polys)
        if faces.size and (faces.min() < 0 or faces.max() >= len(pts)):
            raise ValueError(f"{path}: face indices out of range [0, {len(pts)})")
    return PlyMesh(vertices=pts, faces=faces, normals=normals, colors=colors, texture_uv=uv)


# ---- writer -------------------------------------------------------------------------------------

def write_ply(path: str | Path, vertices: np.ndarray, faces: np.ndarray | None = None,
              colors: np.ndarray | None = None, normals: np.ndarray | None = None,
              comment: str | None = None, binary: bool = True) -> None:
    """Write a PLY atomically: float32 ``x y z`` [``nx ny nz``] [uchar ``red green blue``] and an
    ``element face`` of triangles (``list uchar int vertex_indices``; 0 faces for a point cloud).

    Args:
        path: output file.
        vertices: (N, 3) positions, written as float32 in the caller's units.
        faces: (F, 3) triangle indices or None.
        colors: (N, 3) uint8 RGB or None.
        normals: (N, 3) normals or None.
        comment: one ``comment`` header line (no newlines), or None.
        binary: binary little-endian (default) or ASCII.
    """
    v = np.asarray(vertices, dtype=np.float32).reshape(-1, 3)
    f = np.zeros((0, 3), np.int32) if faces is None else np.asarray(faces, dtype=np.int32).reshape(-1, 3)
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    header = ["ply", "format " + ("binary_little_endian" if binary else "ascii") + " 1.0"]
    if comment is not None:
        if "\n" in comment:
            raise ValueError(f"{path}: PLY comment must be one line")
        header.append(f"comment {comment}")
    header += [f"element vertex {len(v)}", "property float x", "property float y", "property float z"]
    if normals is not None:
        fields += [("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")]
        header += ["property float nx", "property float ny", "property float nz"]
    if colors is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
        header += ["property uchar red", "property uchar green", "property uchar blue"]
    header += [f"element face {len(f)}", "property list uchar int vertex_indices", "end_header"]
    vert = np.zeros(len(v), dtype=fields)
    vert["x"], vert["y"], vert["z"] = v[:, 0], v[:, 1], v[:, 2]
    if normals is not None:
        nn = np.asarray(normals, dtype=np.float32).reshape(-1, 3)
        vert["nx"], vert["ny"], vert["nz"] = nn[:, 0], nn[:, 1], nn[:, 2]
    if colors is not None:
        c = np.asarray(colors, dtype=np.uint8).reshape(-1, 3)
        vert["red"], vert["green"], vert["blue"] = c[:, 0], c[:, 1], c[:, 2]
    head = ("\n".join(header) + "\n").encode("ascii")
    if binary:
        face = np.zeros(len(f), dtype=[("n", "u1"), ("i", "<i4", (3,))])
        face["n"] = 3
        face["i"] = f
        data = head + vert.tobytes() + face.tobytes()
    else:
        # repr-exact float32 text ("%.9g" round-trips float32) so ASCII and binary files hold equal values.
        rows = [" ".join(("%d" if vert.dtype[k].kind == "u" else "%.9g") % vert[k][i] for k in vert.dtype.names)
                for i in range(len(vert))]
        rows += ["3 %d %d %d" % tuple(t) for t in f]
        data = head + ("\n".join(rows) + ("\n" if rows else "")).encode("ascii")
    atomic_write_bytes(path, data)
