"""Point-cloud file formats: every format in and out, values checked exactly."""
import struct

import numpy as np
import pytest

from cljn_addon.core.errors import InputError
from cljn_addon.core.formats import points as pointio
from cljn_addon.core.formats.points import PointCloud


def _cloud(n=50, dtype=np.float32, seed=0):
    rng = np.random.default_rng(seed)
    pts = rng.normal(size=(n, 3)).astype(dtype)
    nrm = rng.normal(size=(n, 3))
    nrm = (nrm / np.linalg.norm(nrm, axis=1, keepdims=True)).astype(np.float32)
    extra = {
        "red": rng.integers(0, 256, n).astype(np.uint8),
        "green": rng.integers(0, 256, n).astype(np.uint8),
        "blue": rng.integers(0, 256, n).astype(np.uint8),
        "intensity": rng.random(n).astype(np.float32),
        "label": rng.integers(-5, 5000, n).astype(np.int32),
    }
    return PointCloud(pts, nrm, extra, comments=["made by a test"])


@pytest.mark.parametrize("fmt", ["binary_little_endian", "binary_big_endian", "ascii"])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_ply_round_trip(tmp_path, fmt, dtype):
    src = _cloud(dtype=dtype)
    out = tmp_path / "c.ply"
    outliers = np.zeros(len(src), bool)
    outliers[[3, 7]] = True
    pointio.write_ply(out, src, outliers=outliers, fmt=fmt)
    header = out.read_bytes()[:400]
    assert f"format {fmt} 1.0".encode() in header
    back = pointio.read_ply(out)
    assert back.points.dtype == np.dtype(dtype)
    np.testing.assert_array_equal(back.points, src.points)
    np.testing.assert_array_equal(back.normals, src.normals)
    assert list(back.extra) == ["red", "green", "blue", "intensity", "label", "cljn_outlier"]
    for name, values in src.extra.items():
        assert back.extra[name].dtype == values.dtype, name
        np.testing.assert_array_equal(back.extra[name], values)
    np.testing.assert_array_equal(back.extra["cljn_outlier"], outliers.astype(np.uint8))
    assert back.comments == ["made by a test"]
    assert not list(tmp_path.glob(".*tmp*"))            # no temporary left behind


def test_ply_rewrite_replaces_outlier_flags(tmp_path):
    src = _cloud(n=10)
    src.extra["cljn_outlier"] = np.ones(10, np.uint8)
    pointio.write_ply(tmp_path / "a.ply", src, outliers=np.zeros(10, bool))
    back = pointio.read_ply(tmp_path / "a.ply")
    assert list(back.extra).count("cljn_outlier") == 1
    assert not back.extra["cljn_outlier"].any()


def test_ascii_ply_by_hand_crlf_faces_and_comments(tmp_path):
    text = ("ply\r\nformat ascii 1.0\r\ncomment hello\r\nobj_info scanner 1\r\n"
            "element vertex 4\r\nproperty float x\r\nproperty float y\r\nproperty float z\r\n"
            "property uchar red\r\n"
            "element face 2\r\nproperty list uchar int vertex_indices\r\nend_header\r\n"
            "0 0 0 255\r\n1 0 0 0\r\n0 1 0 10\r\n\r\n0 0 1.5 20\r\n"
            "3 0 1 2\r\n4 0 1 2 3\r\n")
    path = tmp_path / "hand.ply"
    path.write_bytes(text.encode())
    c = pointio.read_ply(path)
    np.testing.assert_array_equal(c.points, np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.5]],
                                                     np.float32))
    assert c.normals is None
    np.testing.assert_array_equal(c.extra["red"], [255, 0, 10, 20])
    assert c.extra["red"].dtype == np.uint8
    assert [list(f) for f in c.faces] == [[0, 1, 2], [0, 1, 2, 3]]
    assert c.comments == ["hello"]


def _binary_ply(endian, verts, faces, vertex_first=True, normal_names=("nx", "ny", "nz")):
    fmt = "binary_little_endian" if endian == "<" else "binary_big_endian"
    vhead = ("element vertex %d\nproperty double x\nproperty double y\nproperty double z\n"
             "property float %s\nproperty float %s\nproperty float %s\n" % ((len(verts),) + normal_names))
    fhead = "element face %d\nproperty list uchar uint vertex_indices\n" % len(faces)
    vbody = b"".join(struct.pack(endian + "dddfff", *v) for v in verts)
    fbody = b"".join(struct.pack(endian + "B" + "I" * len(f), len(f), *f) for f in faces)
    head = "ply\nformat %s 1.0\n" % fmt + (vhead + fhead if vertex_first else fhead + vhead)
    body = vbody + fbody if vertex_first else fbody + vbody
    return (head + "end_header\n").encode() + body


