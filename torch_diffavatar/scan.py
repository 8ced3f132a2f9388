"""Scans in: meshes and point clouds (PLY, OBJ, GLB via trimesh), with optional per-vertex garment labels
and colours, unit and up-axis conversion, sanity checks, and clean-up (floor, statistical outliers).

Every loaded scan is in our world frame: Y up, metres (see DESIGN.md). Scans in other units or axes are
converted by explicit options; `check_scan_frame` warns when the result still looks mis-scaled, lying
down or upside down.
"""

from __future__ import annotations

import itertools
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from torch_diffavatar.atomic_file import atomic_write
from torch_diffavatar.errors import ScanError

UNITS = {"m": 1.0, "cm": 0.01, "mm": 0.001}
# Rotations taking a scan's axes to ours (Y up). "z": Z up and facing −Y (Anny/Blender-like) -> Y up,
# facing +Z. "-y"/"-z" are the upside-down variants (a 180° turn about X from "y"/"z").
UP_AXES = {
    "y": np.eye(3),
    "-y": np.diag([1.0, -1.0, -1.0]),
    "z": np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]]),
    "-z": np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]),
}
LABEL_PROPERTIES = ("label", "labels", "garment", "segment", "segmentation", "class")
SCAN_SUFFIXES = (".ply", ".obj", ".glb", ".gltf", ".off", ".stl", ".xyz")
# The largest scan file read whole [bytes]: reading one (trimesh) holds about 4 times its size in memory.
# A PLY whose vertices come first is not read whole when it has more points than asked for: its vertices
# stream through in blocks of `READ_BLOCK` rows, and only a random subset stays (`load_scan`'s
# ``max_points``; a 50M-point scan read whole asked for 6.3 GiB).
MAX_SCAN_BYTES = 1024**3
READ_BLOCK = 1_000_000
_PLY_ORDERS = {"ascii": "ascii", "binary_little_endian": "<", "binary_big_endian": ">"}
_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip


class ScanWarning(UserWarning):
    """A scan that loads but looks wrong (units, up axis)."""


@dataclass
class Scan:
    """A scan in the world frame.

    Attributes:
        points: (N, 3) float64 vertex / point positions [m], Y up.
        faces: (F, 3) int64 triangles, or None for a point cloud.
        colors: (N, 3) uint8 RGB, or None.
        labels: (N,) int64 per-point garment labels (0 = not garment), or None.
        source: the file it came from.
        normals: (N, 3) float64 per-point unit normals (a PLY's ``nx ny nz``, e.g. towards the sensor of a
            depth capture), or None.
        warnings: messages from `check_scan_frame` (also issued as `ScanWarning`).
        file_point_count: the file's point count when only a random subset of it was read (`load_scan`'s
            ``max_points``), else None.
    """

    points: np.ndarray
    faces: np.ndarray | None = None
    colors: np.ndarray | None = None
    labels: np.ndarray | None = None
    source: str = ""
    warnings: list[str] = field(default_factory=list)
    normals: np.ndarray | None = None
    file_point_count: int | None = None

    @property
    def point_count(self) -> int:
        return len(self.points)

    def subset(self, keep: np.ndarray) -> Scan:
        """The scan restricted to the points where the (N,) bool ``keep`` is true (faces re-indexed)."""
        faces = None
        if self.faces is not None:
            new_index = np.cumsum(keep) - 1
            ok = keep[self.faces].all(1)
            faces = new_index[self.faces[ok]]
        return replace(
            self,
            points=self.points[keep],
            faces=faces,
            colors=None if self.colors is None else self.colors[keep],
            labels=None if self.labels is None else self.labels[keep],
            normals=None if self.normals is None else self.normals[keep],
        )


