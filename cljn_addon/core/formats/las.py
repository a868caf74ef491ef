"""LAS/LAZ point clouds through laspy (LAZ with the lazrs backend); never imports bpy.

Reading keeps a `LasSource` on the returned `PointCloud`: the input's header (version, point
format, scale, offset, VLRs incl. the CRS, EVLRs) and where its point records are. Writing a
cloud that has one streams the records again, chunk by chunk, and changes only:
- X, Y, Z: the output positions at the file's offset and scale, or a scale a power of ten finer
  where the file's grid would round the cleaning away (`finer_decades`); positions that did not
  move (outliers, `normals`) come back to the same coordinates (the same integers at the file's
  own scale, times 10^k at a finer one);
- the extra-bytes dimensions NORMAL_DIMS (float32) and OUTLIER_DIM (uint8, 1 = flagged), added
  after the input's own dimensions (overwritten when the input already has them);
- on request (`classify_outliers`), the classification of flagged outliers: NOISE_CLASS.
A COPC file's octree index (its "copc" VLR and EVLR) is left out: the rewritten chunks no
longer match it, and the rest is a plain LAZ 1.4.
Every other byte of every record is copied, so intensity, returns, classification, RGB, GPS
time and existing extra bytes come back exactly, in their order. Neither the records nor the
fields are ever held for the whole file at once: positions are (N, 3) float64 in memory, the
rest moves CHUNK_POINTS at a time.

A cloud without a LAS source (from .ply/.xyz/.npy) is written as LAS 1.4 point format 6 (7 with
red/green/blue), with a scale of 1e-8 of its extent; its other numeric properties go to the
standard dimension of the same name or to extra bytes.
"""
from __future__ import annotations

import copy
import io
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError

LAS_SUFFIXES = (".las", ".laz")
NORMAL_DIMS = ("NormalX", "NormalY", "NormalZ")   # PDAL's names; float32 extra bytes
OUTLIER_DIM = "cljn_outlier"                       # uint8 extra bytes, 1 = flagged outlier
CHUNK_POINTS = 1_000_000
NOISE_CLASS = 7                # ASPRS "low point (noise)": what PDAL's filters.outlier sets
MAX_FINER_DECADES = 3          # write at most 1000x finer than the input's scale
MOVE_PER_STEP = 2.0            # grid step <= half the median move: rounding ~13% of a move
_INT32 = np.iinfo(np.int32)


def laspy_module():
    """laspy, or an InputError that says how to get it."""
    try:
        import laspy
    except ImportError:
        raise InputError(_MISSING) from None
    return laspy


_MISSING = ("LAS/LAZ files need the laspy and lazrs packages (in Blender: Install Dependencies in "
            "the extension's preferences; elsewhere: pip install laspy lazrs)")


def _need_laz_backend(path):
    laspy = laspy_module()
    if Path(path).suffix.lower() == ".laz" and not laspy.LazBackend.detect_available():
        raise InputError(f"{path}: LAZ (compressed) files need the lazrs package; {_MISSING}")


@dataclass
class LasSource:
    """Where a cloud's LAS records come from: the input file (streamed again on writing) or,
    for a Blender object, its records held in memory ((N, record size) uint8)."""

    header: object                       # laspy.LasHeader of the input, EVLRs included
    path: Path | None = None
    records: np.ndarray | None = None

    @property
    def record_size(self) -> int:
        return self.header.point_format.size


def _unreadable(path, exc) -> InputError:
    detail = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    return InputError(f"{path}: not a readable LAS/LAZ file ({detail})")


def _open_reader(path):
    laspy = laspy_module()
    _need_laz_backend(path)
    try:
        return laspy.open(str(path))
    except OSError as exc:
        raise InputError(f"{path}: cannot read the file ({exc.strerror or exc})") from None
    except Exception as exc:                                    # noqa: BLE001 laspy/lazrs errors
        raise _unreadable(path, exc) from None


def _chunks(path, reader):
    """Each chunk of records as (ScaleAwarePointRecord, (m, size) uint8 view); errors name the file."""
    expected, seen = reader.header.point_count, 0
    try:
        for chunk in reader.chunk_iterator(CHUNK_POINTS):
            if len(chunk) == 0:
                break
            seen += len(chunk)
            yield chunk, chunk.array.view(np.uint8).reshape(len(chunk), -1)
    except InputError:
        raise
    except Exception as exc:                                    # noqa: BLE001 truncated/corrupt data
        raise _unreadable(path, exc) from None
    if seen != expected:
        raise InputError(f"{path}: the file is truncated (header says {expected} points, "
                         f"found {seen})")