@pytest.mark.parametrize("endian", ["<", ">"])
@pytest.mark.parametrize("faces", [[(0, 1, 2), (1, 2, 0)], [(0, 1, 2), (0, 1, 2, 1)]])
@pytest.mark.parametrize("vertex_first", [True, False])
def test_binary_ply_by_hand(tmp_path, endian, faces, vertex_first):
    verts = [(0.1, 0.2, 0.3, 0, 0, 1), (1e-3, -2.5, 7.0, 0, 1, 0), (3.0, 2.0, 1.0, 1, 0, 0)]
    path = tmp_path / "b.ply"
    path.write_bytes(_binary_ply(endian, verts, faces, vertex_first, ("normal_x", "normal_y",
                                                                      "normal_z")))
    c = pointio.read_ply(path)
    np.testing.assert_array_equal(c.points, np.array(verts)[:, :3])
    assert c.points.dtype == np.float64
    np.testing.assert_array_equal(c.normals, np.array(verts, np.float32)[:, 3:])
    assert c.extra == {}
    assert [list(f) for f in c.faces] == [list(f) for f in faces]


def test_truncated_binary_ply(tmp_path):
    verts = [(0.1, 0.2, 0.3, 0, 0, 1)] * 10
    data = _binary_ply("<", verts, [])
    path = tmp_path / "t.ply"
    path.write_bytes(data[:-30])
    with pytest.raises(InputError, match=r"t\.ply: truncated PLY.*10 vertex.*holds 9"):
        pointio.read_ply(path)


def test_truncated_ascii_ply(tmp_path):
    path = tmp_path / "t.ply"
    path.write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                    "property float z\nend_header\n0 0 0\n1 1 1\n")
    with pytest.raises(InputError, match="truncated PLY"):
        pointio.read_ply(path)


