"""LAS/LAZ in and out (issue #15): core reader/writer, the command line, bad files.

Files are generated here with laspy (formats 1, 3, 6, 7, 8; with and without extra bytes; a
WKT CRS VLR). The engine runs with an untrained tiny model where only the file handling is
under test.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

laspy = pytest.importorskip("laspy")

from cljn_addon.core.errors import InputError  # noqa: E402
from cljn_addon.core.formats import las as lasio  # noqa: E402
from cljn_addon.core.formats import points as pointio  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_runner import cli  # noqa: E402

GEO_OFFSET = np.array([500_000.0, 5_000_000.0, 100.0])
WKT = ('PROJCS["WGS 84 / UTM zone 33N",GEOGCS["WGS 84",DATUM["WGS_1984",SPHEROID["WGS 84",6378137,'
       '298.257223563]],PRIMEM["Greenwich",0],UNIT["degree",0.0174532925199433]],PROJECTION['
       '"Transverse_Mercator"],UNIT["metre",1],AUTHORITY["EPSG","32633"]]')


def _cloud(n=1500, seed=0):
    """A noisy box surface, about 4 x 3 x 2 m."""
    from cljn_addon.core.evaluation import shapes

    noisy, _clean, _normals = shapes.sample_shape("box", n, noise=0.01, seed=seed)
    return noisy * 2.0


def make_las(path, points, fmt=7, extra_bytes=True, offset=GEO_OFFSET, scale=0.001, crs=True, seed=1):
    rng = np.random.default_rng(seed)
    header = laspy.LasHeader(version="1.4" if fmt >= 6 else "1.2", point_format=fmt)
    header.scales = np.full(3, scale)
    header.offsets = np.asarray(offset, np.float64)
    if extra_bytes:
        header.add_extra_dims([laspy.ExtraBytesParams(name="range", type=np.float64),
                               laspy.ExtraBytesParams(name="amplitude", type=np.int16)])
    if crs:
        header.vlrs.append(laspy.vlrs.known.WktCoordinateSystemVlr(WKT))
    data = laspy.LasData(header)
    n = len(points)
    data.x, data.y, data.z = (points + offset).T
    data.intensity = rng.integers(0, 65535, n)
    data.classification = rng.integers(0, 13, n)
    data.return_number = rng.integers(1, 3, n)
    data.number_of_returns = np.full(n, 3)
    data.point_source_id = rng.integers(0, 100, n)
    dims = set(data.point_format.dimension_names)
    if "gps_time" in dims:
        data.gps_time = 3.0e8 + rng.random(n) * 1e3
    if "red" in dims:
        data.red, data.green, data.blue = rng.integers(0, 65535, (3, n))
    if "nir" in dims:
        data.nir = rng.integers(0, 65535, n)
    if extra_bytes:
        data.range = rng.random(n) * 50
        data.amplitude = rng.integers(-3000, 3000, n)
    data.synthetic = rng.integers(0, 2, n).astype(bool)      # a flag beside the class
    data.write(str(path))
    return path


def _fields_equal(a, b, rows=slice(None), skip=("X", "Y", "Z")):
    """Every raw field of the input record equal in the output (by name, in the same order)."""
    names = [f for f in a.points.array.dtype.names if f not in skip]
    out_names = list(b.points.array.dtype.names)
    assert out_names[:len(a.points.array.dtype.names)] == list(a.points.array.dtype.names)
    return all(np.array_equal(a.points.array[f][rows], b.points.array[f][rows]) for f in names)


@pytest.mark.parametrize("suffix", [".las", ".laz"])
@pytest.mark.parametrize("extra_bytes", [False, True])
@pytest.mark.parametrize("fmt", [1, 3, 6, 7, 8])
def test_round_trip_keeps_every_field_and_the_header(tmp_path, fmt, extra_bytes, suffix):
    points = _cloud(800)
    src = make_las(tmp_path / f"in{suffix}", points, fmt=fmt, extra_bytes=extra_bytes)
    cloud = pointio.read_points(src, with_fields=False)
    assert cloud.points.dtype == np.float64 and np.allclose(cloud.true_points(), points + GEO_OFFSET, atol=6e-4)
    moved = cloud.points.copy()
    moved[:50] += [0.0123, -0.02, 0.0071]
    normals = np.tile(np.float32([0.0, 0.6, 0.8]), (len(moved), 1))
    outliers = np.zeros(len(moved), bool)
    outliers[::97] = True
    out = tmp_path / f"out{suffix}"
    pointio.write_points(out, pointio.PointCloud(moved, normals, source=cloud.source, origin=cloud.origin),
                         outliers=outliers)

    a, b = laspy.read(str(src)), laspy.read(str(out))
    assert b.header.point_format.id == fmt and str(b.header.version) == str(a.header.version)
    assert np.array_equal(b.header.scales, a.header.scales) and np.array_equal(b.header.offsets, a.header.offsets)
    assert [v.record_id for v in b.header.vlrs if v.user_id == "LASF_Projection"] == \
        [v.record_id for v in a.header.vlrs if v.user_id == "LASF_Projection"]
    wkt = [v.string for v in b.header.vlrs if isinstance(v, laspy.vlrs.known.WktCoordinateSystemVlr)]
    assert wkt and wkt[0].rstrip("\x00") == WKT, "the CRS VLR was lost"
    assert _fields_equal(a, b), "a field other than X/Y/Z changed"
    # Unmoved points: bit-identical integers; moved ones at the file's scale.
    for axis in "XYZ":
        assert np.array_equal(a.points.array[axis][50:], b.points.array[axis][50:])
    got = np.stack([b.x, b.y, b.z], axis=1)[:50]
    assert np.abs(got - (moved[:50] + cloud.origin)).max() <= 0.0005 + 1e-9
    extra = list(b.point_format.extra_dimension_names)
    assert extra[-4:] == [*lasio.NORMAL_DIMS, lasio.OUTLIER_DIM]
    if extra_bytes:
        assert extra[:2] == ["range", "amplitude"]
    assert b["NormalX"].dtype == np.float32
    assert np.allclose(np.stack([b[d] for d in lasio.NORMAL_DIMS], axis=1), normals)
    assert np.array_equal(np.asarray(b[lasio.OUTLIER_DIM]), outliers.astype(np.uint8))

    # Our own output read again: normals come back; writing again overwrites, never duplicates.
    again = pointio.read_points(out, with_fields=False)
    assert np.allclose(again.normals, normals)
    out2 = tmp_path / f"out2{suffix}"
    pointio.write_points(out2, pointio.PointCloud(again.points, -normals, source=again.source, origin=again.origin),
                         outliers=outliers)
    c = laspy.read(str(out2))
    assert list(c.point_format.extra_dimension_names) == extra
    assert np.allclose(np.asarray(c["NormalY"]), -0.6)


def test_writing_streams_in_chunks(tmp_path, monkeypatch):
    """Chunks smaller than the file: the same bytes as one chunk."""
    points = _cloud(700)
    src = make_las(tmp_path / "in.laz", points, fmt=6)
    cloud = pointio.read_points(src, with_fields=False)
    normals = np.tile(np.float32([1.0, 0.0, 0.0]), (len(points), 1))
    pointio.write_points(tmp_path / "one.las", pointio.PointCloud(cloud.points, normals, source=cloud.source,
                                                                   origin=cloud.origin))
    monkeypatch.setattr(lasio, "CHUNK_POINTS", 64)
    chunked = pointio.read_points(src, with_fields=False)
    assert np.array_equal(chunked.points, cloud.points)
    pointio.write_points(tmp_path / "many.las", pointio.PointCloud(chunked.points, normals, source=chunked.source,
                                                                    origin=chunked.origin))
    assert (tmp_path / "one.las").read_bytes() == (tmp_path / "many.las").read_bytes()


def _moved_copy(cloud, size, seed=3, still=100):
    """cloud's positions moved by ~size (random directions), the first `still` not moved."""
    rng = np.random.default_rng(seed)
    steps = rng.normal(size=cloud.points.shape)
    moved = cloud.points + size * steps / np.linalg.norm(steps, axis=1, keepdims=True)
    moved[:still] = cloud.points[:still]
    return moved


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_a_grid_too_coarse_for_the_moves_is_written_finer_and_unmoved_points_stay_exact(tmp_path, suffix):
    """1 cm file, 3 mm moves: at the file's scale most moves would round back to the input
    (the plane.laz case). Written at 1 mm: each move kept to 0.5 mm a coordinate, unmoved
    points at 10x their input integers, every other byte and the offsets as they were;
    --keep-las-scale (keep_las_scale) writes the file's own grid."""
    src = make_las(tmp_path / f"in{suffix}", _cloud(900), fmt=6, scale=0.01)
    cloud = pointio.read_points(src, with_fields=False)
    moved = _moved_copy(cloud, 0.003)
    result = pointio.PointCloud(moved, None, source=cloud.source, origin=cloud.origin)
    a = laspy.read(str(src))

    on_file_grid = tmp_path / f"kept{suffix}"
    pointio.write_points(on_file_grid, result, keep_las_scale=True)
    kept = laspy.read(str(on_file_grid))
    assert np.array_equal(kept.header.scales, a.header.scales)
    lost = np.all(np.stack([a.points.array[x] == kept.points.array[x] for x in "XYZ"]), axis=0)
    assert lost[100:].mean() > 0.4, "the case under test: the 1 cm grid rounds many moves back"

    out = tmp_path / f"out{suffix}"
    pointio.write_points(out, result)
    b = laspy.read(str(out))
    assert np.allclose(b.header.scales, 0.001) and np.array_equal(b.header.offsets, a.header.offsets)
    assert lasio.file_scales(out) == (0.001, 0.001, 0.001)
    assert _fields_equal(a, b)
    for axis in "XYZ":
        assert np.array_equal(np.asarray(b.points.array[axis][:100], np.int64),
                              10 * np.asarray(a.points.array[axis][:100], np.int64)), axis
    got = np.stack([b.x, b.y, b.z], axis=1)
    assert np.abs(got - (moved + cloud.origin)).max() <= 0.0005 + 1e-9
    kept_share = np.linalg.norm(got - cloud.true_points(), axis=1)[100:] / 0.003
    assert np.median(kept_share) > 0.8, np.median(kept_share)