def record_ints(record) -> np.ndarray:
    """(m, 3) int64 X, Y, Z of a laspy record."""
    return np.stack([np.asarray(record.array[a], np.int64) for a in "XYZ"], axis=1)


def grid_origin(header, ints_min, ints_max):
    """(origin integers, origin in true coordinates) at the middle of the integer box."""
    mid = (np.asarray(ints_min, np.int64) + np.asarray(ints_max, np.int64)) // 2
    return mid, mid * np.asarray(header.scales) + np.asarray(header.offsets)


def local_positions(ints, mid, header) -> np.ndarray:
    """(m, 3) float64 positions relative to the grid origin `mid`, computed from the integers:
    the same for a file and the same file shifted by any offset."""
    return (ints - mid) * np.asarray(header.scales)


def mid_of(origin, header):
    """The integers of `origin` when it lies on the file's grid (else None)."""
    if origin is None:
        return None
    m = (np.asarray(origin, np.float64) - np.asarray(header.offsets)) / np.asarray(header.scales)
    r = np.round(m)
    return r.astype(np.int64) if np.all(np.abs(m - r) < 1e-6) else None


def read_las(path, with_fields=True):
    """A PointCloud of the file's positions (float64) relative to `origin`, the middle of its
    integer box (so results do not depend on how far from 0 the file lies; true coordinates:
    `cloud.true_points()`). with_fields: every dimension but X, Y, Z in `extra` (for writing
    another format); without, only positions are kept in memory (writing back to LAS streams
    the rest from the file). NormalX/Y/Z become `normals`."""
    from .points import PointCloud

    path = Path(path)
    with _open_reader(path) as reader:
        header = reader.header
        n = int(header.point_count)
        if n == 0:
            raise InputError(f"{path}: the file holds no points")
        names = [d for d in header.point_format.dimension_names if d not in ("X", "Y", "Z")]
        ints = np.empty((n, 3), np.int32)
        normals = np.empty((n, 3), np.float32) if all(d in names for d in NORMAL_DIMS) else None
        extra = {d: [] for d in names} if with_fields else {}
        start = 0
        for chunk, _raw in _chunks(path, reader):
            stop = start + len(chunk)
            ints[start:stop] = record_ints(chunk)
            if normals is not None:
                normals[start:stop] = np.stack([np.asarray(chunk[d]) for d in NORMAL_DIMS], axis=1)
            for d in extra:
                extra[d].append(np.array(chunk[d]))
            start = stop
        try:
            if header.evlrs is None and header.number_of_evlrs:
                reader.read_evlrs()
        except Exception as exc:                                # noqa: BLE001
            raise _unreadable(path, exc) from None
        header = copy.deepcopy(reader.header)
    extra = {d: np.concatenate(v) for d, v in extra.items()
             if d not in NORMAL_DIMS and d != OUTLIER_DIM and v and v[0].ndim == 1}
    mid, origin = grid_origin(header, ints.min(axis=0), ints.max(axis=0))
    points = local_positions(ints, mid, header)
    del ints
    return PointCloud(points, normals, extra, source=LasSource(header, path=path), origin=origin)


# --------------------------------------------------------------------------- writing

def _is_copc(vlr) -> bool:
    return str(getattr(vlr, "user_id", "")).rstrip("\x00") == "copc"


def _without_copc(header):
    """A copy of header less a COPC index: its info VLR and hierarchy EVLR locate octree chunks
    by byte offset, which rewritten points no longer have (and laspy writes no COPC)."""
    laspy = laspy_module()
    out = copy.deepcopy(header)
    out.vlrs = laspy.vlrs.vlrlist.VLRList([v for v in out.vlrs if not _is_copc(v)])
    if out.evlrs:
        out.evlrs = laspy.vlrs.vlrlist.VLRList([v for v in out.evlrs if not _is_copc(v)])
    return out