def _read_geometry(path: Path):
    import trimesh

    size = path.stat().st_size
    if size > MAX_SCAN_BYTES:
        raise ScanError(
            f"{path}: {size / 1e9:.3g} GB, more than the {MAX_SCAN_BYTES / 1e9:.3g} GB read whole here; "
            "save it as a PLY (read in part, --max-points N) or subsample it first"
        )
    try:
        geom = trimesh.load(str(path), process=False)
    except Exception as exc:  # trimesh raises many types for unreadable files
        raise ScanError(f"{path}: cannot read it as a mesh or point cloud ({exc})") from exc
    if isinstance(geom, trimesh.Scene):
        parts = [g for g in geom.dump() if hasattr(g, "vertices")]
        if not parts:
            raise ScanError(f"{path}: the scan has no points (the file holds no geometry)")
        meshes = [g for g in parts if isinstance(g, trimesh.Trimesh)]
        for mesh in meshes:  # before they are joined: concatenating textures would pack their images
            _texture_as_vertex_colours(mesh)
        geom = trimesh.util.concatenate(meshes) if len(meshes) == len(parts) else parts[0]
    elif isinstance(geom, trimesh.Trimesh):
        _texture_as_vertex_colours(geom)
    return geom


def _texture_as_vertex_colours(mesh) -> None:
    """A textured trimesh's colours read at its vertices, in place: photogrammetry meshes carry their
    colour as a texture (OBJ + MTL + image, GLB). A texture without an image gives one colour everywhere,
    which tells nothing: then the mesh is left without colours."""
    import trimesh

    if mesh.visual.kind != "texture":
        return
    colours = mesh.visual.to_color()  # the image at each vertex's UV
    rgb = np.asarray(colours.vertex_colors)
    uniform = rgb.ndim != 2 or bool((rgb == rgb[:1]).all())
    mesh.visual = trimesh.visual.ColorVisuals(mesh) if uniform else colours


def _colors_of(geom, count: int) -> np.ndarray | None:
    """(count, 3) uint8 per-point colours of a trimesh geometry: its vertex colours (a texture's, read at
    the vertices by `_read_geometry`) or a point cloud's colours; None without colour."""
    colors = None
    visual = getattr(geom, "visual", None)
    if visual is not None and getattr(visual, "kind", None) == "vertex":
        colors = np.asarray(visual.vertex_colors)
    elif getattr(geom, "colors", None) is not None and len(geom.colors) == count:
        colors = np.asarray(geom.colors)
    if colors is None or len(colors) != count:
        return None
    return colors[:, :3].astype(np.uint8)


def _vertex_table(geom):
    """A PLY's per-vertex properties as trimesh read them (a structured array or a dict), or None."""
    return (
        geom.metadata.get("_ply_raw", {}).get("vertex", {}).get("data") if hasattr(geom, "metadata") else None
    )


def _labels_of(raw, count: int, label_property: str | None, path: Path) -> np.ndarray | None:
    """(count,) int64 labels from the vertex table ``raw`` (`_vertex_table`), or None."""
    if raw is None:
        if label_property is not None:
            raise ScanError(f"{path}: no per-vertex property {label_property!r} (only PLY files carry them)")
        return None
    names = list(raw.keys()) if isinstance(raw, dict) else list(raw.dtype.names or ())
    wanted = (label_property,) if label_property else LABEL_PROPERTIES
    for name in wanted:
        if name in names:
            values = np.asarray(raw[name]).reshape(-1)
            if len(values) != count:
                raise ScanError(f"{path}: property {name!r} has {len(values)} values for {count} vertices")
            return values.astype(np.int64)
    if label_property is not None:
        raise ScanError(f"{path}: no vertex property {label_property!r}; found {names}")
    return None


def _normals_of(raw, count: int) -> np.ndarray | None:
    """(count, 3) float64 per-vertex ``nx ny nz`` of a PLY's vertex table ``raw``, or None."""
    names = (
        () if raw is None else (list(raw.keys()) if isinstance(raw, dict) else list(raw.dtype.names or ()))
    )
    if not {"nx", "ny", "nz"} <= set(names):
        return None
    normals = np.stack([np.asarray(raw[a], np.float64).reshape(-1) for a in ("nx", "ny", "nz")], 1)
    return normals if len(normals) == count and np.isfinite(normals).all() else None


def read_labels(path: str | Path, count: int) -> np.ndarray:
    """Per-point labels from a side file: ``.npy`` or text with one integer per line. -> (count,) int64."""
    path = Path(path)
    if not path.exists():
        raise ScanError(f"{path}: label file not found")
    try:
        values = np.load(path) if path.suffix == ".npy" else np.loadtxt(path, dtype=np.int64, ndmin=1)
    except Exception as exc:
        raise ScanError(f"{path}: cannot read labels ({exc})") from exc
    values = np.asarray(values).reshape(-1)
    if len(values) != count:
        raise ScanError(f"{path}: {len(values)} labels for a scan of {count} points")
    return values.astype(np.int64)