def test_how_much_finer_follows_the_moves_within_int32(tmp_path):
    """Decades finer: none where the grid holds the moves, one per tenfold smaller move, at
    most MAX_FINER_DECADES; fewer where the finer integers would leave int32; none when no
    position left the grid (normals only)."""
    src = make_las(tmp_path / "in.las", _cloud(600), fmt=1, scale=0.01)
    cloud = pointio.read_points(src, with_fields=False)
    decades = {size: lasio.finer_decades(pointio.PointCloud(_moved_copy(cloud, size), None, source=cloud.source,
                                                            origin=cloud.origin), cloud.source)
               for size in (0.05, 0.02, 0.003, 0.0003, 1e-6)}
    assert decades == {0.05: 0, 0.02: 0, 0.003: 1, 0.0003: 2, 1e-6: lasio.MAX_FINER_DECADES}
    assert lasio.finer_decades(cloud, cloud.source) == 0

    # 20,000 km from the offset at 1 cm: 2e9 units; ten times that leaves int32.
    far = make_las(tmp_path / "far.las", _cloud(300) + [2.0e7, 0.0, 0.0], fmt=1, offset=np.zeros(3), scale=0.01)
    cloud = pointio.read_points(far, with_fields=False)
    moved = pointio.PointCloud(_moved_copy(cloud, 0.003), None, source=cloud.source, origin=cloud.origin)
    assert lasio.finer_decades(moved, cloud.source) == 0
    pointio.write_points(tmp_path / "far_out.las", moved)
    assert lasio.file_scales(tmp_path / "far_out.las") == (0.01, 0.01, 0.01)


