"""The extension's operators on real Blender objects (bpy wheel, headless, installed from the zip).

Mechanics tests use an untrained tiny network saved to a temporary file and chosen in the
panel settings (fast); the accuracy test needs the shipped trained model.
"""
from __future__ import annotations

import sys as _sys
from pathlib import Path as _Path

_sys.path.insert(0, str(_Path(__file__).resolve().parent))   # blender_helpers, any import mode

from blender_helpers import blender_env, in_blender  # noqa: F401 (fixture)

# A transform with rotation, non-uniform scale and translation: world-space handling must hold.
MATRIX = [[0.0, -2.0, 0.0, 1.5],
          [1.5, 0.0, 0.0, -0.5],
          [0.0, 0.0, 1.0, 3.0],
          [0.0, 0.0, 0.0, 1.0]]


@in_blender(needs_shipped_model=True, timeout=400)
def test_denoise_points_with_the_shipped_model(bx):
    """Chamfer to the clean shape drops, normals beat PCA, original kept, restore exact."""
    import bpy
    import numpy as np

    metrics = __import__(bx.package + ".core.evaluation.metrics", fromlist=["metrics"])
    shapes = __import__(bx.package + ".core.evaluation.shapes", fromlist=["shapes"])
    baselines = __import__(bx.package + ".core.evaluation.baselines", fromlist=["baselines"])
    bx.clear_scene()
    # A sharp CAD shape; the shipped model does not yet beat tuned PCA on every shape
    # (see its MODEL_CARD.md), so this checks the glue on one where it does.
    noisy, clean, clean_normals = shapes.sample_shape("octahedron", 6000, noise=0.01, seed=3)
    m = np.array(MATRIX)
    local = np.linalg.solve(m[:3, :3], (noisy - m[:3, 3]).T).T      # world = the noisy sample
    obj = bx.make_cloud(local, "Scan", matrix=m)
    bx.select(obj)
    before_local = bx.local_points(obj)
    world_in = bx.world_points(obj)
    bx.settings.model_source = "DEFAULT"
    bx.settings.auto_iterations = False
    bx.settings.iterations = 4
    assert bpy.ops.cljn.denoise_points() == {"FINISHED"}

    world_out = bx.world_points(obj)
    cd_in, cd_out = metrics.chamfer(world_in, clean), metrics.chamfer(world_out, clean)
    print(f"chamfer noisy {cd_in:.3e} -> denoised {cd_out:.3e}")
    assert cd_out < 0.8 * cd_in, (cd_in, cd_out)

    normals = bx.world_normals(obj)
    assert np.allclose(np.linalg.norm(bx.attribute(obj, bx.normal_attr), axis=1), 1.0, atol=1e-5)
    _, near = __import__("scipy.spatial", fromlist=["cKDTree"]).cKDTree(clean).query(world_in)
    truth = clean_normals[near]
    ours = metrics.msae(normals, truth)
    pca = min(metrics.msae(baselines.pca_normals(world_in, k), truth) for k in (20, 40, 60))
    print(f"normal MSAE ours {ours:.4f}, best PCA {pca:.4f}")
    assert ours < pca, (ours, pca)
    # Outward orientation: on this convex shape the normals point away from the centre.
    centre = clean.mean(axis=0)
    assert np.mean(np.einsum("ij,ij->i", normals, world_out - centre) > 0) > 0.95

    assert np.array_equal(bx.attribute(obj, "cljn_original_position"), before_local)
    assert bpy.ops.cljn.restore_original() == {"FINISHED"}
    assert np.array_equal(bx.local_points(obj), before_local)