@dataclass(frozen=True)
class _PlyVertices:
    """Where a PLY's vertex rows lie: ``count`` rows of ``fields`` ((name, numpy type code) pairs) from byte
    ``start``, as text (``order`` "ascii") or binary (``order`` "<" or ">")."""

    order: str
    count: int
    fields: tuple[tuple[str, str], ...]
    start: int

    @property
    def dtype(self) -> np.dtype:
        order = "<" if self.order == "ascii" else self.order
        return np.dtype([(name, order + t) for name, t in self.fields])


def _ply_vertices(path: Path) -> _PlyVertices | None:
    """The vertex rows of a PLY whose first element is its vertices, each a fixed set of scalar properties
    (what `_sample_ply` streams); None for any other file (read whole, `_read_geometry`)."""
    elements, order = [], None
    with open(path, "rb") as f:
        if f.readline().strip() != b"ply":
            return None
        for _ in range(10_000):  # a header is a few lines; a file that never ends it is no PLY we stream
            words = f.readline().decode("ascii", "replace").split()
            try:
                if words[:1] == ["format"]:
                    order = _PLY_ORDERS[words[1]]
                elif words[:1] == ["element"]:
                    elements.append((words[1], int(words[2]), []))
                elif words[:1] == ["property"] and elements:
                    elements[-1][2].append(tuple(words[1:]))
                elif words[:1] == ["end_header"]:
                    break
            except (IndexError, KeyError, ValueError):
                return None
        else:
            return None
        start = f.tell()
    if order is None or not elements or elements[0][0] != "vertex":
        return None
    _, count, props = elements[0]
    if any(len(p) != 2 or p[0] not in _PLY_TYPES for p in props):  # a list property: rows vary in size
        return None
    return _PlyVertices(order, count, tuple((name, _PLY_TYPES[t]) for t, name in props), start)


def _ply_rows(f, ply: _PlyVertices, count: int, keep: np.ndarray, path: Path) -> np.ndarray:
    """The rows where the (count,) bool ``keep`` is true among the next ``count`` vertex rows of the PLY
    open as ``f``: a structured array of ``ply.dtype``."""
    dtype = ply.dtype
    if ply.order != "ascii":
        data = f.read(count * dtype.itemsize)
        if len(data) < count * dtype.itemsize:
            raise ScanError(f"{path}: the header promises {ply.count:,} points; the file ends before them")
        return np.frombuffer(data, dtype)[keep]
    lines = list(itertools.islice(f, count))
    if len(lines) < count:
        raise ScanError(f"{path}: the header promises {ply.count:,} points; the file ends before them")
    rows = np.empty(int(keep.sum()), dtype)
    try:  # only the rows kept are parsed
        table = np.loadtxt([lines[k].decode("ascii") for k in np.flatnonzero(keep)], ndmin=2)
        for column, name in enumerate(dtype.names):
            rows[name] = table[:, column]
    except (ValueError, IndexError, UnicodeDecodeError) as exc:
        raise ScanError(f"{path}: cannot read its vertex rows ({exc})") from exc
    return rows


def _sample_ply(path: Path, ply: _PlyVertices, max_points: int) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """A seeded random ``max_points`` of the vertex rows ``ply`` (`_ply_vertices`) of the file ``path``,
    read in one pass in blocks of `READ_BLOCK` rows: (name -> (max_points,) column, (max_points,) int64
    row numbers), in file order."""
    rng = np.random.default_rng(0)
    # each row kept with a probability a little above the share asked (6 sigma), then the surplus dropped
    share = min(1.0, (max_points + 6 * max_points**0.5 + 10) / ply.count)
    rows, index = [], []
    with open(path, "rb") as f:
        f.seek(ply.start)
        for first in range(0, ply.count, READ_BLOCK):
            count = min(READ_BLOCK, ply.count - first)
            keep = rng.random(count) < share
            rows.append(_ply_rows(f, ply, count, keep, path))
            index.append(first + np.flatnonzero(keep))
    rows, index = np.concatenate(rows), np.concatenate(index)
    if len(rows) > max_points:
        chosen = np.sort(rng.choice(len(rows), max_points, replace=False))
        rows, index = rows[chosen], index[chosen]
    return {name: rows[name] for name in rows.dtype.names}, index