def test_a_new_file_from_another_format_keeps_its_own_scale(tmp_path):
    """A cloud from .ply/.npy gets 1e-8 of its extent as scale, never refined further."""
    pts = _cloud(400) + GEO_OFFSET
    out = tmp_path / "new.las"
    pointio.write_points(out, pointio.PointCloud(pts, None))
    scale = lasio.file_scales(out)[0]
    assert scale == float(f"{scale:.0e}") and 1e-8 <= scale <= 1e-7, scale
    b = laspy.read(str(out))
    assert np.abs(np.stack([b.x, b.y, b.z], axis=1) - pts).max() <= scale


def test_las_fields_go_to_other_formats_and_back(tmp_path):
    points = _cloud(600)
    src = make_las(tmp_path / "in.las", points, fmt=7)
    cloud = pointio.read_points(src)
    a = laspy.read(str(src))
    for name in ("intensity", "classification", "red", "gps_time", "range", "return_number"):
        assert np.array_equal(cloud.extra[name], np.asarray(a[name])), name
    pointio.write_points(tmp_path / "mid.ply", cloud)
    ply = pointio.read_points(tmp_path / "mid.ply")
    # A file from another format: LAS 1.4, format 7 (it has RGB), standard fields by name.
    pointio.write_points(tmp_path / "new.laz", ply, outliers=np.zeros(len(ply.points), bool))
    b = laspy.read(str(tmp_path / "new.laz"))
    assert b.header.point_format.id == 7 and str(b.header.version) == "1.4"
    assert np.abs(np.stack([b.x, b.y, b.z], axis=1) - cloud.true_points()).max() < 1e-6
    for name in ("intensity", "classification", "red", "blue", "gps_time"):
        assert np.array_equal(np.asarray(b[name]), np.asarray(a[name])), name
    assert np.allclose(np.asarray(b["range"]), np.asarray(a["range"]))


