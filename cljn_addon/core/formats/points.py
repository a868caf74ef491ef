"""Point-cloud files: PLY (ascii, binary little/big endian), PCPNet .xyz (+ .normals), .npy;
LAS/LAZ live in las.py and are dispatched from here.

Pure numpy; never imports bpy. Every reader returns a `PointCloud`; every writer replaces its
target atomically (a temporary file in the same folder, then `os.replace`), so an interrupted
run never leaves a half-written file behind.

Errors a user can fix raise `InputError` whose message starts with the file name.

Layouts written:
- .ply: binary little endian, vertex properties x y z (the input's float type), nx ny nz
  (float), every other property of the input in its order and type, then `cljn_outlier`
  (uchar, 1 = flagged) when outlier flags are given.
- .xyz: "x y z" per line, with the normals in a sibling .normals file ("nx ny nz" per line),
  as in the PCPNet data set. Other properties are not written.
- .npy: an (N, 6) array x y z nx ny nz in the positions' float type (float32 or float64).
"""
from __future__ import annotations

import os
import re
import tempfile
import warnings
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputError
from . import POINT_SUFFIXES

# PLY scalar type names (both spellings) -> numpy kind.
_PLY_TYPES = {
    "char": "i1", "int8": "i1",
    "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4",
    "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4",
    "double": "f8", "float64": "f8",
}
# numpy kind -> PLY name written.
_PLY_NAMES = {"i1": "char", "u1": "uchar", "i2": "short", "u2": "ushort", "i4": "int",
              "u4": "uint", "f4": "float", "f8": "double"}

_NORMAL_NAMES = (("nx", "ny", "nz"), ("normal_x", "normal_y", "normal_z"))
OUTLIER_PROPERTY = "cljn_outlier"


@dataclass
class PointCloud:
    """Points as read. `points` keeps the file's float type (float32 or float64) so that
    writing unchanged positions back reproduces them bit for bit."""

    points: np.ndarray                                   # (N, 3) float32 or float64
    normals: np.ndarray | None = None                    # (N, 3) or None
    extra: dict = field(default_factory=dict)            # name -> (N,) array, in file order
    faces: object = None                                 # PLY face element: (F, k) int64 or list
    comments: list = field(default_factory=list)         # PLY comments, kept on writing
    source: object = None                                # las.LasSource of a LAS/LAZ input
    origin: np.ndarray | None = None                     # points are relative to this (float64)

    def __len__(self):
        return len(self.points)

    def true_points(self) -> np.ndarray:
        """Positions in the file's own coordinates (points + origin)."""
        if self.origin is None:
            return self.points
        return np.asarray(self.points, np.float64) + np.asarray(self.origin, np.float64)


# --------------------------------------------------------------------------- helpers

def _looks_like_normals(cols: np.ndarray) -> bool:
    """Unlabelled columns are taken as normals when every row is a unit vector."""
    if cols.shape[1] != 3 or len(cols) == 0 or not np.isfinite(cols).all():
        return False
    return bool(np.all(np.abs(np.linalg.norm(cols, axis=1) - 1.0) < 1e-2))


# --------------------------------------------------------------------------- atomic writes

@contextmanager
def atomic_paths(*targets):
    """Yield temporary paths next to `targets`; on success each replaces its target.

    On error the temporaries are removed and the targets are left as they were.
    """
    temps = []
    try:
        for target in targets:
            target = Path(target)
            fd, tmp = tempfile.mkstemp(prefix=f".{target.stem}.", suffix=f".tmp{target.suffix}",
                                       dir=target.parent if str(target.parent) else ".")
            os.close(fd)
            temps.append(Path(tmp))
        yield temps
        for tmp, target in zip(temps, targets):
            try:
                os.chmod(tmp, 0o666 & ~_umask())
            except OSError:
                pass
            os.replace(tmp, target)
    finally:
        for tmp in temps:
            if tmp.exists():
                try:
                    tmp.unlink()
                except OSError:
                    pass


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