@in_blender
def test_denoise_writes_every_attribute_in_object_space(bx):
    """A PointCloud object with a transform: positions, normals and extras written consistently."""
    import bpy
    import numpy as np

    shapes = __import__(bx.package + ".core.evaluation.shapes", fromlist=["shapes"])
    bx.clear_scene()
    noisy, _, _ = shapes.sample_shape("box", 1500, noise=0.01, seed=1)
    obj = bx.make_cloud(noisy, "Box", kind=bx.point_cloud_kind, matrix=MATRIX)
    bx.select(obj)
    bx.use_model_file()
    bx.settings.auto_iterations = False
    bx.settings.iterations = 1
    before = bx.local_points(obj)
    world_before = bx.world_points(obj)
    assert bpy.ops.cljn.denoise_points() == {"FINISHED"}

    after = bx.local_points(obj)
    assert not np.array_equal(after, before), "positions did not change"
    names = bx.attribute_names(obj)
    for name in (bx.normal_attr, "cljn_normal", "cljn_original_position", "cljn_displacement", "cljn_outlier"):
        assert name in names, (name, names)
    assert obj.data.attributes["cljn_outlier"].data_type == "BOOLEAN"
    assert np.array_equal(bx.attribute(obj, "cljn_original_position"), before)
    normals = bx.attribute(obj, bx.normal_attr)
    assert np.allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-5)
    assert np.array_equal(normals, bx.attribute(obj, "cljn_normal"))
    moved = np.linalg.norm(bx.world_points(obj) - world_before, axis=1)
    assert np.allclose(bx.attribute(obj, "cljn_displacement"), moved, atol=1e-4 * (1 + moved.max()))
    assert moved.max() > 0

    # A second run keeps the first original; after save and reload, Restore brings back exactly that.
    assert bpy.ops.cljn.denoise_points() == {"FINISHED"}
    assert np.array_equal(bx.attribute(obj, "cljn_original_position"), before)
    blend = bx.tmp / "denoised.blend"
    assert bpy.ops.wm.save_as_mainfile(filepath=str(blend)) == {"FINISHED"}
    assert bpy.ops.wm.open_mainfile(filepath=str(blend), load_ui=False) == {"FINISHED"}
    obj = bpy.data.objects["Box"]
    assert obj.type == bx.point_cloud_kind and not np.array_equal(bx.local_points(obj), before)
    bx.select(obj)
    assert bpy.ops.cljn.restore_original() == {"FINISHED"}
    assert np.array_equal(bx.local_points(obj), before)


@in_blender
def test_estimate_normals_leaves_positions_bit_identical(bx):
    import bpy
    import numpy as np

    shapes = __import__(bx.package + ".core.evaluation.shapes", fromlist=["shapes"])
    bx.clear_scene()
    noisy, _, _ = shapes.sample_shape("torus", 1500, noise=0.005, seed=2)
    obj = bx.make_cloud(noisy, "Torus", matrix=MATRIX)
    bx.select(obj)
    bx.use_model_file()
    before = bx.local_points(obj)
    assert bpy.ops.cljn.estimate_normals() == {"FINISHED"}
    after = bx.local_points(obj)
    assert before.tobytes() == after.tobytes(), "Estimate Normals moved points"
    normals = bx.attribute(obj, bx.normal_attr)
    assert np.allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-5)
    # Blender 5.0 takes the custom_normal POINT attribute as the vertex normals (4.x: not).
    if bpy.app.version >= (5, 0, 0):
        vertex_normals = np.empty(len(after) * 3, np.float32)
        obj.data.vertex_normals.foreach_get("vector", vertex_normals)
        assert np.allclose(vertex_normals.reshape(-1, 3), normals, atol=1e-6)
    assert not bx.attribute(obj, "cljn_displacement").any()


