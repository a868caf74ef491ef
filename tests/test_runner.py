"""Headless command line (standalone/run.py -> cljn_addon.cli) on point-cloud files.

An untrained network stands in for the shipped model: these tests check formats, argument
handling, exit codes, reports and file safety, not denoising quality. The .blend and
--preview paths are in test_runner_blend.py.
"""
import io
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from cljn_addon import cli as command_line
from cljn_addon.cli.progress import Progress
from cljn_addon.core.formats import points as pointio
from cljn_addon.core.formats.points import PointCloud

ROOT = Path(__file__).resolve().parents[1]
RUN = ROOT / "standalone" / "run.py"
N = 1200


def cli(*args, cwd=None, timeout=240):
    """Run standalone/run.py as a subprocess of this interpreter (the .venv python)."""
    env = dict(os.environ, PYTHONDONTWRITEBYTECODE="1", OMP_NUM_THREADS="1")
    return subprocess.run([sys.executable, str(RUN), *map(str, args)], capture_output=True,
                          text=True, cwd=cwd or ROOT, env=env, timeout=timeout)


@pytest.fixture(scope="module")
def torus():
    from cljn_addon.core.evaluation import shapes

    noisy, _clean, _normals = shapes.sample_shape("torus", N, noise=0.01, seed=3)
    return noisy


def _extras(n, seed=0):
    rng = np.random.default_rng(seed)
    return {"red": rng.integers(0, 256, n).astype(np.uint8),
            "green": rng.integers(0, 256, n).astype(np.uint8),
            "blue": rng.integers(0, 256, n).astype(np.uint8),
            "intensity": rng.random(n).astype(np.float32)}


def _base_args(model_path):
    return ["--model", model_path, "--iterations", "1", "--no-progress", "--threads", "1"]


# ----------------------------------------------------------------------------- argv

@pytest.mark.parametrize("argv,expected", [
    (["blender", "-b", "-P", "standalone/run.py", "--", "denoise", "a.ply", "-o", "b.ply"],
     ["denoise", "a.ply", "-o", "b.ply"]),
    (["blender", "--background", "--python", "run.py", "--", "normals", "--", "x.ply"],
     ["normals", "--", "x.ply"]),
    (["blender", "-b", "-P", "standalone/run.py"], []),
    (["standalone/run.py", "denoise", "a.ply", "-o", "b.ply"], ["denoise", "a.ply", "-o", "b.ply"]),
    (["run.py", "normals", "--", "-odd-name.ply"], ["normals", "--", "-odd-name.ply"]),
])
def test_argv_from_sys(argv, expected):
    assert command_line.argv_from_sys(argv) == expected


def test_argv_inside_blender_without_dash_dash():
    assert command_line.argv_from_sys(["/opt/blender/blender", "scene.blend"], in_blender=True) == []
    assert command_line.argv_from_sys(["/opt/blender/blender", "--", "bench"], in_blender=True) == ["bench"]


def test_blender_style_argv_end_to_end(tmp_path, model_path, torus):
    """sys.argv exactly as Blender leaves it for `blender -b -P standalone/run.py -- ...`."""
    src = tmp_path / "in.ply"
    pointio.write_ply(src, PointCloud(torus.astype(np.float32)))
    out = tmp_path / "out.ply"
    argv = ["blender", "-b", "-P", str(RUN), "--", "normals", str(src), "-o", str(out),
            *map(str, _base_args(model_path))]
    code = ("import runpy, sys; sys.argv = %r; runpy.run_path(%r, run_name='__main__')"
            % (argv, str(RUN)))
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          cwd=tmp_path, timeout=240)
    assert proc.returncode == 0, proc.stderr
    back = pointio.read_ply(out)
    np.testing.assert_array_equal(back.points, torus.astype(np.float32))
    assert f"{src}: {N} points" in proc.stdout