def _output_header(header, with_normals, with_outliers):
    """The input's header (less a COPC index) with the normal and outlier extra bytes added
    when missing."""
    laspy = laspy_module()
    out = _without_copc(header)
    have = set(out.point_format.dimension_names)
    wanted = [laspy.ExtraBytesParams(name=d, type=np.float32, description="CLJN Denoise unit normal")
              for d in NORMAL_DIMS if with_normals]
    if with_outliers:
        wanted.append(laspy.ExtraBytesParams(name=OUTLIER_DIM, type=np.uint8,
                                             description="CLJN Denoise outlier flag"))
    missing = [p for p in wanted if p.name not in have]
    if missing:
        out.add_extra_dims(missing)
    return out


def quantise(path, positions, header, origin=None, mid=None) -> np.ndarray:
    """(m, 3) int32 record coordinates of positions (relative to `origin`, default: true
    coordinates) at the header's scale and offset; InputError (naming path) when a position
    does not fit the file's integer range. On the file's grid (`mid`: the integers of origin,
    default: found from the header) the integers come from the relative positions alone
    (exact, whatever the offset)."""
    mid = mid_of(origin, header) if mid is None else mid
    if mid is not None:
        scaled = np.round(positions / np.asarray(header.scales)) + mid
    else:
        true = positions if origin is None else positions + np.asarray(origin, np.float64)
        scaled = np.round((true - np.asarray(header.offsets)) / np.asarray(header.scales))
    bad = ~((scaled >= _INT32.min) & (scaled <= _INT32.max)).all(axis=1)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        where = scaled[i] * np.asarray(header.scales) + np.asarray(header.offsets)
        raise InputError(f"{path}: {int(bad.sum())} position(s) cannot be stored at the file's scale "
                         f"{tuple(header.scales)} and offset {tuple(header.offsets)} "
                         f"(first: point {i} at {tuple(np.round(where, 6))}); "
                         "write another format or a LAS with a coarser scale")
    return scaled.astype(np.int32)


def _fill(path, record, raw, positions, origin, normals, outliers, header, mid, classify):
    """The output record: the input bytes, then new X/Y/Z, normals and outlier flags (and with
    classify, the outliers' class)."""
    buf = record.array.view(np.uint8).reshape(len(record), -1)
    buf[:, :raw.shape[1]] = raw
    ints = quantise(path, positions, header, origin, mid)
    for k, axis in enumerate("XYZ"):
        record.array[axis] = ints[:, k]
    if normals is not None:
        for k, d in enumerate(NORMAL_DIMS):
            record[d] = normals[:, k].astype(np.float32)
    if outliers is not None:
        record[OUTLIER_DIM] = np.asarray(outliers, np.uint8)
        if classify:
            classes = np.array(record["classification"])
            classes[np.asarray(outliers, bool)] = NOISE_CLASS
            record["classification"] = classes


def _write_records(path, tmp, header, source_records, cloud, outliers, mid, classify):
    """Stream (raw chunk) pairs from source_records into a LAS/LAZ file at tmp."""
    laspy = laspy_module()
    compress = Path(path).suffix.lower() == ".laz"
    normals = None if cloud.normals is None else np.asarray(cloud.normals, np.float32)
    start = 0
    with open(tmp, "wb") as fh:
        with laspy.LasWriter(fh, header, do_compress=compress, closefd=False) as writer:
            for raw in source_records:
                stop = start + len(raw)
                record = laspy.ScaleAwarePointRecord.zeros(len(raw), header=writer.header)
                _fill(path, record, raw, cloud.points[start:stop], cloud.origin,
                      None if normals is None else normals[start:stop],
                      None if outliers is None else outliers[start:stop], header, mid, classify)
                writer.write_points(record)
                start = stop
            if header.evlrs and header.version.minor >= 4:
                writer.write_evlrs(header.evlrs)
    if start != len(cloud.points):
        raise InputError(f"{path}: the source has {start} points but the result has "
                         f"{len(cloud.points)}")


def load_records(source: LasSource) -> np.ndarray:
    """All of a source's records as one (N, record size) uint8 array."""
    return np.concatenate(list(_source_records(source)))


def record_view(records: np.ndarray, header):
    """A laspy record over (N, record size) uint8 bytes (field access by name; no copy)."""
    laspy = laspy_module()
    fmt = header.point_format
    array = np.ascontiguousarray(records).reshape(-1).view(fmt.dtype())
    return laspy.ScaleAwarePointRecord(array, fmt, header.scales, header.offsets)