def test_command_line_normals_keeps_every_byte_but_adds_normals(tmp_path, model_path):
    src = make_las(tmp_path / "scan.laz", _cloud(1200), fmt=8)
    before = src.read_bytes()
    proc = cli("normals", src, "-o", tmp_path / "out.laz", "--model", model_path, "--no-progress")
    assert proc.returncode == 0, proc.stderr
    assert src.read_bytes() == before
    a, b = laspy.read(str(src)), laspy.read(str(tmp_path / "out.laz"))
    assert _fields_equal(a, b, skip=()), "normals must not change any input field, X/Y/Z included"
    n = np.stack([b[d] for d in lasio.NORMAL_DIMS], axis=1)
    assert np.allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-5)


def test_command_line_denoise_las_to_las_and_to_ply(tmp_path, model_path):
    src = make_las(tmp_path / "scan.las", _cloud(1200), fmt=3)
    proc = cli("denoise", src, "-o", tmp_path / "clean.las", "--model", model_path, "--iterations", "1",
               "--no-progress")
    assert proc.returncode == 0, proc.stderr
    a, b = laspy.read(str(src)), laspy.read(str(tmp_path / "clean.las"))
    assert _fields_equal(a, b)
    assert not np.array_equal(a.points.array["Z"], b.points.array["Z"]), "nothing moved"
    proc = cli("denoise", src, "-o", tmp_path / "clean.ply", "--model", model_path, "--iterations", "1",
               "--no-progress")
    assert proc.returncode == 0, proc.stderr
    ply = pointio.read_points(tmp_path / "clean.ply")
    assert np.array_equal(ply.extra["intensity"], np.asarray(a.intensity))
    assert np.allclose(ply.points, np.stack([b.x, b.y, b.z], axis=1), atol=6e-4)