def test_importing_the_cli_does_not_import_bpy_or_torch():
    code = ("import sys; sys.path.insert(0, %r); import cljn_addon.cli, cljn_addon; "
            "print('bpy' in sys.modules, 'torch' in sys.modules)" % str(ROOT))
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split() == ["False", "False"]


# ----------------------------------------------------------------------------- formats

def _write_inputs(folder, pts):
    """The same cloud in every readable layout; returns {name: (path, positions as stored)}."""
    folder.mkdir(parents=True, exist_ok=True)
    p32, p64 = pts.astype(np.float32), pts.astype(np.float64)
    extras = _extras(len(pts))
    made = {}
    for fmt, tag in (("ascii", "asc"), ("binary_little_endian", "le"), ("binary_big_endian", "be")):
        path = folder / f"ply_{tag}.ply"
        pointio.write_ply(path, PointCloud(p32, None, dict(extras)), fmt=fmt)
        made[path.stem] = (path, p32, extras)
    nrm = np.tile(np.array([[0.0, 0.0, 1.0]], np.float32), (len(pts), 1))
    path = folder / "ply_normals_double.ply"
    pointio.write_ply(path, PointCloud(p64, nrm, {"quality": extras["intensity"]}))
    made[path.stem] = (path, p64, {"quality": extras["intensity"]})
    path = folder / "pcp.xyz"
    np.savetxt(path, p64, fmt="%.17g")
    np.savetxt(folder / "pcp.normals", nrm, fmt="%.9g")
    made[path.stem] = (path, p64, {})
    path = folder / "arr32.npy"
    np.save(path, p32)
    made[path.stem] = (path, p32, {})
    path = folder / "arr64_6.npy"
    np.save(path, np.concatenate([p64, nrm], axis=1))
    made[path.stem] = (path, p64, {})
    return made


@pytest.mark.parametrize("out_format", ["ply", "xyz", "npy"])
def test_normals_every_format_in_and_out(tmp_path, model_path, torus, out_format, capsys):
    made = _write_inputs(tmp_path / "in", torus)
    out_dir = tmp_path / "out"
    report = tmp_path / "report.json"
    code = command_line.main(["normals", *[str(p) for p, _, _ in made.values()], "--out-dir", str(out_dir),
                        "--format", out_format, "--report", str(report), *map(str, _base_args(model_path))])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    data = json.loads(report.read_text())
    assert data["exit_code"] == 0 and data["succeeded"] == len(made) and data["failed"] == 0
    for entry in data["inputs"]:
        assert entry["status"] == "ok" and entry["points"] == N
    for stem, (src, stored, extras) in made.items():
        out = out_dir / f"{stem}.{out_format}"
        back = pointio.read_points(out)
        # Positions bit-identical in the input's float type.
        np.testing.assert_array_equal(back.points.astype(stored.dtype), stored)
        if out_format != "xyz":
            assert back.points.dtype == stored.dtype, stem
        assert back.normals.shape == (N, 3)
        np.testing.assert_allclose(np.linalg.norm(back.normals, axis=1), 1.0, atol=1e-5)
        if out_format == "ply":
            assert list(back.extra)[:len(extras)] == list(extras)
            for name, values in extras.items():
                np.testing.assert_array_equal(back.extra[name], values)
                assert back.extra[name].dtype == values.dtype
            assert "cljn_outlier" in back.extra
        if out_format == "xyz":
            assert (out_dir / f"{stem}.normals").exists()
    assert f"{len(made)} of {len(made)} inputs done" in captured.out