@in_blender
def test_bad_selections_report_and_change_nothing(bx):
    import bpy
    import numpy as np
    import pytest

    bx.clear_scene()
    bx.use_model_file()
    rng = np.random.default_rng(0)

    def snapshot(obj):
        data = {"names": bx.attribute_names(obj)}
        if obj.type in ("MESH", "POINTCLOUD"):
            data["points"] = bx.local_points(obj).tobytes()
        return data

    bpy.ops.mesh.primitive_ico_sphere_add(subdivisions=2)
    cube = bpy.context.active_object
    cube.name = "Ico"
    cloud = bx.make_cloud(rng.normal(size=(300, 3)), "Cloud")
    tiny = bx.make_cloud(rng.normal(size=(5, 3)), "Tiny")
    cam_data = bpy.data.cameras.new("Cam")
    camera = bpy.data.objects.new("Cam", cam_data)
    bpy.context.scene.collection.objects.link(camera)
    objects = (cube, cloud, tiny)
    state = {o.name: snapshot(o) for o in objects}

    def unchanged():
        for o in objects:
            assert snapshot(o) == state[o.name], f"{o.name} changed"

    cases = [
        ((), "Nothing selected"),
        ((cube,), "'Ico' is a mesh with faces"),
        ((camera,), "'Cam' is a camera object, not a point cloud"),
        ((tiny,), r"'Tiny' has too few points \(5\)"),
    ]
    for op in (bpy.ops.cljn.denoise_points, bpy.ops.cljn.estimate_normals):
        for selection, message in cases:
            bx.select(*selection)
            with pytest.raises(RuntimeError, match=message):
                op()
            unchanged()

    bx.select(cloud)
    bx.settings.model_path = str(bx.tmp / "missing.safetensors")
    with pytest.raises(RuntimeError, match="Model file not found"):
        bpy.ops.cljn.denoise_points()
    unchanged()

    # Weights of one network with the config of another: refused with the mismatch named.
    import shutil
    bad = bx.tmp / "mismatch.safetensors"
    shutil.copy(bx.model_file("tiny"), bad)
    small = bx.core.build_model("small").config.to_json()
    bad.with_suffix(".json").write_text(small)
    bx.settings.model_path = str(bad)
    with pytest.raises(RuntimeError, match="Model file mismatch"):
        bpy.ops.cljn.denoise_points()
    unchanged()

    bx.settings.model_source = "FILE"
    bx.settings.model_path = ""
    with pytest.raises(RuntimeError, match="no file is chosen"):
        bpy.ops.cljn.denoise_points()

    bx.settings.orientation = "CAMERA"
    bpy.context.scene.camera = None
    bx.use_model_file()
    with pytest.raises(RuntimeError, match="needs an active scene camera"):
        bpy.ops.cljn.denoise_points()
    unchanged()
    bx.settings.orientation = "OUTWARD"

    bx.select(cloud, cube)
    with pytest.raises(RuntimeError, match="nothing to restore"):
        bpy.ops.cljn.restore_original()
    unchanged()

    # Mixed selection: the cloud is processed, the cube is skipped and stays as it was.
    bx.settings.auto_iterations = False
    bx.settings.iterations = 1
    assert bpy.ops.cljn.denoise_points() == {"FINISHED"}
    assert snapshot(cube) == state["Ico"]
    assert "cljn_normal" in bx.attribute_names(cloud)

    # Opting in to mesh vertices filters the mesh's vertices (its faces follow).
    bx.select(cube)
    bx.settings.use_mesh_vertices = True
    faces = len(cube.data.polygons)
    bx.settings.patch_radius = 40.0          # 42 sparse vertices: a wide neighbourhood
    assert bpy.ops.cljn.denoise_points() == {"FINISHED"}
    assert len(cube.data.polygons) == faces
    assert bx.local_points(cube).tobytes() != state["Ico"]["points"]
    bx.settings.use_mesh_vertices = False

    # Edit mode: the operators do not run (poll), with a reason.
    bx.select(cloud)
    bpy.ops.object.mode_set(mode="EDIT")
    assert not bpy.ops.cljn.denoise_points.poll()
    bpy.ops.object.mode_set(mode="OBJECT")
    assert bpy.ops.cljn.denoise_points.poll()


@in_blender
def test_ply_export_carries_our_normals_and_ply_import_then_denoise(bx):
    import bpy
    import numpy as np

    shapes = __import__(bx.package + ".core.evaluation.shapes", fromlist=["shapes"])
    bx.clear_scene()
    bx.use_model_file()
    bx.settings.auto_iterations = False
    bx.settings.iterations = 1
    noisy, _, normals_true = shapes.sample_shape("sphere", 1200, noise=0.005, seed=4)
    obj = bx.make_cloud(noisy, "Sphere")
    bx.select(obj)
    assert bpy.ops.cljn.denoise_points() == {"FINISHED"}

    out = bx.tmp / "denoised.ply"
    assert bpy.ops.wm.ply_export(filepath=str(out), export_selected_objects=True, export_normals=True,
                                 ascii_format=True) == {"FINISHED"}
    header, rows = _read_ascii_ply(out)
    assert {"x", "y", "z", "nx", "ny", "nz"} <= set(header), header
    cols = [header.index(c) for c in ("x", "y", "z", "nx", "ny", "nz")]
    table = rows[:, cols]
    assert np.allclose(table[:, :3], bx.local_points(obj), atol=1e-5)
    if bpy.app.version >= (5, 0, 0):      # 4.x's PLY export writes Blender's own vertex normals
        assert np.allclose(table[:, 3:], bx.attribute(obj, "cljn_normal"), atol=1e-5)

    # Scans from PLY, with and without normals: import, then Denoise Points.
    for with_normals in (False, True):
        path = bx.tmp / f"scan_{with_normals}.ply"
        _write_ascii_ply(path, noisy, normals_true if with_normals else None)
        bx.select()
        assert bpy.ops.wm.ply_import(filepath=str(path)) == {"FINISHED"}
        scan = bpy.context.selected_objects[0]
        assert scan.type == "MESH" and len(scan.data.vertices) == len(noisy) and not len(scan.data.polygons)
        names_before = set(bx.attribute_names(scan))
        before = bx.local_points(scan)
        assert bpy.ops.cljn.denoise_points() == {"FINISHED"}
        assert not np.array_equal(bx.local_points(scan), before)
        assert names_before <= set(bx.attribute_names(scan)), "an attribute of the scan was deleted"
        assert bx.normal_attr in bx.attribute_names(scan)
        if with_normals:
            assert np.allclose(bx.attribute(scan, "normal"), normals_true, atol=1e-5), "imported normals changed"