def test_command_line_reports_the_written_scale_and_keeps_the_file_s_on_request(tmp_path, model_path):
    """The report says the scale written; the note is printed exactly when it is finer than the
    input's; --keep-las-scale writes the input's."""
    import json

    src = make_las(tmp_path / "coarse.laz", _cloud(900), fmt=6, scale=0.01)
    for flags, name in (([], "auto.laz"), (["--keep-las-scale"], "kept.laz")):
        proc = cli("denoise", src, "-o", tmp_path / name, "--model", model_path, "--iterations", "1",
                   "--no-progress", "--report", tmp_path / "r.json", *flags)
        assert proc.returncode == 0, proc.stderr
        written = lasio.file_scales(tmp_path / name)
        assert json.loads((tmp_path / "r.json").read_text())["inputs"][0]["las_scale"] == list(written)
        assert ("finer than the input's 0.01" in proc.stdout) == (written[0] < 0.01), proc.stdout
        if flags:
            assert written == (0.01, 0.01, 0.01)
        else:
            assert written[0] in (0.01, 0.001, 0.0001, 0.00001)


@pytest.mark.parametrize("fmt", [1, 6])
def test_classified_outliers_get_the_noise_class_and_nothing_else_changes(tmp_path, fmt):
    """Formats 0-5 hold the class in 5 bits, 6-10 in a byte: either way flagged points read 7
    (ASPRS low point/noise) and every other point and field is as it was."""
    src = make_las(tmp_path / "in.las", _cloud(500), fmt=fmt)
    cloud = pointio.read_points(src, with_fields=False)
    outliers = np.zeros(500, bool)
    outliers[[3, 77, 400]] = True
    out = tmp_path / "out.las"
    pointio.write_points(out, pointio.PointCloud(cloud.points, None, source=cloud.source, origin=cloud.origin),
                         outliers=outliers, classify_outliers=True)
    a, b = laspy.read(str(src)), laspy.read(str(out))
    classes = np.asarray(b.classification)
    assert np.all(classes[outliers] == lasio.NOISE_CLASS)
    assert np.array_equal(classes[~outliers], np.asarray(a.classification)[~outliers])
    assert np.count_nonzero(np.asarray(a.classification)[outliers] != lasio.NOISE_CLASS) > 0
    assert _fields_equal(a, b, skip=("classification", "raw_classification"))
    if fmt < 6:          # the byte's 3 flag bits (synthetic, key-point, withheld) kept
        assert np.array_equal(a.points.array["raw_classification"] & 0xE0, b.points.array["raw_classification"] & 0xE0)
    # Without the request the class is the input's.
    pointio.write_points(out, pointio.PointCloud(cloud.points, None, source=cloud.source, origin=cloud.origin),
                         outliers=outliers)
    assert np.array_equal(np.asarray(laspy.read(str(out)).classification), np.asarray(a.classification))


def test_command_line_classifies_the_outliers_it_flags(tmp_path, model_path):
    """Three stray points far off the box are flagged; --classify-outliers gives exactly the
    flagged points class 7 and says how many; a LAS-only flag without a LAS output is refused."""
    import json

    points = np.vstack([_cloud(1200), [[40.0, 0.0, 0.0], [0.0, 40.0, 0.0], [0.0, 0.0, 40.0]]])
    src = make_las(tmp_path / "stray.las", points, fmt=6)
    proc = cli("denoise", src, "-o", tmp_path / "clean.las", "--model", model_path, "--iterations", "1",
               "--no-progress", "--classify-outliers", "--report", tmp_path / "r.json")
    assert proc.returncode == 0, proc.stderr
    b = laspy.read(str(tmp_path / "clean.las"))
    flagged = np.asarray(b[lasio.OUTLIER_DIM]).astype(bool)
    assert flagged[-3:].all()
    assert np.array_equal(np.asarray(b.classification) == lasio.NOISE_CLASS,
                          flagged | (np.asarray(laspy.read(str(src)).classification) == lasio.NOISE_CLASS))
    report = json.loads((tmp_path / "r.json").read_text())["inputs"][0]
    assert report["outliers_classified"] == int(flagged.sum()) == report["outliers"]
    for flag in ("--classify-outliers", "--keep-las-scale"):
        proc = cli("denoise", src, "-o", tmp_path / "clean.ply", "--model", model_path, "--no-progress", flag)
        assert proc.returncode == 2 and f"{flag} applies to .las/.laz outputs" in proc.stderr, proc.stderr
        assert not (tmp_path / "clean.ply").exists()