def _read_points(path: Path, max_points: int | None):
    """The file's points and what comes with them: (points (N, 3) float64 in the file's frame, faces or
    None, colours (N, 3) uint8 or None, the PLY vertex table or None, and for a sample: (its row numbers,
    the file's point count), else None).
    A PLY of more than ``max_points`` points is sampled as it streams (`_sample_ply`), any other file read
    whole (`_read_geometry`)."""
    ply = None if max_points is None else _ply_vertices(path)
    if ply is not None and ply.count > max_points:
        columns, index = _sample_ply(path, ply, max_points)
        if not {"x", "y", "z"} <= set(columns):
            raise ScanError(f"{path}: its vertices have no x, y, z")
        points = np.stack([columns[a] for a in "xyz"], 1).astype(np.float64)
        rgb = [columns.get(c) for c in ("red", "green", "blue")]
        colors = None if any(c is None for c in rgb) else np.stack(rgb, 1).astype(np.uint8)
        return points, None, colors, columns, (index, ply.count)
    geom = _read_geometry(path)
    points = np.asarray(getattr(geom, "vertices", np.zeros((0, 3))), dtype=np.float64)
    faces = np.asarray(geom.faces, dtype=np.int64) if hasattr(geom, "faces") else None
    colors = _colors_of(geom, len(points)) if points.ndim == 2 else None
    return points, None if faces is None or len(faces) == 0 else faces, colors, _vertex_table(geom), None


def load_scan(
    path: str | Path,
    *,
    units: str = "m",
    up: str = "y",
    labels: str | Path | None = None,
    label_property: str | None = None,
    require_faces: bool = False,
    check: bool = True,
    max_points: int | None = None,
) -> Scan:
    """Load a scan mesh or point cloud into the world frame.

    Args:
        path: a PLY, OBJ, GLB/GLTF (or any format trimesh reads) file.
        units: the file's length unit, one of ``UNITS`` ("m", "cm", "mm").
        up: the file's up axis, one of ``UP_AXES`` ("y", "-y", "z", "-z").
        labels: optional side file of per-point garment labels (see `read_labels`).
        label_property: name of a PLY vertex property holding labels; by default the first of
            ``LABEL_PROPERTIES`` present is used, if any.
        require_faces: raise if the file has no triangles (a point cloud).
        check: run `check_scan_frame` and issue `ScanWarning`s.
        max_points: read a seeded random subset of this many points from a PLY that has more (streamed:
            memory for the subset only; no faces), with ``file_point_count`` set; None: read all.

    Returns:
        a `Scan`.

    Raises:
        ScanError: empty or unreadable file, no points, NaN/inf coordinates, missing faces when required,
            bad labels. ValueError for an unknown ``units``/``up``.
    """
    if units not in UNITS:
        raise ScanError(f"unknown units {units!r}; use one of {sorted(UNITS)}")
    if up not in UP_AXES:
        raise ScanError(f"unknown up axis {up!r}; use one of {sorted(UP_AXES)}")
    path = Path(path)
    if not path.exists():
        raise ScanError(f"{path}: file not found")
    if path.stat().st_size == 0:
        raise ScanError(f"{path}: the file is empty")
    points, faces, colors, raw, sampled = _read_points(path, max_points)
    if points.ndim != 2 or points.shape[0] == 0:
        raise ScanError(f"{path}: the scan has no points")
    if not np.isfinite(points).all():
        bad = int((~np.isfinite(points)).any(1).sum())
        raise ScanError(f"{path}: {bad} of {len(points)} points have NaN or infinite coordinates")
    if require_faces and faces is None:
        raise ScanError(f"{path}: the file has no faces (a point cloud), but a triangle mesh is needed here")
    scan = Scan(
        points=points @ UP_AXES[up].T * UNITS[units],
        faces=faces,
        colors=colors,
        labels=_labels_of(raw, len(points), label_property, path),
        source=str(path),
        file_point_count=None if sampled is None else sampled[1],
    )
    normals = _normals_of(raw, len(points))
    if normals is not None:
        scan.normals = normals @ UP_AXES[up].T
    if labels is not None:
        scan.labels = read_labels(labels, scan.file_point_count or len(points))
        scan.labels = scan.labels if sampled is None else scan.labels[sampled[0]]
    if check:
        scan.warnings = check_scan_frame(scan.points)
        for message in scan.warnings:
            warnings.warn(f"{path}: {message}", ScanWarning, stacklevel=2)
    return scan