def _write_ascii_ply(path, points, normals=None):
    props = ["x", "y", "z"] + (["nx", "ny", "nz"] if normals is not None else [])
    lines = ["ply", "format ascii 1.0", f"element vertex {len(points)}"]
    lines += [f"property float {p}" for p in props] + ["end_header"]
    import numpy as np

    data = points if normals is None else np.hstack([points, normals])
    lines += [" ".join(f"{v:.7g}" for v in row) for row in data]
    path.write_text("\n".join(lines) + "\n")


def _read_ascii_ply(path):
    import numpy as np

    text = path.read_text().splitlines()
    end = text.index("end_header")
    header = [ln.split()[-1] for ln in text[:end] if ln.startswith("property")]
    count = next(int(ln.split()[-1]) for ln in text[:end] if ln.startswith("element vertex"))
    rows = np.array([[float(v) for v in ln.split()] for ln in text[end + 1:end + 1 + count]])
    return header, rows


@in_blender
def test_worker_job_cancel_leaves_object_unchanged(bx):
    """The modal operator's worker: Esc sets the cancel event; the engine stops, nothing is written."""
    import time

    import numpy as np
    import pytest

    shapes = __import__(bx.package + ".core.evaluation.shapes", fromlist=["shapes"])
    ops, pipeline, core = bx.operators, bx.pipeline, bx.core
    bx.clear_scene()
    noisy, _, _ = shapes.sample_shape("box", 3000, noise=0.01, seed=5)
    obj = bx.make_cloud(noisy, "Box")
    names, before = bx.attribute_names(obj), bx.local_points(obj)
    model = core.load_model(bx.model_file("tiny"))
    options = __import__(bx.package + ".core.options", fromlist=["options"]).DenoiseOptions(iterations=50)
    snapshots = [pipeline.snapshot(obj)]
    seen = []

    def work(progress, cancel):
        return pipeline.compute(snapshots, options, model, progress=progress, cancel=cancel)

    job = ops.BackgroundJob(work, "denoising")
    job.start()
    deadline = time.time() + 60
    while job.fraction == 0.0 and not job.done and time.time() < deadline:
        time.sleep(0.01)
    seen.append(job.fraction)
    job.cancel.set()
    while not job.done and time.time() < deadline:
        time.sleep(0.01)
    assert job.done and isinstance(job.error, core.Cancelled), (job.error, seen)
    assert "cancelling" in job.status_text()
    assert bx.attribute_names(obj) == names and np.array_equal(bx.local_points(obj), before)

    # The synchronous path of the same pipeline: cancel set before the run -> Cancelled, unchanged.
    import threading
    event = threading.Event()
    event.set()
    with pytest.raises(core.Cancelled):
        results = pipeline.compute([pipeline.snapshot(obj)], options.replace(iterations=1), model,
                                   cancel=event)
        pipeline.write_back(snapshots[0], results[0])
    assert bx.attribute_names(obj) == names and np.array_equal(bx.local_points(obj), before)


@in_blender
def test_solid_object_setting_reaches_the_engine(bx):
    """Solid Object: a thin plate, read thin-walled by default, runs as a solid (as --solid)."""
    import bpy

    shapes = __import__(bx.package + ".core.evaluation.shapes", fromlist=["shapes"])
    pipeline = bx.pipeline
    bx.clear_scene()
    noisy, _, _ = shapes.sample_shape("thin_plate", 8000, noise=0.006, seed=1)
    obj = bx.make_cloud(noisy, "Plate")
    bx.select(obj)
    bx.use_model_file("tiny")
    model = bx.core.load_model(bx.model_file("tiny"))
    read = {}
    for solid in (False, True):
        bx.settings.treat_as_solid = solid
        options = pipeline.options_from_settings(bpy.context, bx.settings)
        assert options.solid is solid
        read[solid] = pipeline.compute([pipeline.snapshot(obj)], options.replace(iterations=1), model)[0].thin_walled
    assert read == {False: True, True: False}, read