# --------------------------------------------------------------------------- PLY reading

@dataclass
class _Element:
    name: str
    count: int
    props: list            # (name, kind) for scalars, (name, (count_kind, item_kind)) for lists

    @property
    def has_lists(self) -> bool:
        return any(isinstance(k, tuple) for _, k in self.props)


def _parse_header(path, data: bytes):
    if not data.startswith(b"ply"):
        raise InputError(f"{path}: not a PLY file (it does not start with 'ply')")
    m = re.search(rb"end_header[ \t]*\r?\n", data)
    if m is None:
        raise InputError(f"{path}: PLY header has no end_header line (file truncated?)")
    header = data[:m.start()].decode("ascii", errors="replace").splitlines()
    fmt = None
    elements: list[_Element] = []
    comments = []
    for no, line in enumerate(header, start=1):
        toks = line.split()
        if not toks or toks[0] in ("ply", "obj_info"):
            continue
        key = toks[0]
        try:
            if key == "format":
                fmt = toks[1]
                if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
                    raise InputError(f"{path}: unknown PLY format {fmt!r}")
            elif key == "comment":
                comments.append(line.strip()[len("comment"):].strip())
            elif key == "element":
                elements.append(_Element(toks[1], int(toks[2]), []))
                if elements[-1].count < 0:
                    raise ValueError
            elif key == "property":
                if not elements:
                    raise InputError(f"{path}, header line {no}: property before any element")
                if toks[1] == "list":
                    kind = (_PLY_TYPES[toks[2]], _PLY_TYPES[toks[3]])
                    name = toks[4]
                else:
                    kind, name = _PLY_TYPES[toks[1]], toks[2]
                elements[-1].props.append((name, kind))
            else:
                raise InputError(f"{path}, header line {no}: unexpected PLY header line {line!r}")
        except (IndexError, ValueError, KeyError) as exc:
            if isinstance(exc, InputError):
                raise
            raise InputError(f"{path}, header line {no}: cannot read {line.strip()!r}") from None
    if fmt is None:
        raise InputError(f"{path}: PLY header has no format line")
    return fmt, elements, comments, m.end()


def _truncated(path, el, got):
    return InputError(f"{path}: truncated PLY: the header promises {el.count} {el.name} "
                      f"record(s) but the file holds {got}")


def _read_binary_element(path, el, data, pos, endian):
    """(dict name -> array or list of arrays, new position)."""
    if not el.has_lists:
        dtype = np.dtype([(n, endian + k) for n, k in el.props])
        need = el.count * dtype.itemsize
        if pos + need > len(data):
            got = (len(data) - pos) // dtype.itemsize if dtype.itemsize else 0
            raise _truncated(path, el, got)
        arr = np.frombuffer(data, dtype=dtype, count=el.count, offset=pos)
        return {n: arr[n].astype(arr[n].dtype.newbyteorder("=")) for n, _ in el.props}, pos + need
    # Fast path: every list has the length it has in the first record (triangle meshes).
    fields, p = [], pos
    try:
        for n, k in el.props:
            if isinstance(k, tuple):
                cnt = int(np.frombuffer(data, endian + k[0], 1, p)[0])
                if cnt == 0:
                    raise ValueError("empty list")
                fields += [(n + "#n", endian + k[0]), (n, endian + k[1], (cnt,))]
                p += np.dtype(k[0]).itemsize + cnt * np.dtype(k[1]).itemsize
            else:
                fields.append((n, endian + k))
                p += np.dtype(k).itemsize
        dtype = np.dtype(fields)
    except ValueError:
        dtype = None
    if el.count and dtype is not None and pos + el.count * dtype.itemsize <= len(data):
        arr = np.frombuffer(data, dtype=dtype, count=el.count, offset=pos)
        lists = [n for n, k in el.props if isinstance(k, tuple)]
        if all(np.all(arr[n + "#n"] == arr[n].shape[1]) for n in lists):
            out = {n: (arr[n].astype(np.int64) if n in lists
                       else arr[n].astype(arr[n].dtype.newbyteorder("="))) for n, _ in el.props}
            return out, pos + el.count * dtype.itemsize
    # General path: record by record.
    out = {n: [] for n, _ in el.props}
    for i in range(el.count):
        for n, k in el.props:
            try:
                if isinstance(k, tuple):
                    cnt = int(np.frombuffer(data, endian + k[0], 1, pos)[0])
                    pos += np.dtype(k[0]).itemsize
                    out[n].append(np.frombuffer(data, endian + k[1], cnt, pos).astype(np.int64))
                    pos += cnt * np.dtype(k[1]).itemsize
                else:
                    out[n].append(np.frombuffer(data, endian + k, 1, pos)[0])
                    pos += np.dtype(k).itemsize
            except ValueError:
                raise _truncated(path, el, i) from None
    for n, k in el.props:
        if not isinstance(k, tuple):
            out[n] = np.asarray(out[n], dtype=k)
    return out, pos