def test_denoise_ply_keeps_properties_and_moves_points(tmp_path, model_path, torus, capsys):
    src = tmp_path / "scan.ply"
    extras = _extras(N)
    pointio.write_ply(src, PointCloud(torus.astype(np.float32), None, dict(extras)),
                      fmt="binary_big_endian")
    before = src.read_bytes()
    out = tmp_path / "clean.ply"
    report = tmp_path / "r.json"
    code = command_line.main(["denoise", str(src), "-o", str(out), "--report", str(report),
                        "--patch-radius", "6", "--orient", "viewpoint", "--viewpoint", "0", "0", "5",
                        *map(str, _base_args(model_path))])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    assert src.read_bytes() == before
    back = pointio.read_ply(out)
    assert b"format binary_little_endian 1.0" in out.read_bytes()[:200]
    assert back.points.shape == (N, 3) and np.isfinite(back.points).all()
    assert not np.array_equal(back.points, torus.astype(np.float32))
    for name, values in extras.items():
        np.testing.assert_array_equal(back.extra[name], values)
    entry = json.loads(report.read_text())["inputs"][0]
    assert entry["output"] == str(out) and entry["status"] == "ok"
    assert entry["points"] == N and entry["outliers"] == int(back.extra["cljn_outlier"].sum())
    moved = np.linalg.norm(back.points.astype(np.float64) - torus.astype(np.float32), axis=1)
    assert entry["mean_displacement"] == pytest.approx(moved.mean(), rel=1e-3, abs=1e-6)
    assert entry["seconds"] > 0
    assert entry["passes"] == 1 and entry["stopped_by_noise"] is False     # --iterations 1
    options = json.loads(report.read_text())["options"]
    assert options["patch_radius_percent"] == 6 and options["viewpoint"] == [0, 0, 5]
    assert "outliers flagged" in captured.out and "mean displacement" in captured.out
    assert ", 1 pass, " in captured.out


def _run_with_noise(command, tmp_path, model_path, cloud, capsys, noise="0.0025"):
    """Run `command` on `cloud` with --noise and a report: (output, report path, captured)."""
    src = tmp_path / "scan.xyz"
    np.savetxt(src, cloud, fmt="%.17g")
    out, report = tmp_path / "out.xyz", tmp_path / "r.json"
    code = command_line.main([command, str(src), "-o", str(out), "--report", str(report), "--noise", noise,
                              *map(str, _base_args(model_path))])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    return out, report, captured


def test_a_given_scanner_noise_is_used_and_reported(tmp_path, model_path, torus, capsys):
    """--noise: the engine takes the given sigma (motion bound 3 x it), and the line and the
    report say it was given."""
    out, report, captured = _run_with_noise("denoise", tmp_path, model_path, torus, capsys)
    data = json.loads(report.read_text())
    entry = data["inputs"][0]
    assert data["options"]["noise"] == 0.0025
    assert entry["noise_sigma"] == 0.0025 and entry["noise_given"] is True
    assert entry["displacement_bound"] == pytest.approx(0.0075)
    moved = np.linalg.norm(np.loadtxt(out) - torus, axis=1)
    assert moved.max() <= 0.0075 * (1 + 1e-6)
    assert "given noise 0.0025" in captured.out


def test_normals_take_a_given_scanner_noise_and_leave_positions_alone(tmp_path, model_path, torus, capsys):
    """normals --noise: the posterior's reach; nothing moves, so the line states no motion bound."""
    out, report, captured = _run_with_noise("normals", tmp_path, model_path, torus, capsys)
    entry = json.loads(report.read_text())["inputs"][0]
    assert entry["noise_sigma"] == 0.0025 and entry["noise_given"] is True
    assert entry["displacement_bound"] is None
    assert np.array_equal(np.loadtxt(out), torus)
    assert "given noise 0.0025, " in captured.out and "no point moved" not in captured.out