def _source_records(source: LasSource):
    if source.records is not None:
        for start in range(0, len(source.records), CHUNK_POINTS):
            yield source.records[start:start + CHUNK_POINTS]
        return
    if source.path is None or not Path(source.path).exists():
        raise InputError(f"{source.path}: the input LAS/LAZ file is gone; cannot copy its fields")
    with _open_reader(source.path) as reader:
        for _chunk, raw in _chunks(source.path, reader):
            yield raw


def _input_positions(raw, header, origin, mid) -> np.ndarray:
    """(m, 3) float64 positions of raw records in the frame of a cloud with this origin."""
    ints = record_ints(record_view(raw, header))
    if mid is not None:
        return local_positions(ints, mid, header)
    true = ints * np.asarray(header.scales) + np.asarray(header.offsets)
    return true if origin is None else true - np.asarray(origin, np.float64)


def _fits(points, header, origin, mid, factor) -> bool:
    """Whether every position's integer at the header's scale / factor fits in int32."""
    lo, hi = points.min(axis=0), points.max(axis=0)
    scales = np.asarray(header.scales) / factor
    if mid is not None:
        ends = np.stack([lo, hi]) / scales + mid * factor
    else:
        base = np.zeros(3) if origin is None else np.asarray(origin, np.float64)
        ends = (np.stack([lo, hi]) + base - np.asarray(header.offsets)) / scales
    return bool(np.all(np.abs(np.round(ends)) <= _INT32.max))


def finer_decades(cloud, source: LasSource) -> int:
    """How many powers of ten finer than the input's scale to write `cloud` at: 0 unless the
    file's grid step is more than 1/MOVE_PER_STEP of the median move of the points that moved
    (a 1 cm file of 4.6 mm noise: moves of 2.4 mm would round back to the input for most
    points), then the fewest decades (at most MAX_FINER_DECADES, within int32) that bring it
    there. Moves are read against the source's records (a LAZ is streamed once more) only when
    some position is off the file's grid."""
    header, points = source.header, np.asarray(cloud.points, np.float64)
    mid = mid_of(cloud.origin, header)
    step = float(np.max(header.scales))
    base = np.zeros(3) if mid is not None or cloud.origin is None else np.asarray(cloud.origin)
    on_grid = np.zeros(3) if mid is not None else np.asarray(header.offsets) - base
    for start in range(0, len(points), CHUNK_POINTS):
        units = (points[start:start + CHUNK_POINTS] - on_grid) / np.asarray(header.scales)
        if np.any(np.abs(units - np.round(units)) > 1e-6):
            break
    else:
        return 0                                        # nothing moved off the grid
    moves, start = np.empty(len(points)), 0
    for raw in _source_records(source):
        stop = start + len(raw)
        if stop > len(points):
            return 0                                    # count mismatch: the writer says so
        moves[start:stop] = np.linalg.norm(
            points[start:stop] - _input_positions(raw, header, cloud.origin, mid), axis=1)
        start = stop
    moved = moves[:start][moves[:start] > 1e-6 * step]
    if start != len(points) or len(moved) == 0:
        return 0
    wanted = float(np.median(moved)) / MOVE_PER_STEP
    decades = 0
    while decades < MAX_FINER_DECADES and step / 10 ** decades > wanted:
        decades += 1
    while decades and not _fits(points, header, cloud.origin, mid, 10 ** decades):
        decades -= 1
    return decades


def _finer_scales(scales, decades) -> np.ndarray:
    """scales / 10^decades, each the short decimal it is written as (0.01 -> 0.001, not
    0.0009999...)."""
    return np.array([float(f"{s / 10 ** decades:.12g}") for s in scales])