def _read_ascii_element(path, el, lines, start):
    """(dict, next line index). `lines` holds the non-blank body lines."""
    rows = lines[start:start + el.count]
    if len(rows) < el.count:
        raise _truncated(path, el, len(rows))
    if not el.has_lists:
        nprop = len(el.props)
        toks = b" ".join(rows).split()
        if len(toks) == el.count * nprop:
            try:
                table = np.array(toks, dtype=np.float64).reshape(el.count, nprop)
            except ValueError:
                table = None
            if table is not None:
                return ({n: _cast(table[:, j], k) for j, (n, k) in enumerate(el.props)},
                        start + el.count)
    out = {n: [] for n, _ in el.props}
    for i, row in enumerate(rows):
        toks = row.split()
        j = 0
        try:
            for n, k in el.props:
                if isinstance(k, tuple):
                    cnt = int(toks[j])
                    out[n].append(np.array([int(t) for t in toks[j + 1:j + 1 + cnt]], np.int64))
                    if len(out[n][-1]) != cnt:
                        raise IndexError
                    j += 1 + cnt
                else:
                    out[n].append(float(toks[j]))
                    j += 1
        except (IndexError, ValueError):
            raise InputError(f"{path}: {el.name} record {i} of the PLY body cannot be read: "
                             f"{row[:80].decode('ascii', 'replace')!r}") from None
    for n, k in el.props:
        if not isinstance(k, tuple):
            out[n] = _cast(np.asarray(out[n], np.float64), k)
    return out, start + el.count


def _cast(values: np.ndarray, kind: str) -> np.ndarray:
    if kind[0] == "f":
        return values.astype(kind)
    return np.rint(values).astype(kind)


def _as_faces(lists):
    """(F, k) int64 when every polygon has k corners, else a list of int64 arrays."""
    if isinstance(lists, np.ndarray):
        return lists
    if not lists:
        return np.zeros((0, 3), np.int64)
    sizes = {len(p) for p in lists}
    if len(sizes) == 1:
        return np.stack(lists).astype(np.int64)
    return lists