def test_points_on_rods_are_reported(tmp_path, model_path, capsys):
    """A pole: the line and the report give the share whose normals came from the rod's section."""
    rng = np.random.default_rng(4)
    side = rng.integers(0, 4, 3000)
    across = rng.uniform(-0.015, 0.015, 3000)
    pole = np.c_[rng.uniform(-0.5, 0.5, 3000), np.choose(side, [np.full(3000, 0.015), np.full(3000, -0.015), across, across]),
                 np.choose(side, [across, across, np.full(3000, 0.015), np.full(3000, -0.015)])]
    np.savetxt(tmp_path / "pole.xyz", pole + rng.normal(scale=0.002, size=pole.shape), fmt="%.17g")
    report = tmp_path / "r.json"
    code = command_line.main(["denoise", str(tmp_path / "pole.xyz"), "-o", str(tmp_path / "out.xyz"),
                              "--report", str(report), "--noise", "0.002",
                              *map(str, _base_args(model_path))])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    assert json.loads(report.read_text())["inputs"][0]["rod_share"] > 0.5
    assert "on rods (normals from the rod's section)" in captured.out


def test_in_place_keeps_a_backup(tmp_path, model_path, torus, capsys):
    src = tmp_path / "c.xyz"
    np.savetxt(src, torus, fmt="%.17g")
    original = src.read_bytes()
    assert command_line.main(["denoise", str(src), "--in-place", *map(str, _base_args(model_path))]) == 0
    assert (tmp_path / "c.xyz.bak").read_bytes() == original
    assert src.read_bytes() != original
    assert (tmp_path / "c.normals").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.normals", "c.xyz", "c.xyz.bak"]


# ----------------------------------------------------------------------------- usage and bad input

def _bad_files(folder, pts):
    folder.mkdir(parents=True, exist_ok=True)
    good = folder / "good.ply"
    pointio.write_ply(good, PointCloud(pts.astype(np.float32)))
    data = good.read_bytes()
    (folder / "truncated.ply").write_bytes(data[:len(data) - 100])
    (folder / "empty.xyz").write_text("")
    nan = pts.copy()
    nan[5, 1] = np.nan
    np.save(folder / "nan.npy", nan)
    (folder / "garbage.npy").write_bytes(b"\x00\x01 not an array")
    (folder / "unreadable.ply").write_bytes(b"PK\x03\x04 zip file")
    return {
        "truncated.ply": "truncated PLY",
        "empty.xyz": "empty",
        "nan.npy": "NaN",
        "garbage.npy": "not a readable .npy",
        "unreadable.ply": "not a PLY file",
        "missing.ply": "file not found",
    }


@pytest.mark.parametrize("name", ["truncated.ply", "empty.xyz", "nan.npy", "garbage.npy",
                                  "unreadable.ply", "missing.ply"])
def test_bad_input_one_line_exit_2_no_output(tmp_path, model_path, torus, name, capsys):
    problems = _bad_files(tmp_path / "in", torus)
    out = tmp_path / "out" / f"result{Path(name).suffix}"
    code = command_line.main(["denoise", str(tmp_path / "in" / name), "-o", str(out),
                        *map(str, _base_args(model_path))])
    err = capsys.readouterr().err
    assert code == 2
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, err
    assert lines[0].startswith("error: ") and name in lines[0] and problems[name] in lines[0]
    assert not out.exists()
    assert not (tmp_path / "out").exists() or not list((tmp_path / "out").iterdir())


def test_solid_flag_reaches_the_engine(tmp_path, model_path):
    """A thin plate reads thin-walled; --solid runs it as a solid, and the summary says which."""
    from cljn_addon.core.evaluation import shapes

    noisy, _, _ = shapes.sample_shape("thin_plate", 8000, noise=0.006, seed=1)
    src = tmp_path / "plate.npy"
    np.save(src, noisy.astype(np.float32))
    reports = {}
    for flags in ((), ("--solid",)):
        report = tmp_path / f"report{len(flags)}.json"
        proc = cli("denoise", src, "-o", tmp_path / f"out{len(flags)}.npy", "--report", report,
                   *flags, *_base_args(model_path))
        assert proc.returncode == 0, proc.stderr
        data = json.loads(report.read_text())
        assert data["options"]["solid"] is bool(flags)
        reports[flags] = (data["inputs"][0], proc.stdout + proc.stderr)
    (plain, said), (solid, said_solid) = reports[()], reports[("--solid",)]
    assert plain["thin_walled"] and "thin-walled" in said and "--solid" in said
    assert not solid["thin_walled"] and "thin-walled" not in said_solid
    assert 0.0 <= plain["solid_share"] <= 1.0 and solid["solid_share"] == 0.0