@pytest.mark.parametrize("content,message", [
    (b"hello world", "not a PLY file"),
    (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\n", "no end_header"),
    (b"ply\nformat ascii 1.0\nelement face 0\nend_header\n", "no vertex element"),
    (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nend_header\n1 2\n",
     "no 'z' coordinate"),
    (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty quux x\nend_header\n", "header line 4"),
    (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n"
     b"property float z\nend_header\n1 2 oops\n", "record 0"),
    (b"ply\nformat binary_middle_endian 1.0\nend_header\n", "unknown PLY format"),
])
def test_bad_ply(tmp_path, content, message):
    path = tmp_path / "bad.ply"
    path.write_bytes(content)
    with pytest.raises(InputError, match=message) as info:
        pointio.read_points(path)
    assert str(info.value).startswith(str(path))


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_xyz_round_trip_with_normals(tmp_path, dtype):
    src = _cloud(dtype=dtype)
    written = pointio.write_points(tmp_path / "c.xyz", src)
    assert written == [tmp_path / "c.xyz", tmp_path / "c.normals"]
    back = pointio.read_points(tmp_path / "c.xyz")
    np.testing.assert_array_equal(back.points.astype(dtype), src.points)
    np.testing.assert_array_equal(back.normals.astype(np.float32), src.normals)
    assert back.extra == {}


def test_xyz_variants(tmp_path):
    (tmp_path / "plain.xyz").write_text("# comment\n1 2 3\n4 5 6\n")
    c = pointio.read_points(tmp_path / "plain.xyz")
    np.testing.assert_array_equal(c.points, [[1, 2, 3], [4, 5, 6]])
    assert c.normals is None
    (tmp_path / "six.xyz").write_text("1 2 3 0 0 1\n4 5 6 0.6 0.8 0\n")
    c = pointio.read_points(tmp_path / "six.xyz")
    np.testing.assert_array_equal(c.normals, [[0, 0, 1], [0.6, 0.8, 0]])
    (tmp_path / "rgb.xyz").write_text("1 2 3 255 0 0\n4 5 6 0 255 0\n")
    c = pointio.read_points(tmp_path / "rgb.xyz")
    assert c.normals is None and list(c.extra) == ["col3", "col4", "col5"]
    (tmp_path / "short.xyz").write_text("1 2 3\n")
    (tmp_path / "short.normals").write_text("0 0 1\n0 1 0\n")
    with pytest.raises(InputError, match="short.normals: expected 1 rows"):
        pointio.read_points(tmp_path / "short.xyz")
    (tmp_path / "bad.xyz").write_text("1 2 3\n4 five 6\n")
    with pytest.raises(InputError, match="bad.xyz: cannot read the numbers"):
        pointio.read_points(tmp_path / "bad.xyz")
    (tmp_path / "empty.xyz").write_text("")
    with pytest.raises(InputError, match="empty"):
        pointio.read_points(tmp_path / "empty.xyz")
    (tmp_path / "two.xyz").write_text("1 2\n")
    with pytest.raises(InputError, match="at least 3 columns"):
        pointio.read_points(tmp_path / "two.xyz")


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_npy_round_trip(tmp_path, dtype):
    src = _cloud(dtype=dtype)
    pointio.write_points(tmp_path / "c.npy", src)
    raw = np.load(tmp_path / "c.npy")
    assert raw.shape == (len(src), 6) and raw.dtype == np.dtype(dtype)
    back = pointio.read_points(tmp_path / "c.npy")
    np.testing.assert_array_equal(back.points, src.points)
    np.testing.assert_array_equal(back.normals.astype(np.float32), src.normals)


def test_npy_variants(tmp_path):
    np.save(tmp_path / "p3.npy", np.arange(12, dtype=np.float32).reshape(4, 3))
    c = pointio.read_points(tmp_path / "p3.npy")
    assert c.points.dtype == np.float32 and c.normals is None
    np.save(tmp_path / "ints.npy", np.arange(12).reshape(4, 3))
    assert pointio.read_points(tmp_path / "ints.npy").points.dtype == np.float64
    rec = np.zeros(3, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("nx", "f4"), ("ny", "f4"),
                             ("nz", "f4"), ("red", "u1")])
    rec["x"] = [1, 2, 3]
    rec["red"] = [9, 8, 7]
    np.save(tmp_path / "rec.npy", rec)
    c = pointio.read_points(tmp_path / "rec.npy")
    np.testing.assert_array_equal(c.points[:, 0], [1, 2, 3])
    np.testing.assert_array_equal(c.extra["red"], [9, 8, 7])
    np.save(tmp_path / "flat.npy", np.zeros(5))
    with pytest.raises(InputError, match=r"flat.npy: expected an \(N, 3\)"):
        pointio.read_points(tmp_path / "flat.npy")
    (tmp_path / "junk.npy").write_bytes(b"not numpy at all")
    with pytest.raises(InputError, match="junk.npy: not a readable"):
        pointio.read_points(tmp_path / "junk.npy")


def test_points_are_validated_by_the_engine():
    """One validator (core.infer.validate_points) checks clouds from every file format."""
    from cljn_addon.core.infer import validate_points

    with pytest.raises(InputError, match="empty"):
        validate_points(np.zeros((0, 3)))
    pts = np.random.default_rng(0).random((5, 3))
    pts[2, 1] = np.nan
    pts[4, 0] = np.inf
    with pytest.raises(InputError, match=r"2 point\(s\) have NaN.*row 2"):
        validate_points(pts)
    assert validate_points(np.random.default_rng(1).random((4, 3)).astype(np.float32)).dtype == np.float64


def test_read_points_dispatch_errors(tmp_path):
    with pytest.raises(InputError, match="file not found"):
        pointio.read_points(tmp_path / "missing.ply")
    with pytest.raises(InputError, match="unsupported point-cloud format '.obj'"):
        pointio.read_points(tmp_path / "x.obj")
    with pytest.raises(InputError, match="unsupported output format"):
        pointio.write_points(tmp_path / "x.e57", _cloud())


def test_atomic_write_leaves_target_alone_on_error(tmp_path):
    target = tmp_path / "keep.ply"
    target.write_bytes(b"original")
    bad = _cloud(n=5)
    bad.extra["oops"] = np.zeros(3)                    # wrong length: the writer fails
    with pytest.raises(ValueError):
        pointio.write_ply(target, bad)
    assert target.read_bytes() == b"original"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keep.ply"]