@in_blender(timeout=400)
def test_train_model_makes_the_result_the_active_model(bx):
    import os

    import bpy
    import numpy as np

    bx.clear_scene()
    bpy.ops.mesh.primitive_ico_sphere_add(subdivisions=3)
    sphere = bpy.context.active_object
    cloud = bx.make_cloud(np.random.default_rng(0).normal(size=(400, 3)), "Cloud")
    bx.select(sphere, cloud)            # the point cloud (no faces) is not a training mesh
    t0 = __import__("time").time()
    assert bpy.ops.cljn.train_model(preset="tiny") == {"FINISHED"}
    print(f"training took {__import__('time').time() - t0:.1f} s")
    assert bx.settings.model_source == "FILE"
    path = bx.settings.model_path
    assert os.path.isfile(path) and path.startswith(bpy.utils.extension_path_user(bx.package)), path
    model = bx.core.load_model(path)
    assert model.config.preset == "tiny"
    # The trained model is used by the next run.
    bx.select(cloud)
    bx.settings.auto_iterations = False
    bx.settings.iterations = 1
    assert bpy.ops.cljn.denoise_points() == {"FINISHED"}

    import pytest
    with pytest.raises(RuntimeError, match="needs clean meshes with faces"):
        bpy.ops.cljn.train_model(preset="tiny")


@in_blender
def test_modal_run_updates_progress_and_esc_cancels(bx):
    """The interactive path (invoke -> modal timer events -> write), driven by fake events.

    bpy in background mode has no event loop, so the window manager, workspace and events are
    stand-ins that record what the operator asks of them; the operator code is the real one.
    """
    import time
    from types import SimpleNamespace

    import bpy
    import numpy as np

    ops = bx.operators
    shapes = __import__(bx.package + ".core.evaluation.shapes", fromlist=["shapes"])
    bx.clear_scene()
    bx.use_model_file()
    noisy, _, _ = shapes.sample_shape("box", 3000, noise=0.01, seed=6)
    obj = bx.make_cloud(noisy, "Box")
    bx.select(obj)

    class WindowManager:
        def __init__(self):
            self.calls = []

        def __getattr__(self, name):
            return lambda *args, **kw: self.calls.append((name, args)) or name

    class Workspace:
        def __init__(self):
            self.texts = []

        def status_text_set(self, text):
            self.texts.append(text)

    class Denoise(ops._PointsOperator):      # the real operator code, outside RNA
        job_title = "denoising"

        def __init__(self):
            self.reports = []

        def report(self, kind, message):
            self.reports.append((next(iter(kind)), message))

    def context():
        return SimpleNamespace(window=object(), window_manager=WindowManager(), workspace=Workspace(),
                               scene=bpy.context.scene, selected_objects=[obj], mode="OBJECT",
                               preferences=bpy.context.preferences, screen=None)

    def drive(op, ctx, first_event=None):
        if first_event is not None:
            assert op.modal(ctx, SimpleNamespace(type=first_event, value="PRESS")) == {"RUNNING_MODAL"}
        deadline = time.time() + 120
        while time.time() < deadline:
            state = op.modal(ctx, SimpleNamespace(type="TIMER", value="NOTHING"))
            if state != {"PASS_THROUGH"}:
                return state
            assert not bpy.ops.cljn.denoise_points.poll(), "a second job could start"
            time.sleep(0.02)
        raise AssertionError("the job did not finish")

    ops._run_synchronously = lambda context: False
    computed = []                        # the engine's results, to check the report's wording against
    compute = ops.pipeline.compute

    def recording_compute(*args, **kwargs):
        results = compute(*args, **kwargs)
        computed.extend(results)
        return results

    ops.pipeline.compute = recording_compute
    before = bx.local_points(obj)
    ctx = context()
    op = Denoise()
    bx.settings.auto_iterations = False
    bx.settings.iterations = 2
    assert op.invoke(ctx, None) == {"RUNNING_MODAL"}
    assert ops._active_job is not None
    assert drive(op, ctx) == {"FINISHED"}, op.reports
    names = [c[0] for c in ctx.window_manager.calls]
    assert names[:3] == ["event_timer_add", "progress_begin", "modal_handler_add"], names
    assert "progress_update" in names and names[-2:] == ["event_timer_remove", "progress_end"], names
    assert any(t and "%" in t and "Esc to cancel" in t for t in ctx.workspace.texts), ctx.workspace.texts
    assert ctx.workspace.texts[-1] is None, "status text not cleared"
    assert ops._active_job is None and bpy.ops.cljn.denoise_points.poll()
    assert not np.array_equal(bx.local_points(obj), before)
    assert op.reports and op.reports[-1][0] == "INFO", op.reports
    steps = computed[-1].steps_taken()
    assert all(step in op.reports[-1][1] for step in steps), (steps, op.reports)
    print("steps reported:", steps)

    # Esc: cancelled, and the object is exactly as it was.
    snapshot = {n: bx.attribute(obj, n).tobytes() for n in bx.attribute_names(obj) if not n.startswith(".")}
    bx.settings.auto_iterations = False
    bx.settings.iterations = 50
    ctx, op = context(), Denoise()
    assert op.invoke(ctx, None) == {"RUNNING_MODAL"}
    assert drive(op, ctx, first_event="ESC") == {"CANCELLED"}
    assert any(t and "cancelling" in t for t in ctx.workspace.texts), ctx.workspace.texts
    assert op.reports[-1] == ("WARNING", "Denoising cancelled: nothing was changed"), op.reports
    assert {n: bx.attribute(obj, n).tobytes() for n in snapshot} == snapshot
    assert ops._active_job is None and ctx.workspace.texts[-1] is None
    ops.pipeline.compute = compute


