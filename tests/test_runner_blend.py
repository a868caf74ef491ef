"""Headless runner on .blend scenes (batch scene cleanup) and --preview.

Every bpy step runs in a subprocess (the bpy wheel, or whatever `import bpy` finds), so these
tests never change the bpy state of the pytest process. Skipped where bpy is not installed.
"""
import hashlib
import importlib.util
import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from cljn_addon.core.formats import points as pointio
from cljn_addon.core.formats.points import PointCloud

pytestmark = pytest.mark.skipif(importlib.util.find_spec("bpy") is None,
                                reason="needs the bpy module (pip install bpy==5.0.1)")

ROOT = Path(__file__).resolve().parents[1]
RUN = ROOT / "standalone" / "run.py"
N = 1500

MAKE_SCENE = textwrap.dedent("""
    import sys
    import numpy as np
    import bpy
    sys.path.insert(0, {root!r})
    from cljn_addon.core.evaluation import shapes

    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    if {clouds}:
        for i, (name, shape) in enumerate([("CloudA", "sphere"), ("CloudB", "torus")]):
            noisy, _, _ = shapes.sample_shape(shape, {n}, noise=0.01, seed=i)
            mesh = bpy.data.meshes.new(name)
            mesh.vertices.add(len(noisy))
            mesh.vertices.foreach_set("co", noisy.astype(np.float32).ravel())
            mesh.update()
            obj = bpy.data.objects.new(name, mesh)
            scene.collection.objects.link(obj)
            obj.location = (3.0 * i, 1.0, 0.5)
            obj.rotation_euler = (0.3, 0.0, 0.7 * i)
            obj.scale = (2.0, 2.0, 2.0)
    bpy.ops.mesh.primitive_uv_sphere_add(segments=16, ring_count=8, location=(0, -3, 0))
    bpy.context.active_object.name = "Ball"
    bpy.ops.wm.save_as_mainfile(filepath={path!r})
""")

DUMP = textwrap.dedent("""
    import json, sys
    import numpy as np
    import bpy
    spec = json.loads(sys.argv[-1])
    out = {"blends": {}, "images": {}}
    for path in spec["blends"]:
        bpy.ops.wm.open_mainfile(filepath=path, load_ui=False)
        objs = {}
        for obj in bpy.data.objects:
            entry = {"type": obj.type}
            if obj.type == "MESH":
                me = obj.data
                co = np.empty(len(me.vertices) * 3, np.float32)
                me.vertices.foreach_get("co", co)
                entry["co"] = co.tolist()
                entry["faces"] = len(me.polygons)
                entry["attributes"] = sorted(a.name for a in me.attributes)
                for name in ("cljn_original_position", "cljn_normal"):
                    if name in me.attributes:
                        v = np.empty(len(me.vertices) * 3, np.float32)
                        me.attributes[name].data.foreach_get("vector", v)
                        entry[name] = v.tolist()
                for name in ("red", "cljn_outlier"):
                    if name in me.attributes:
                        attr = me.attributes[name]
                        entry[name] = [d.value for d in attr.data]
            objs[obj.name] = entry
        out["blends"][path] = objs
    for path in spec["images"]:
        img = bpy.data.images.load(path)
        px = np.empty(img.size[0] * img.size[1] * img.channels, np.float32)
        img.pixels.foreach_get(px)
        rgb = px.reshape(-1, img.channels)[:, :3]
        background = np.median(rgb, axis=0)
        differs = np.abs(rgb - background).max(axis=1) > 0.05
        out["images"][path] = {"size": list(img.size), "std": float(rgb.std()),
                                "foreground": float(differs.mean()),
                                "colours": int(len(np.unique((rgb * 255).round(), axis=0)))}
    with open(spec["out"], "w") as fh:
        json.dump(out, fh)
""")