def write_las(path, cloud, outliers=None, keep_scale=False, classify_outliers=False) -> list:
    """Write `cloud` as .las or .laz (by suffix), atomically. See the module docstring.
    keep_scale: always the input's own scale, even where it rounds the cleaning away.
    classify_outliers: flagged outliers also get classification NOISE_CLASS (their own class
    is not kept in the output; the input file still has it)."""
    from .points import atomic_paths

    path = Path(path)
    _need_laz_backend(path)
    source = cloud.source if isinstance(getattr(cloud, "source", None), LasSource) else None
    made = source is None                               # a new file's scale is already fine
    if made:
        source = new_source(path, cloud)
    header = _output_header(source.header, cloud.normals is not None, outliers is not None)
    mid = mid_of(cloud.origin, header)
    decades = 0 if keep_scale or made else finer_decades(cloud, source)
    if decades:
        header.scales = _finer_scales(header.scales, decades)
        mid = None if mid is None else mid * 10 ** decades
    with atomic_paths(path) as (tmp,):
        try:
            _write_records(path, tmp, header, _source_records(source),
                           cloud, None if outliers is None else np.asarray(outliers), mid,
                           classify_outliers)
        except InputError:
            raise
        except OSError as exc:
            raise InputError(f"{path}: cannot write ({exc.strerror or exc})") from None
    return [path]


def file_scales(path) -> tuple:
    """The X, Y, Z scales in a LAS/LAZ file's header (read without its points)."""
    with _open_reader(path) as reader:
        return tuple(float(v) for v in reader.header.scales)


# --------------------------------------------------------------------------- a new file

def _scale_and_offset(points):
    lo, hi = points.min(axis=0), points.max(axis=0)
    extent = float(np.max(hi - lo))
    scale = 10.0 ** np.floor(np.log10(extent)) * 1e-8 if extent > 0 else 1e-8
    scale = float(f"{scale:.0e}")                       # exactly a power of ten as written
    offset = np.floor((lo + hi) / 2.0 / (scale * 1e6)) * (scale * 1e6)
    return np.full(3, scale), offset


def _field_type(values: np.ndarray):
    if values.dtype == np.bool_:
        return np.uint8
    return values.dtype if values.dtype.kind in "iuf" else None


def new_source(path, cloud) -> LasSource:
    """A LAS 1.4 header (format 6, or 7 with red/green/blue) and records for a cloud read from
    another format: standard dimensions filled by name, other numeric properties as extra bytes."""
    laspy = laspy_module()
    extra = {k: np.asarray(v) for k, v in (cloud.extra or {}).items()
             if np.asarray(v).ndim == 1 and _field_type(np.asarray(v)) is not None}
    rgb = all(c in extra for c in ("red", "green", "blue"))
    header = laspy.LasHeader(version="1.4", point_format=7 if rgb else 6)
    header.scales, header.offsets = _scale_and_offset(np.asarray(cloud.true_points(), np.float64))
    standard = set(header.point_format.dimension_names)
    params, names = [], {}
    for key, values in extra.items():
        if key in standard:
            continue
        name = re.sub(r"[^A-Za-z0-9_]", "_", key)[:32]
        if name in standard or name in names.values() or name in NORMAL_DIMS or name == OUTLIER_DIM:
            continue
        names[key] = name
        params.append(laspy.ExtraBytesParams(name=name, type=_field_type(values)))
    if params:
        header.add_extra_dims(params)
    n = len(cloud.points)
    record = laspy.ScaleAwarePointRecord.zeros(n, header=header)
    for key, values in extra.items():
        target = key if key in standard else names.get(key)
        if target is None:
            continue
        try:
            record[target] = values.astype(record[target].dtype)
        except (ValueError, OverflowError, TypeError) as exc:
            raise InputError(f"{path}: property {key!r} does not fit LAS field {target!r} ({exc})") from None
    records = np.array(record.array.view(np.uint8).reshape(n, -1))
    return LasSource(header, records=records)


def header_bytes(header) -> bytes:
    """The header (VLRs and EVLRs included) as a zero-point LAS file: how a Blender object
    keeps its file's georeferencing for export."""
    laspy = laspy_module()
    header = _without_copc(header)
    buf = io.BytesIO()
    with laspy.LasWriter(buf, header, do_compress=False, closefd=False) as writer:
        if header.evlrs and header.version.minor >= 4:
            writer.write_evlrs(header.evlrs)
    return buf.getvalue()


def header_from_bytes(data: bytes):
    laspy = laspy_module()
    try:
        with laspy.open(io.BytesIO(data)) as reader:
            if reader.header.evlrs is None and reader.header.number_of_evlrs:
                reader.read_evlrs()
            return copy.deepcopy(reader.header)
    except Exception as exc:                                    # noqa: BLE001
        raise InputError(f"the stored LAS header cannot be read ({exc})") from None