def _slab_spread(points: np.ndarray, lo: float, hi: float) -> float:
    """RMS horizontal (x, z) distance to the slab centroid of points with lo <= y < hi [m]."""
    sel = points[(points[:, 1] >= lo) & (points[:, 1] < hi)][:, [0, 2]]
    if len(sel) < 10:
        return float("nan")
    return float(np.sqrt(((sel - sel.mean(0)) ** 2).sum(1).mean()))


def check_scan_frame(points: np.ndarray) -> list[str]:
    """Heuristic checks that a scan of a standing person is in metres, Y up and upright.

    - height (Y extent) outside [0.5, 2.5] m: probably wrong units;
    - a horizontal extent larger than 1.3 × the height: probably the wrong up axis;
    - the slab at 88–98 % of the height (the head) more than 1.25× as wide as the slab at 5–20 % (the
      lower legs): the person is probably upside down. On Anny bodies, bare or under a dress or pants,
      the head slab's spread is 0.07–0.08 m and the lower-leg slab's 0.17–0.22 m.

    Args:
        points: (N, 3) [m] in the world frame.

    Returns:
        a list of human-readable warnings (empty when all looks fine).
    """
    out = []
    lo = np.quantile(points, 0.001, axis=0)
    hi = np.quantile(points, 0.999, axis=0)
    extent = hi - lo
    height = extent[1]
    if height > 2.5:
        guess = "mm" if height > 250 else "cm" if height > 25 else "a smaller unit"
        out.append(f"the scan is {height:.3g} m tall; is it in {guess}? (pass --units)")
    elif height < 0.5:
        out.append(
            f"the scan is only {height:.3g} m tall; wrong --units, or --up (lying along another axis)?"
        )
    if max(extent[0], extent[2]) > 1.3 * height:
        out.append(
            f"the scan is wider ({max(extent[0], extent[2]):.3g}) than tall ({height:.3g}); wrong --up axis?"
        )
    elif height > 0:
        low = _slab_spread(points, lo[1] + 0.05 * height, lo[1] + 0.2 * height)
        top = _slab_spread(points, lo[1] + 0.88 * height, lo[1] + 0.98 * height)
        if np.isfinite(low) and np.isfinite(top) and top > 1.25 * low:
            out.append("the scan looks upside down (narrow at the bottom, wide at the top); try --up -y")
    return out


def remove_floor(scan: Scan, *, tolerance: float = 0.015, probe: float = 0.03) -> tuple[Scan, int]:
    """Remove a horizontal floor plane under the person, if there is one.

    A floor is detected when the points in the lowest ``probe`` [m] spread horizontally over more than
    1.5× the spread of the body just above (10–50 cm up). Its level is the median height of those lowest
    points; points less than ``tolerance`` [m] above it are removed.

    Returns:
        (the scan without the floor, number of points removed).
    """
    y = scan.points[:, 1]
    y0 = float(np.quantile(y, 0.0005))
    bottom = y < y0 + probe
    body = _slab_spread(scan.points, y0 + 0.1, y0 + 0.5)
    floor = _slab_spread(scan.points, y0 - 1e-9, y0 + probe)
    if not (np.isfinite(body) and np.isfinite(floor)) or floor < 1.5 * body:
        return scan, 0
    level = float(np.median(y[bottom]))
    keep = y > level + tolerance
    return scan.subset(keep), int((~keep).sum())