def _python(code, *args, timeout=240):
    proc = subprocess.run([sys.executable, "-c", code, *map(str, args)], capture_output=True,
                          text=True, timeout=timeout, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return proc


def cli(*args, timeout=300):
    env = dict(os.environ, PYTHONDONTWRITEBYTECODE="1", OMP_NUM_THREADS="1")
    return subprocess.run([sys.executable, str(RUN), *map(str, args)], capture_output=True,
                          text=True, cwd=ROOT, env=env, timeout=timeout)


def dump(tmp_path, blends=(), images=()):
    out = tmp_path / "dump.json"
    spec = {"blends": [str(p) for p in blends], "images": [str(p) for p in images], "out": str(out)}
    _python(DUMP, json.dumps(spec))
    return json.loads(out.read_text())


def sha(path):
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    folder = tmp_path_factory.mktemp("scenes")
    scene, plain = folder / "scene.blend", folder / "nocloud.blend"
    _python(MAKE_SCENE.format(root=str(ROOT), clouds=True, n=N, path=str(scene)))
    _python(MAKE_SCENE.format(root=str(ROOT), clouds=False, n=N, path=str(plain)))
    return scene, plain


def _args(model_path):
    return ["--model", model_path, "--iterations", "1", "--no-progress", "--threads", "1"]


def test_blend_batch_cleanup_with_report_and_preview(tmp_path, model_path, scenes):
    scene, _ = scenes
    before = sha(scene)
    out_dir, report, preview = tmp_path / "out", tmp_path / "report.json", tmp_path / "look.png"
    proc = cli("denoise", scene, "--out-dir", out_dir, "--report", report, "--preview", preview,
               *_args(model_path))
    assert proc.returncode == 0, proc.stderr
    assert sha(scene) == before                                   # the input is untouched
    out = out_dir / "scene.blend"
    assert sorted(p.name for p in out_dir.iterdir()) == ["scene.blend"]  # no temp, no .blend1
    for name in ("CloudA", "CloudB"):
        line = next(ln for ln in proc.stdout.splitlines() if f"[{name}]" in ln)
        assert f"{N} points" in line and "outliers flagged" in line
        assert "mean displacement" in line and line.rstrip().endswith(" s")
    data = json.loads(report.read_text())
    entry = data["inputs"][0]
    assert data["exit_code"] == 0 and entry["status"] == "ok" and entry["output"] == str(out)
    assert [o["name"] for o in entry["objects"]] == ["CloudA", "CloudB"]
    assert entry["points"] == 2 * N
    for obj in entry["objects"]:
        assert obj["points"] == N and obj["seconds"] > 0 and obj["mean_displacement"] > 0
    pngs = [tmp_path / "look_scene_CloudA.png", tmp_path / "look_scene_CloudB.png"]
    assert sorted(entry["previews"]) == sorted(map(str, pngs))

    info = dump(tmp_path, blends=[scene, out], images=pngs)
    src, res = info["blends"][str(scene)], info["blends"][str(out)]
    assert sorted(res) == sorted(src) == ["Ball", "CloudA", "CloudB"]
    # The ordinary mesh is untouched.
    assert res["Ball"]["co"] == src["Ball"]["co"] and res["Ball"]["faces"] == src["Ball"]["faces"]
    assert res["Ball"]["attributes"] == src["Ball"]["attributes"]
    for name in ("CloudA", "CloudB"):
        assert "cljn_normal" in res[name]["attributes"] and "cljn_outlier" in res[name]["attributes"]
        assert "cljn_normal" not in src[name]["attributes"]
        assert res[name]["co"] != src[name]["co"]                   # positions were filtered
        assert res[name]["cljn_original_position"] == src[name]["co"]
        normals = np.array(res[name]["cljn_normal"]).reshape(-1, 3)
        np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-4)
    for png in pngs:
        stats = info["images"][str(png)]
        assert stats["size"] == [960, 480]
        assert stats["std"] > 0.05 and stats["foreground"] > 0.02 and stats["colours"] > 50, stats


