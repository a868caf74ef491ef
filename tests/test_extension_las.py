"""File > Import/Export > LAS/LAZ through the extension installed from its zip (bpy wheel, headless)."""
from __future__ import annotations

import sys as _sys
from pathlib import Path as _Path

import pytest

_sys.path.insert(0, str(_Path(__file__).resolve().parent))   # blender_helpers, any import mode

pytest.importorskip("laspy")

from blender_helpers import blender_env, in_blender  # noqa: E402, F401 (fixture)

OFFSET = (500_000.0, 5_000_000.0, 100.0)


def _make_las(path, n=1500, fmt=7, seed=0):
    """A noisy 4 x 3 x 2 m box 500 km from the origin at 1 mm, with RGB, GPS time and extra bytes."""
    import laspy
    import numpy as np

    rng = np.random.default_rng(seed)
    centre = rng.normal(size=(n, 3))
    box = centre / np.abs(centre).max(axis=1, keepdims=True) * [2.0, 1.5, 1.0]
    box += rng.normal(scale=0.02, size=box.shape)
    header = laspy.LasHeader(version="1.4", point_format=fmt)
    header.scales = np.full(3, 0.001)
    header.offsets = np.array(OFFSET)
    header.add_extra_dims([laspy.ExtraBytesParams(name="range", type=np.float64)])
    header.vlrs.append(laspy.vlrs.known.WktCoordinateSystemVlr('PROJCS["WGS 84 / UTM zone 33N"]'))
    data = laspy.LasData(header)
    data.x, data.y, data.z = (box + OFFSET).T
    data.intensity = rng.integers(0, 65535, n)
    data.classification = rng.integers(0, 13, n)
    data.gps_time = 3.0e8 + rng.random(n)
    data.range = rng.random(n) * 40
    if "red" in data.point_format.dimension_names:
        data.red, data.green, data.blue = rng.integers(0, 65535, (3, n))
    data.write(str(path))
    return path