def remove_outliers(scan: Scan, *, neighbors: int = 16, std_ratio: float = 3.0) -> tuple[Scan, int]:
    """Statistical outlier removal: drop points whose mean distance to their ``neighbors`` nearest points
    exceeds the mean of that quantity by ``std_ratio`` standard deviations.

    Returns:
        (the cleaned scan, number of points removed).
    """
    if scan.point_count <= neighbors:
        return scan, 0
    dist, _ = cKDTree(scan.points).query(scan.points, k=neighbors + 1)
    mean = dist[:, 1:].mean(1)
    keep = mean <= mean.mean() + std_ratio * mean.std()
    return scan.subset(keep), int((~keep).sum())


def save_ply(
    path: str | Path,
    points: np.ndarray,
    *,
    colors: np.ndarray | None = None,
    faces: np.ndarray | None = None,
    int_properties: dict[str, np.ndarray] | None = None,
    normals: np.ndarray | None = None,
    binary: bool = False,
) -> None:
    """Write an ASCII PLY with optional colours, faces and integer vertex properties (e.g. labels).

    Args:
        points: (N, 3) [m]; colors: (N, 3) uint8; faces: (F, 3) int; int_properties: name -> (N,) ints.
        normals: (N, 3) unit normals (``nx ny nz``, binary files only).
        binary: write binary little-endian PLY (float32 points; `save_point_cloud_ply`) instead: ASCII
            takes seconds per 100k points.
    """
    if binary:
        if faces is not None:
            raise ValueError("save_ply: binary=True writes point clouds only (no faces)")
        save_point_cloud_ply(path, points, colors=colors, normals=normals, int_properties=int_properties)
        return
    if normals is not None:
        raise ValueError("save_ply: normals are written in binary files only (pass binary=True)")
    points = np.asarray(points, dtype=np.float64)
    props = dict(int_properties or {})
    header = ["ply", "format ascii 1.0", f"element vertex {len(points)}"]
    header += [f"property double {a}" for a in "xyz"]
    if colors is not None:
        header += [f"property uchar {c}" for c in ("red", "green", "blue")]
    header += [f"property int {name}" for name in props]
    if faces is not None:
        header += [f"element face {len(faces)}", "property list uchar int vertex_indices"]
    header.append("end_header")
    cols = [points]
    if colors is not None:
        cols.append(np.asarray(colors)[:, :3].astype(np.int64))
    cols += [np.asarray(v).reshape(-1, 1).astype(np.int64) for v in props.values()]
    with atomic_write(path, "w") as f:
        f.write("\n".join(header) + "\n")
        for row in zip(*cols):
            f.write(" ".join(np.format_float_positional(x, 7, trim="-") for x in row[0]))
            for extra in row[1:]:
                f.write(" " + " ".join(str(int(x)) for x in extra))
            f.write("\n")
        if faces is not None:
            for tri in np.asarray(faces, dtype=np.int64):
                f.write(f"3 {tri[0]} {tri[1]} {tri[2]}\n")


def save_point_cloud_ply(
    path: str | Path,
    points: np.ndarray,
    *,
    colors: np.ndarray | None = None,
    normals: np.ndarray | None = None,
    int_properties: dict[str, np.ndarray] | None = None,
) -> None:
    """Write a binary little-endian PLY point cloud: ``x y z`` float32, then optional ``nx ny nz`` float32,
    ``red green blue`` uchar and int32 properties (e.g. ``label``); `load_scan` reads it back.

    Args:
        points: (N, 3); normals: (N, 3); colors: (N, 3) uint8; int_properties: name -> (N,) ints.
    """
    points = np.asarray(points)
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    columns = {"x": points[:, 0], "y": points[:, 1], "z": points[:, 2]}
    if normals is not None:
        fields += [("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")]
        columns.update(zip(("nx", "ny", "nz"), np.asarray(normals).T))
    if colors is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
        columns.update(zip(("red", "green", "blue"), np.asarray(colors)[:, :3].T))
    for name, values in (int_properties or {}).items():
        fields.append((name, "<i4"))
        columns[name] = np.asarray(values).reshape(-1)
    record = np.empty(len(points), dtype=fields)
    for name, values in columns.items():
        record[name] = values
    ply_types = {"<f4": "float", "u1": "uchar", "<i4": "int"}
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {len(points)}"]
    header += [f"property {ply_types[t]} {name}" for name, t in fields]
    header.append("end_header")
    with atomic_write(path) as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        f.write(record.tobytes())