def test_blend_in_place_normals_on_named_object(tmp_path, model_path, scenes):
    scene = tmp_path / "work.blend"
    scene.write_bytes(scenes[0].read_bytes())
    original = sha(scene)
    proc = cli("normals", scene, "--in-place", "--objects", "CloudB", *_args(model_path))
    assert proc.returncode == 0, proc.stderr
    assert sha(tmp_path / "work.blend1") == original                  # the backup
    assert sha(scene) != original
    info = dump(tmp_path, blends=[tmp_path / "work.blend1", scene])
    src, res = info["blends"][str(tmp_path / "work.blend1")], info["blends"][str(scene)]
    assert res["CloudA"] == src["CloudA"]                            # not named: untouched
    assert res["Ball"] == src["Ball"]
    assert res["CloudB"]["co"] == src["CloudB"]["co"]                # normals only: bit-identical
    assert "cljn_normal" in res["CloudB"]["attributes"]
    assert "[CloudA]" not in proc.stdout and "[CloudB]" in proc.stdout


def test_blend_errors(tmp_path, model_path, scenes):
    scene, plain = scenes
    garbage = tmp_path / "garbage.blend"
    garbage.write_bytes(b"BLENDER-v999 this is not a real file")
    good = tmp_path / "good.npy"
    from cljn_addon.core.evaluation import shapes

    np.save(good, shapes.sample_shape("sphere", N, noise=0.01)[0])
    out_dir = tmp_path / "out"
    proc = cli("denoise", plain, garbage, good, "--out-dir", out_dir, *_args(model_path))
    assert proc.returncode == 3, proc.stderr
    assert "Traceback" not in proc.stderr
    errors = [ln for ln in proc.stderr.splitlines() if ln.startswith("error: ")]
    assert len(errors) == 2, proc.stderr
    assert "nocloud.blend" in errors[0] and "no point-cloud objects" in errors[0]
    assert "garbage.blend" in errors[1] and "not a readable .blend" in errors[1]
    assert sorted(p.name for p in out_dir.iterdir()) == ["good.npy"]

    proc = cli("denoise", scene, "--objects", "Nope", "-o", tmp_path / "x.blend", *_args(model_path))
    assert proc.returncode == 2
    errors = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(errors) == 1 and "no object named 'Nope'" in errors[0] and "CloudA" in errors[0]
    assert not (tmp_path / "x.blend").exists()
    proc = cli("denoise", scene, "--objects", "Ball", "-o", tmp_path / "x.blend", *_args(model_path))
    assert proc.returncode == 2 and "'Ball' is a mesh with faces" in proc.stderr
    assert not (tmp_path / "x.blend").exists()


def test_ply_to_blend_and_preview_by_displacement(tmp_path, model_path):
    from cljn_addon.core.evaluation import shapes

    pts = shapes.sample_shape("box", N, noise=0.01, seed=2)[0].astype(np.float32)
    red = np.arange(N, dtype=np.uint8)
    src = tmp_path / "box.ply"
    pointio.write_ply(src, PointCloud(pts, None, {"red": red}), fmt="ascii")
    out, png = tmp_path / "box.blend", tmp_path / "box.png"
    proc = cli("normals", src, "-o", out, "--preview", png, "--preview-color", "displacement",
               *_args(model_path))
    assert proc.returncode == 0, proc.stderr
    assert f"preview: {png}" in proc.stdout
    info = dump(tmp_path, blends=[out], images=[png])
    obj = info["blends"][str(out)]["box"]
    assert obj["faces"] == 0
    np.testing.assert_array_equal(np.array(obj["co"], np.float32).reshape(-1, 3), pts)
    assert obj["red"] == red.astype(int).tolist()
    assert "cljn_normal" in obj["attributes"]
    stats = info["images"][str(png)]
    assert stats["std"] > 0.05 and stats["foreground"] > 0.02, stats