@in_blender(timeout=400)
def test_import_denoise_export_keeps_fields_and_georeferencing(bx):
    import bpy
    import laspy
    import numpy as np

    las_io = __import__(bx.package + ".blender.las_io", fromlist=["las_io"])
    for as_point_cloud, fmt in ((True, 7), (False, 6)):
        bx.clear_scene()
        src = _make_las(bx.tmp / f"scan{fmt}.laz", fmt=fmt)
        assert bpy.ops.cljn.import_las(filepath=str(src), as_point_cloud=as_point_cloud) == {"FINISHED"}
        obj = bpy.context.active_object
        assert obj.type == (bx.point_cloud_kind if as_point_cloud else "MESH"), obj.type
        a = laspy.read(str(src))
        # Recentred: small float32 coordinates, the offset kept on the object.
        local = bx.local_points(obj)
        assert np.abs(local).max() < 5.0
        true = local.astype(np.float64) + np.asarray(obj[las_io.ORIGIN])
        assert np.abs(true - np.stack([a.x, a.y, a.z], axis=1)).max() < 1e-4
        assert np.array_equal(bx.attribute(obj, "intensity"), np.asarray(a.intensity))
        assert np.array_equal(bx.attribute(obj, "classification"), np.asarray(a.classification))
        if fmt == 7:
            colour = obj.data.attributes.get(las_io.COLOR)
            assert colour is not None and colour.data_type == "FLOAT_COLOR", colour
            rgba = np.empty(len(colour.data) * 4, np.float32)
            colour.data.foreach_get("color", rgba)
            rgb = rgba.reshape(-1, 4)[:, :3].astype(np.float64) * 65535
            assert np.abs(rgb - np.stack([a.red, a.green, a.blue], axis=1)).max() < 0.01
            assert obj.active_material is not None and "Color" in [
                nd.attribute_name for nd in obj.active_material.node_tree.nodes if nd.type == "ATTRIBUTE"]

        # Export untouched: byte-identical records (the container may differ only in the header).
        same = bx.tmp / f"same{fmt}.las"
        assert bpy.ops.cljn.export_las(filepath=str(same)) == {"FINISHED"}
        b = laspy.read(str(same))
        for f in a.points.array.dtype.names:
            assert np.array_equal(a.points.array[f], b.points.array[f]), f
        assert np.array_equal(b.header.offsets, a.header.offsets) and np.array_equal(b.header.scales, a.header.scales)
        assert any(isinstance(v, laspy.vlrs.known.WktCoordinateSystemVlr) for v in b.header.vlrs)

        # Denoise Points, then export: moved positions in true coordinates, normals, every field.
        bx.use_model_file()
        bx.settings.auto_iterations = False
        bx.settings.iterations = 1
        bx.select(obj)
        assert bpy.ops.cljn.denoise_points() == {"FINISHED"}
        out = bx.tmp / f"clean{fmt}.laz"
        assert bpy.ops.cljn.export_las(filepath=str(out)) == {"FINISHED"}
        c = laspy.read(str(out))
        for f in a.points.array.dtype.names:
            if f not in "XYZ":
                assert np.array_equal(a.points.array[f], c.points.array[f]), f
        moved = np.stack([c.x, c.y, c.z], axis=1)
        expect = bx.world_points(obj).astype(np.float64) + np.asarray(obj[las_io.ORIGIN])
        assert np.abs(moved - expect).max() < 0.0006
        # The file's scale or a power of ten finer (moves too small for its grid); Keep File Scale: its own.
        assert any(np.allclose(c.header.scales, a.header.scales / 10 ** k) for k in range(4)), c.header.scales
        kept = bx.tmp / f"kept{fmt}.laz"
        assert bpy.ops.cljn.export_las(filepath=str(kept), keep_scale=True) == {"FINISHED"}
        assert np.array_equal(laspy.read(str(kept)).header.scales, a.header.scales)
        assert not np.array_equal(a.points.array["Z"], c.points.array["Z"])
        normals = np.stack([c["NormalX"], c["NormalY"], c["NormalZ"]], axis=1)
        assert np.allclose(normals, bx.attribute(obj, "cljn_normal"), atol=1e-5)
        assert np.array_equal(np.asarray(c["cljn_outlier"]).astype(bool), bx.attribute(obj, "cljn_outlier"))
        # Outliers as Noise (Class 7): flagged points (two marked here) read 7, the rest as imported.
        flags = obj.data.attributes["cljn_outlier"]
        marked = np.zeros(len(flags.data), bool)
        flags.data.foreach_get("value", marked)
        marked[[0, 5]] = True
        flags.data.foreach_set("value", marked)
        noise = bx.tmp / f"noise{fmt}.laz"
        assert bpy.ops.cljn.export_las(filepath=str(noise), classify_outliers=True) == {"FINISHED"}
        classes = np.asarray(laspy.read(str(noise)).classification)
        assert np.all(classes[marked] == 7)
        assert np.array_equal(classes[~marked], np.asarray(a.classification)[~marked])

        if fmt == 6:
            # A colour painted on a cloud whose file has no RGB: exported with a warning, not lost silently.
            obj.data.color_attributes.new(las_io.COLOR, "FLOAT_COLOR", "POINT")
            warnings = las_io.export_las(obj, bx.tmp / "painted.las")
            assert any("has no RGB" in w for w in warnings), warnings
            obj.data.color_attributes.remove(obj.data.color_attributes[las_io.COLOR])

        # Restore Original, export again: the exact input integers come back.
        assert bpy.ops.cljn.restore_original() == {"FINISHED"}
        back = bx.tmp / f"back{fmt}.las"
        assert bpy.ops.cljn.export_las(filepath=str(back)) == {"FINISHED"}
        d = laspy.read(str(back))
        for axis in "XYZ":
            assert np.array_equal(a.points.array[axis], d.points.array[axis]), axis


@in_blender
def test_export_of_a_plain_cloud_and_bad_files(bx):
    import bpy
    import laspy
    import numpy as np

    bx.clear_scene()
    rng = np.random.default_rng(1)
    pts = rng.normal(size=(500, 3))
    obj = bx.make_cloud(pts, "Plain")
    bx.select(obj)
    out = bx.tmp / "plain.las"
    assert bpy.ops.cljn.export_las(filepath=str(out)) == {"FINISHED"}
    c = laspy.read(str(out))
    assert str(c.header.version) == "1.4" and len(c.points) == 500
    assert np.abs(np.stack([c.x, c.y, c.z], axis=1) - pts.astype(np.float32)).max() < 1e-6

    # Errors are reported (a RuntimeError from an operator called from Python), never a traceback
    # of ours, and leave nothing behind.
    with pytest.raises(RuntimeError, match="must end in .las or .laz"):
        bpy.ops.cljn.export_las(filepath=str(bx.tmp / "plain.ply"))
    assert not (bx.tmp / "plain.ply").exists()
    bad = bx.tmp / "broken.laz"
    bad.write_bytes(b"LASF" + bytes(300))
    before = set(bpy.data.objects)
    with pytest.raises(RuntimeError, match="broken.laz: not a readable LAS/LAZ file"):
        bpy.ops.cljn.import_las(filepath=str(bad))
    assert set(bpy.data.objects) == before, "a failed import left an object behind"