def test_batch_with_failures_exit_3_and_report(tmp_path, model_path, torus):
    problems = _bad_files(tmp_path / "in", torus)
    inputs = [tmp_path / "in" / "good.ply"] + [tmp_path / "in" / n for n in problems]
    report = tmp_path / "report.json"
    proc = cli("denoise", *inputs, "--out-dir", tmp_path / "out", "--report", report,
               *_base_args(model_path))
    assert proc.returncode == 3, proc.stderr
    assert "Traceback" not in proc.stderr
    errors = [ln for ln in proc.stderr.splitlines() if ln.startswith("error: ")]
    assert len(errors) == len(problems)
    for name, problem in problems.items():
        assert any(name in ln and problem in ln for ln in errors), (name, proc.stderr)
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["good.ply"]
    data = json.loads(report.read_text())
    assert data["exit_code"] == 3 and data["succeeded"] == 1 and data["failed"] == len(problems)
    by_name = {Path(e["input"]).name: e for e in data["inputs"]}
    assert by_name["good.ply"]["status"] == "ok"
    assert by_name["good.ply"]["output"] == str(tmp_path / "out" / "good.ply")
    # A solid torus: no merged thin walls to split.
    assert by_name["good.ply"]["split_share"] == 0 and not by_name["good.ply"]["thin_walled"]
    # A set pass count runs no risk check (auto only): no point placed by a plane filter.
    assert by_name["good.ply"]["plane_share"] == 0 and by_name["good.ply"]["kept_share"] == 0
    assert by_name["good.ply"]["scene_radius"] is None   # an object, not a scene
    assert by_name["good.ply"]["noise_range"] is None   # one noise, and a set pass count
    assert 0 <= by_name["good.ply"]["rim_share"] <= 1
    for name in problems:
        assert by_name[name]["status"] == "error" and by_name[name]["output"] is None
        assert problems[name] in by_name[name]["error"]


def test_single_bad_input_subprocess_exit_2(tmp_path, model_path, torus):
    _bad_files(tmp_path / "in", torus)
    proc = cli("normals", tmp_path / "in" / "truncated.ply", "-o", tmp_path / "o.ply",
               *_base_args(model_path))
    assert proc.returncode == 2
    assert proc.stderr.strip().count("\n") == 0 and "truncated.ply" in proc.stderr
    assert "Traceback" not in proc.stderr and not (tmp_path / "o.ply").exists()


def test_missing_and_mismatched_model_exit_2(tmp_path, model_path, torus):
    src = tmp_path / "a.npy"
    np.save(src, torus)
    proc = cli("denoise", src, "-o", tmp_path / "b.npy", "--model", tmp_path / "nope.safetensors")
    assert proc.returncode == 2
    assert proc.stderr.strip().startswith("error: model:") and "nope.safetensors" in proc.stderr
    assert proc.stderr.strip().count("\n") == 0 and not (tmp_path / "b.npy").exists()
    bad = tmp_path / "bad.safetensors"
    bad.write_bytes(model_path.read_bytes())
    cfg = json.loads(model_path.with_suffix(".json").read_text())
    cfg["encoder_channels"] = [16, 32]
    bad.with_suffix(".json").write_text(json.dumps(cfg))
    report = tmp_path / "r.json"
    code = command_line.main(["denoise", str(src), "-o", str(tmp_path / "b.npy"), "--model", str(bad),
                        "--report", str(report)])
    assert code == 2 and not (tmp_path / "b.npy").exists()
    data = json.loads(report.read_text())
    assert data["exit_code"] == 2 and "does not match" in data["error"]
    assert data["inputs"][0]["status"] == "error"