def read_ply(path) -> PointCloud:
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise InputError(f"{path}: cannot read the file ({exc.strerror or exc})") from None
    fmt, elements, comments, pos = _parse_header(path, data)
    names = [e.name for e in elements]
    if "vertex" not in names:
        raise InputError(f"{path}: the PLY file has no vertex element")
    # Elements are stored one after the other: read up to the last one needed (vertex, face).
    needed = {"vertex", "face"} & set(names)
    found = {}
    body, line = None, 0
    endian = "<" if fmt == "binary_little_endian" else ">"
    for el in elements:
        if needed <= set(found):
            break
        if fmt == "ascii":
            if body is None:
                body = [ln for ln in data[pos:].splitlines() if ln.strip()]
            found[el.name], line = _read_ascii_element(path, el, body, line)
        else:
            found[el.name], pos = _read_binary_element(path, el, data, pos, endian)
    vert = found["vertex"]
    vel = elements[names.index("vertex")]
    kinds = dict(vel.props)
    for axis in "xyz":
        if axis not in vert or isinstance(kinds[axis], tuple):
            raise InputError(f"{path}: the PLY vertex element has no '{axis}' coordinate")
    pdtype = np.result_type(*(vert[a].dtype for a in "xyz"))
    if pdtype.kind != "f":
        pdtype = np.dtype(np.float64)
    points = np.stack([vert[a] for a in "xyz"], axis=1).astype(pdtype)
    normals, used = None, {"x", "y", "z"}
    for trio in _NORMAL_NAMES:
        if all(n in vert and not isinstance(kinds[n], tuple) for n in trio):
            normals = np.stack([vert[n] for n in trio], axis=1)
            used.update(trio)
            break
    extra = {n: vert[n] for n, k in vel.props if n not in used and not isinstance(k, tuple)}
    faces = None
    if "face" in found:
        fel = elements[names.index("face")]
        lists = [n for n, k in fel.props if isinstance(k, tuple)]
        key = "vertex_indices" if "vertex_indices" in lists else ("vertex_index" if "vertex_index"
                                                                 in lists else None)
        if key is None and lists:
            key = lists[0]
        if key is not None:
            faces = _as_faces(found["face"][key])
    return PointCloud(points, normals, extra, faces, comments)


# --------------------------------------------------------------------------- PLY writing

def _ply_kind(arr: np.ndarray) -> str:
    dt = np.asarray(arr).dtype
    if dt == np.bool_:
        return "u1"
    key = dt.kind + str(dt.itemsize)
    if key in _PLY_NAMES:
        return key
    if dt.kind in "iu":                       # 64-bit integers: int/uint if they fit, else double
        a = np.asarray(arr)
        if a.size == 0 or (a.min() >= np.iinfo(np.int32).min and a.max() <= np.iinfo(np.int32).max):
            return "i4"
    return "f8"


def write_ply(path, cloud: PointCloud, outliers=None, fmt="binary_little_endian") -> list:
    """Write the vertex element (faces are not written). Returns [path]."""
    path = Path(path)
    n = len(cloud.points)
    points = cloud.true_points()
    pkind = "f8" if np.asarray(points).dtype == np.float64 else "f4"
    columns = [(a, pkind, points[:, i]) for i, a in enumerate("xyz")]
    if cloud.normals is not None:
        nkind = "f8" if np.asarray(cloud.normals).dtype == np.float64 else "f4"
        columns += [(a, nkind, cloud.normals[:, i]) for i, a in enumerate(("nx", "ny", "nz"))]
    for name, values in cloud.extra.items():
        if name == OUTLIER_PROPERTY and outliers is not None:
            continue
        values = np.asarray(values).reshape(-1)
        if len(values) != n:
            raise ValueError(f"property {name!r} has {len(values)} values for {n} points")
        columns.append((name, _ply_kind(values), values))
    if outliers is not None:
        columns.append((OUTLIER_PROPERTY, "u1", np.asarray(outliers).astype(np.uint8)))
    lines = ["ply", f"format {fmt} 1.0"]
    lines += [f"comment {c}" for c in cloud.comments if "\n" not in c and "\r" not in c]
    lines += [f"element vertex {n}"]
    lines += [f"property {_PLY_NAMES[k]} {name}" for name, k, _ in columns]
    lines.append("end_header")
    header = ("\n".join(lines) + "\n").encode("ascii")
    with atomic_paths(path) as (tmp,):
        with open(tmp, "wb") as fh:
            fh.write(header)
            if fmt == "ascii":
                fmts = [("%.17g" if k == "f8" else "%.9g") if k[0] == "f" else "%d"
                        for _, k, _ in columns]
                table = np.empty((n, len(columns)), dtype=object)
                for j, (_, k, v) in enumerate(columns):
                    table[:, j] = np.asarray(v).astype(k).tolist() if n else []
                for row in table:
                    fh.write((" ".join(f % x for f, x in zip(fmts, row)) + "\n").encode("ascii"))
            else:
                endian = "<" if fmt == "binary_little_endian" else ">"
                rec = np.empty(n, dtype=[(name, endian + k) for name, k, _ in columns])
                for name, k, v in columns:
                    rec[name] = v
                fh.write(rec.tobytes())
    return [path]