def test_georeferenced_scan_denoises_like_the_same_scan_at_the_origin(tmp_path, model_path):
    """Same integers, offsets (500 km, 5000 km, 100 m) and 0: results equal to the file's scale."""
    points = _cloud(1500, seed=5)
    geo = make_las(tmp_path / "geo.laz", points, fmt=6, offset=GEO_OFFSET)
    local = make_las(tmp_path / "local.laz", points, fmt=6, offset=np.zeros(3))
    for src in (geo, local):
        proc = cli("denoise", src, "-o", src.with_name(src.stem + "_out.laz"), "--model", model_path,
                   "--iterations", "2", "--no-progress")
        assert proc.returncode == 0, proc.stderr
    g, o = laspy.read(str(tmp_path / "geo_out.laz")), laspy.read(str(tmp_path / "local_out.laz"))
    gp = np.stack([g.x, g.y, g.z], axis=1) - GEO_OFFSET
    op = np.stack([o.x, o.y, o.z], axis=1)
    moved = np.linalg.norm(op - np.stack([laspy.read(str(local)).x, laspy.read(str(local)).y,
                                          laspy.read(str(local)).z], axis=1), axis=1)
    assert moved.max() > 0.002, "the test needs points that move"
    assert np.abs(gp - op).max() <= 0.001 + 1e-9, np.abs(gp - op).max()
    gn = np.stack([g[d] for d in lasio.NORMAL_DIMS], axis=1)
    on = np.stack([o[d] for d in lasio.NORMAL_DIMS], axis=1)
    assert np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", gn, on), -1, 1))).max() < 0.5


# ------------------------------------------------------------------------------- bad input

def _assert_refused(proc, path, words, outputs):
    assert proc.returncode == 2, (proc.returncode, proc.stderr)
    assert str(path) in proc.stderr and words in proc.stderr, proc.stderr
    assert "Traceback" not in proc.stderr
    for out in outputs:
        assert not out.exists(), f"{out} was written"