@pytest.mark.parametrize("args,message", [
    (["denoise", "a.ply", "b.ply", "-o", "c.ply"], "-o takes a single input"),
    (["denoise", "a.ply", "-o", "a.ply"], "refusing to overwrite"),
    (["denoise", "a.ply", "--out-dir", "."], "refusing to overwrite"),
    (["denoise", "a.ply", "-o", "c.e57"], "unsupported output format"),
    (["denoise", "a.obj", "-o", "c.ply"], "unsupported input format"),
    (["denoise", "a.ply", "-o", "c.ply", "--format", "npy"], "--format goes with --out-dir"),
    (["denoise", "s.blend", "-o", "c.ply"], "a .blend input is saved as a .blend"),
    (["denoise", "a.ply", "-o", "c.ply", "--orient", "viewpoint"], "needs --viewpoint"),
    (["denoise", "a.ply", "-o", "c.ply", "--objects", "A"], "--objects applies to .blend"),
    (["denoise", "a.ply", "x/a.ply", "--out-dir", "o"], "would both be written"),
    (["denoise", "a.ply", "-o", "c.ply", "--preview", "p.jpg"], "--preview wants a .png"),
    (["denoise", "a.ply"], "one of the arguments -o/--output --out-dir --in-place is required"),
    (["denoise", "a.ply", "-o", "c.ply", "--iterations", "0"], "must be at least 1"),
    (["denoise", "a.ply", "-o", "c.ply", "--patch-radius", "200"], "at most 100"),
    (["denoise", "a.ply", "-o", "c.ply", "--noise", "0"], "above 0"),
    (["denoise", "a.ply", "-o", "c.ply", "--noise", "nan"], "--noise"),
    (["frobnicate"], "invalid choice"),
])
def test_usage_errors_exit_2(tmp_path, args, message, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "a.ply").write_bytes(b"")
    assert command_line.main(args) == 2
    err = capsys.readouterr().err
    assert message in err
    assert "Traceback" not in err


def test_help_documents_exit_codes(capsys):
    assert command_line.main(["--help"]) == 0
    out = capsys.readouterr().out
    for text in ("exit codes:", "0    success", "2    bad input or usage", "3    a batch",
                 "blender -b -P standalone/run.py --", ".xyz", ".npy", ".blend"):
        assert text in out
    assert command_line.main(["denoise", "--help"]) == 0
    out = capsys.readouterr().out
    for option in ("--model", "--iterations", "--patch-radius", "--orient", "--viewpoint",
                   "--device", "--threads", "--report", "--preview", "--objects", "--in-place"):
        assert option in out


@pytest.mark.parametrize("command", sorted(command_line.COMMANDS))
def test_engine_commands_dispatch_help(command, capsys):
    assert command_line.main([command, "--help"]) == 0
    assert "usage" in capsys.readouterr().out.lower()


# ----------------------------------------------------------------------------- progress

class _Stream(io.StringIO):
    def __init__(self, tty):
        super().__init__()
        self._tty = tty

    def isatty(self):
        return self._tty


def test_progress_plain_lines_in_logs():
    stream = _Stream(tty=False)
    progress = Progress("cloud.ply", stream=stream)
    for i in range(101):
        progress(i / 100, f"step {i}")
    progress.close()
    lines = stream.getvalue().splitlines()
    assert len(lines) == 11
    assert lines[0].startswith("cloud.ply:   0%") and lines[-1].startswith("cloud.ply: 100%")
    assert "\r" not in stream.getvalue()


def test_progress_bar_on_terminal():
    stream = _Stream(tty=True)
    progress = Progress("cloud.ply", stream=stream)
    for i in range(11):
        progress(i / 10, "network")
    progress.close()
    text = stream.getvalue()
    assert "\r" in text and "cloud.ply" in text and "%|" in text


def test_no_progress():
    stream = _Stream(tty=True)
    progress = Progress("x", enabled=False, stream=stream)
    progress(0.5, "half")
    progress.close()
    assert stream.getvalue() == ""