# --------------------------------------------------------------------------- XYZ (PCPNet)

def _load_table(path) -> np.ndarray:
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            table = np.loadtxt(path, dtype=np.float64, comments="#", ndmin=2)
    except OSError as exc:
        raise InputError(f"{path}: cannot read the file ({exc.strerror or exc})") from None
    except ValueError as exc:
        detail = str(exc).splitlines()[0] if str(exc) else "not a table of numbers"
        raise InputError(f"{path}: cannot read the numbers ({detail})") from None
    return table


def read_xyz(path) -> PointCloud:
    path = Path(path)
    table = _load_table(path)
    if table.size == 0:
        raise InputError(f"{path}: the point cloud is empty")
    if table.shape[1] < 3:
        raise InputError(f"{path}: expected at least 3 columns (x y z), found {table.shape[1]}")
    cloud = _from_columns(table)
    sibling = path.with_suffix(".normals")
    if sibling.exists():
        normals = _load_table(sibling)
        if normals.shape != (len(table), 3):
            raise InputError(f"{sibling}: expected {len(table)} rows of 'nx ny nz' to match "
                             f"{path.name}, found shape {normals.shape}")
        cloud.normals = normals
    return cloud


def _from_columns(table: np.ndarray) -> PointCloud:
    """x y z [nx ny nz] [more...] columns -> PointCloud; unlabelled extras are `colK`."""
    points = table[:, :3]
    normals, first_extra = None, 3
    if table.shape[1] >= 6 and _looks_like_normals(table[:, 3:6]):
        normals, first_extra = table[:, 3:6], 6
    extra = {f"col{j}": table[:, j] for j in range(first_extra, table.shape[1])}
    return PointCloud(np.ascontiguousarray(points), normals, extra)


def write_xyz(path, cloud: PointCloud, outliers=None) -> list:
    """PCPNet layout: path (x y z) and path.with_suffix('.normals'). Returns both paths."""
    path = Path(path)
    targets = [path]
    if cloud.normals is not None:
        targets.append(path.with_suffix(".normals"))
    points = cloud.true_points()
    pfmt = "%.17g" if np.asarray(points).dtype == np.float64 else "%.9g"
    with atomic_paths(*targets) as temps:
        np.savetxt(temps[0], points, fmt=pfmt)
        if cloud.normals is not None:
            nfmt = "%.17g" if np.asarray(cloud.normals).dtype == np.float64 else "%.9g"
            np.savetxt(temps[1], cloud.normals, fmt=nfmt)
    return targets


# --------------------------------------------------------------------------- NPY

def read_npy(path) -> PointCloud:
    path = Path(path)
    try:
        arr = np.load(path, allow_pickle=False)
    except OSError as exc:
        raise InputError(f"{path}: cannot read the file ({exc.strerror or exc})") from None
    except ValueError as exc:
        raise InputError(f"{path}: not a readable .npy array ({exc})") from None
    if not isinstance(arr, np.ndarray):
        raise InputError(f"{path}: expected a single array (.npy), not an archive")
    if arr.dtype.names:                                  # structured: fields like a PLY
        names = arr.dtype.names
        if not all(a in names for a in "xyz"):
            raise InputError(f"{path}: structured array without x, y, z fields")
        pdtype = np.result_type(*(arr[a].dtype for a in "xyz"))
        points = np.stack([arr[a] for a in "xyz"], axis=1).astype(
            pdtype if pdtype.kind == "f" else np.float64)
        normals, used = None, {"x", "y", "z"}
        for trio in _NORMAL_NAMES:
            if all(n in names for n in trio):
                normals = np.stack([arr[n] for n in trio], axis=1)
                used.update(trio)
                break
        extra = {n: np.asarray(arr[n]) for n in names if n not in used and arr[n].ndim == 1}
        return PointCloud(points.reshape(-1, 3), normals, extra)
    if arr.ndim != 2 or arr.shape[1] < 3:
        raise InputError(f"{path}: expected an (N, 3) or (N, 6) array, found shape {arr.shape}")
    if arr.dtype.kind not in "fiu":
        raise InputError(f"{path}: expected numbers, found dtype {arr.dtype}")
    if len(arr) == 0:
        raise InputError(f"{path}: the point cloud is empty")
    if arr.dtype.kind != "f" or arr.dtype.itemsize < 4:
        arr = arr.astype(np.float64)
    cloud = _from_columns(arr)
    return cloud