def test_truncated_corrupt_and_empty_files_exit_2_and_write_nothing(tmp_path, model_path):
    good = make_las(tmp_path / "good.laz", _cloud(3000), fmt=7)
    data = good.read_bytes()
    cases = {
        "truncated.laz": (data[: len(data) // 2], "LAS/LAZ"),
        "corrupt.laz": (data[:400] + bytes(np.random.default_rng(0).integers(0, 255, 20000, dtype=np.uint8)),
                        "LAS/LAZ"),
        "notlas.las": (b"this is not a LAS file at all\n" * 20, "not a readable LAS/LAZ file"),
    }
    good_las = make_las(tmp_path / "good.las", _cloud(3000), fmt=1)
    cases["truncated.las"] = (good_las.read_bytes()[:-5000], "truncated")
    for name, (content, words) in cases.items():
        path = tmp_path / name
        path.write_bytes(content)
        out = tmp_path / f"out_{name}"
        proc = cli("denoise", path, "-o", out, "--model", model_path, "--no-progress")
        _assert_refused(proc, path, words, [out])
        assert path.read_bytes() == content
    empty = tmp_path / "empty.las"
    laspy.LasData(laspy.LasHeader(version="1.4", point_format=6)).write(str(empty))
    proc = cli("denoise", empty, "-o", tmp_path / "e_out.las", "--model", model_path, "--no-progress")
    _assert_refused(proc, empty, "no points", [tmp_path / "e_out.las"])


def test_positions_the_file_scale_cannot_hold_are_refused(tmp_path, monkeypatch, model_path, capsys):
    """A move past the int32 range of the file's scale: exit 2, the file named, nothing written."""
    from cljn_addon.cli import app
    from cljn_addon.core.options import DenoiseOptions

    points = _cloud(800)
    src = make_las(tmp_path / "tight.las", points, fmt=1, offset=np.zeros(3), scale=1e-9)
    before = src.read_bytes()
    real_run = DenoiseOptions.run

    def run_and_push(self, pts, model, **kw):
        res = real_run(self, pts, model, **kw)
        res.points = res.points + [3.0, 0.0, 0.0]     # 3 m at 1 nm: past 2^31 units
        return res

    monkeypatch.setattr(DenoiseOptions, "run", run_and_push)
    code = app.main(["denoise", str(src), "-o", str(tmp_path / "out.las"), "--model", str(model_path),
                     "--iterations", "1", "--no-progress"])
    err = capsys.readouterr().err
    assert code == 2 and str(tmp_path / "out.las") in err and "cannot be stored at the file's scale" in err, err
    assert not (tmp_path / "out.las").exists() and src.read_bytes() == before
    assert not list(tmp_path.glob(".out*")), "a temporary file was left behind"

    # The in-place variant leaves the input as it was.
    code = app.main(["denoise", str(src), "--in-place", "--model", str(model_path), "--iterations", "1",
                     "--no-progress"])
    assert code == 2 and src.read_bytes() == before


def test_format_without_rgb_and_quantise_errors_name_the_file(tmp_path):
    src = make_las(tmp_path / "norgb.las", _cloud(300), fmt=1, extra_bytes=False, crs=False)
    cloud = pointio.read_points(src)
    assert "red" not in cloud.extra and "gps_time" in cloud.extra
    with pytest.raises(InputError, match="norgb_out.las"):
        lasio.quantise(tmp_path / "norgb_out.las", np.array([[1e12, 0.0, 0.0]]), cloud.source.header)


def test_las_to_blend_keeps_what_export_needs(tmp_path, model_path):
    """`.las -> .blend` makes the object File > Import makes (recentred), denoised; exporting it
    gives the true coordinates and every field back."""
    import subprocess

    pytest.importorskip("bpy")
    src = make_las(tmp_path / "scan.laz", _cloud(1000), fmt=7)
    proc = cli("denoise", src, "-o", tmp_path / "scan.blend", "--model", model_path, "--iterations", "1",
               "--no-progress")
    assert proc.returncode == 0, proc.stderr
    code = f"""
import sys
sys.path.insert(0, {str(Path(__file__).resolve().parents[1])!r})
import bpy
bpy.ops.wm.open_mainfile(filepath={str(tmp_path / 'scan.blend')!r})
from cljn_addon.blender import las_io
obj = bpy.data.objects['scan']
assert max(abs(v) for v in obj.bound_box[0]) < 10, 'not recentred'
las_io.export_las(obj, {str(tmp_path / 'back.las')!r})
"""
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr[-3000:]
    a, b = laspy.read(str(src)), laspy.read(str(tmp_path / "back.las"))
    assert _fields_equal(a, b)
    assert np.array_equal(b.header.offsets, a.header.offsets)
    moved = np.linalg.norm(np.stack([b.x - a.x, b.y - a.y, b.z - a.z], axis=1), axis=1)
    assert 0 < moved.max() < 1.0, moved.max()
    assert np.allclose(np.linalg.norm(np.stack([b[d] for d in lasio.NORMAL_DIMS], axis=1), axis=1), 1, atol=1e-5)


SCANS = Path(__file__).resolve().parents[2] / "shared" / "data" / "scans"


@pytest.mark.skipif(not (SCANS / "plane.laz").exists(), reason="../shared/data/scans/plane.laz absent")
def test_real_laz_scan_with_the_shipped_model(tmp_path):
    """A real 1 cm-quantised LiDAR patch: noise seen (it was ~1e-10 before the dithered estimate),
    points moved within the bound, every field kept, exact integers where nothing moved."""
    import json

    src = SCANS / "plane.laz"
    out = tmp_path / "plane_clean.laz"
    proc = cli("denoise", src, "-o", out, "--iterations", "auto", "--no-progress", "--report",
               tmp_path / "r.json")
    assert proc.returncode == 0, proc.stderr
    report = json.loads((tmp_path / "r.json").read_text())["inputs"][0]
    assert 0.002 < report["noise_sigma"] < 0.02, report
    a, b = laspy.read(str(src)), laspy.read(str(out))
    assert _fields_equal(a, b)
    move = np.linalg.norm(np.stack([b.x - a.x, b.y - a.y, b.z - a.z], axis=1), axis=1)
    assert 0 < np.count_nonzero(move) and move.max() <= report["displacement_bound"] + 0.001 * np.sqrt(3) / 2
    # Moves of ~3 mm on its 1 cm grid: written at 1 mm, so the file holds the cleaning (at 1 cm
    # 81% of the points rounded back to the input).
    assert report["las_scale"] == [0.001] * 3 and "finer than the input's 0.01" in proc.stdout, proc.stdout
    assert np.count_nonzero(move) > 0.8 * len(move)             # 89% (1 cm: 19%)
    assert abs(move.mean() - report["mean_displacement"]) < 0.1 * report["mean_displacement"]


def test_evlrs_are_kept(tmp_path):
    """LAS 1.4 extended VLRs (after the points) come back in the output."""
    src = tmp_path / "evlr.laz"
    make_las(src, _cloud(400), fmt=6)
    data = laspy.read(str(src))
    data.evlrs = laspy.vlrs.vlrlist.VLRList([laspy.VLR(user_id="CLJN_TEST", record_id=42, description="kept",
                                          record_data=b"x" * 70000)])
    data.write(str(src))
    cloud = pointio.read_points(src, with_fields=False)
    out = tmp_path / "out.laz"
    pointio.write_points(out, pointio.PointCloud(cloud.points, np.tile(np.float32([0, 0, 1]), (400, 1)),
                                                 source=cloud.source, origin=cloud.origin))
    evlrs = laspy.read(str(out)).evlrs
    assert [(v.user_id, v.record_id, len(v.record_data)) for v in evlrs] == [("CLJN_TEST", 42, 70000)]


def test_a_copc_index_is_left_out_and_the_rest_kept(tmp_path):
    """A COPC file (LAZ 1.4 plus a "copc" info VLR and hierarchy EVLR that locate octree chunks
    by byte offset): written back as plain LAZ without that index, which would point into the
    rewritten chunks; the CRS, other (E)VLRs and every record kept."""
    src = tmp_path / "tile.copc.laz"
    make_las(src, _cloud(500), fmt=6)
    data = laspy.read(str(src))
    data.header.vlrs.insert(0, laspy.VLR(user_id="copc", record_id=1, description="copc info",
                                         record_data=bytes(160)))
    data.evlrs = laspy.vlrs.vlrlist.VLRList([
        laspy.VLR(user_id="copc", record_id=1000, description="EPT hierarchy", record_data=bytes(32)),
        laspy.VLR(user_id="CLJN_TEST", record_id=7, description="kept", record_data=b"y" * 40)])
    data.write(str(src))
    a = laspy.read(str(src))
    assert any(_vlr_id(v) == ("copc", 1) for v in a.header.vlrs), "the test file has no COPC info"

    cloud = pointio.read_points(src, with_fields=False)
    out = tmp_path / "clean.copc.laz"
    pointio.write_points(out, pointio.PointCloud(cloud.points, np.tile(np.float32([0, 0, 1]), (500, 1)),
                                                 source=cloud.source, origin=cloud.origin))
    b = laspy.read(str(out))
    assert [_vlr_id(v) for v in b.header.vlrs if _vlr_id(v)[0] == "copc"] == []
    assert [_vlr_id(v) for v in b.evlrs] == [("CLJN_TEST", 7)]
    assert any(isinstance(v, laspy.vlrs.known.WktCoordinateSystemVlr) for v in b.header.vlrs)
    assert _fields_equal(a, b, skip=())
    # What a Blender object keeps of the header (File > Import): the same, less the index.
    kept = lasio.header_from_bytes(lasio.header_bytes(cloud.source.header))
    assert [_vlr_id(v) for v in kept.vlrs if _vlr_id(v)[0] == "copc"] == []
    assert [_vlr_id(v) for v in kept.evlrs] == [("CLJN_TEST", 7)]
    assert any(isinstance(v, laspy.vlrs.known.WktCoordinateSystemVlr) for v in kept.vlrs)


def _vlr_id(vlr):
    return (str(vlr.user_id).rstrip("\x00"), int(vlr.record_id))