@in_blender(timeout=400)
def test_operator_and_command_line_give_identical_results(bx):
    """The anchor of the one pipeline: the same cloud through the Denoise Points operator and
    through `standalone/run.py denoise` on a .blend gives identical positions and normals."""
    import os
    import subprocess
    import sys

    import bpy
    import numpy as np
    import torch
    from blender_helpers import REPO

    shapes = __import__(bx.package + ".core.evaluation.shapes", fromlist=["shapes"])
    bx.clear_scene()
    noisy, _, _ = shapes.sample_shape("octahedron", 3000, noise=0.01, seed=11)
    m = np.array(MATRIX)
    local = np.linalg.solve(m[:3, :3], (noisy - m[:3, 3]).T).T
    obj = bx.make_cloud(local, "Scan", matrix=m)
    bx.select(obj)
    bx.use_model_file("tiny")
    bx.settings.auto_iterations = False
    bx.settings.iterations = 2
    bx.settings.patch_radius = 5.0
    bx.settings.orientation = "OUTWARD"
    bx.settings.use_known_noise = True          # world units, as the command line's --noise
    bx.settings.noise_sigma = 0.004
    scene_in, scene_out = bx.tmp / "anchor_in.blend", bx.tmp / "anchor_out.blend"
    assert bpy.ops.wm.save_as_mainfile(filepath=str(scene_in), copy=True) == {"FINISHED"}

    assert bpy.ops.cljn.denoise_points() == {"FINISHED"}
    names = ("position", bx.normal_attr, "cljn_normal", "cljn_displacement", "cljn_outlier")
    by_operator = {n: bx.attribute(obj, n).copy() for n in names}
    assert not np.array_equal(by_operator["position"], local.astype(np.float32)), "nothing moved"
    moved = np.linalg.norm(bx.world_points(obj) - noisy, axis=1)
    assert moved.max() <= 3 * 0.004 * (1 + 1e-4), "the given scanner noise did not bound the motion"

    env = dict(os.environ, PYTHONDONTWRITEBYTECODE="1")
    proc = subprocess.run(
        [sys.executable, str(REPO / "standalone" / "run.py"), "denoise", str(scene_in), "-o", str(scene_out),
         "--model", bx.model_file("tiny"), "--iterations", "2", "--patch-radius", "5", "--orient", "outward",
         "--noise", "0.004",
         "--threads", str(torch.get_num_threads()), "--no-progress"],
        capture_output=True, text=True, env=env, cwd=REPO, timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr

    assert bpy.ops.wm.open_mainfile(filepath=str(scene_out), load_ui=False) == {"FINISHED"}
    by_cli = {n: bx.attribute(bpy.data.objects["Scan"], n) for n in names}
    for name in names:
        assert np.array_equal(by_operator[name], by_cli[name]), f"{name} differs between operator and CLI"