def write_npy(path, cloud: PointCloud, outliers=None) -> list:
    """(N, 6) x y z nx ny nz in the positions' float type ((N, 3) when there are no normals)."""
    path = Path(path)
    points = cloud.true_points()
    dtype = np.float64 if np.asarray(points).dtype == np.float64 else np.float32
    cols = [np.asarray(points, dtype)]
    if cloud.normals is not None:
        cols.append(np.asarray(cloud.normals, dtype))
    table = np.concatenate(cols, axis=1)
    with atomic_paths(path) as (tmp,):
        with open(tmp, "wb") as fh:
            np.save(fh, table, allow_pickle=False)
    return [path]


# --------------------------------------------------------------------------- dispatch

def _read_las(path, with_fields=True):
    from .las import read_las

    return read_las(path, with_fields=with_fields)


def _write_las(path, cloud, outliers=None, keep_las_scale=False, classify_outliers=False):
    from .las import write_las

    return write_las(path, cloud, outliers=outliers, keep_scale=keep_las_scale,
                     classify_outliers=classify_outliers)


_READERS = {".ply": read_ply, ".xyz": read_xyz, ".npy": read_npy, ".las": _read_las, ".laz": _read_las}
_WRITERS = {".ply": write_ply, ".xyz": write_xyz, ".npy": write_npy, ".las": _write_las, ".laz": _write_las}


def read_points(path, *, with_fields=True) -> PointCloud:
    """Read a .ply, .xyz, .npy, .las or .laz point cloud (format by extension). with_fields=False
    lets a LAS/LAZ reader keep only positions in memory (for writing back to LAS/LAZ)."""
    path = Path(path)
    reader = _READERS.get(path.suffix.lower())
    if reader is None:
        raise InputError(f"{path}: unsupported point-cloud format {path.suffix or '(none)'!r} "
                         f"(use {', '.join(POINT_SUFFIXES)})")
    if not path.exists():
        raise InputError(f"{path}: file not found")
    if path.is_dir():
        raise InputError(f"{path}: is a folder, not a file")
    if reader is _read_las:
        return reader(path, with_fields=with_fields)
    return reader(path)


def write_points(path, cloud: PointCloud, outliers=None, keep_las_scale=False,
                 classify_outliers=False) -> list:
    """Write by extension; returns the list of files written (the .xyz writer adds .normals).
    LAS/LAZ only: keep_las_scale keeps a LAS input's scale even where its grid rounds the
    cleaning away (default: a finer power of ten then; see las.finer_decades);
    classify_outliers gives flagged outliers the noise class (las.NOISE_CLASS)."""
    path = Path(path)
    writer = _WRITERS.get(path.suffix.lower())
    if writer is None:
        raise InputError(f"{path}: unsupported output format {path.suffix or '(none)'!r} "
                         f"(use {', '.join(POINT_SUFFIXES)})")
    if writer is _write_las:
        return writer(path, cloud, outliers=outliers, keep_las_scale=keep_las_scale,
                      classify_outliers=classify_outliers)
    return writer(path, cloud, outliers=outliers)
