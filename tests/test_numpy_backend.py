"""The numpy inference backend (issue #14): same network, same weights file, no torch."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from cljn_addon.core import InputError
from cljn_addon.core.errors import ModelMismatchError
from cljn_addon.core.evaluation import shapes
from cljn_addon.core.infer import network_pass, predictor
from cljn_addon.core.numpy_net import load_numpy_net
from cljn_addon.core.options import DenoiseOptions, resolve_backend
from cljn_addon.core.patches import bbox_diagonal
from cljn_addon.core.weights import expected_tensors

ROOT = Path(__file__).resolve().parents[1]
SHIPPED = ROOT / "cljn_addon" / "weights" / "cljn_small.safetensors"
needs_shipped = pytest.mark.skipif(not SHIPPED.exists(), reason="no shipped model")


def _agreement(points, torch_model, numpy_model):
    """Both backends on the same patches (same seed): worst normal angle (deg), worst
    displacement difference over the patch radius."""
    radius = 0.05 * bbox_diagonal(points)
    out = []
    for model, mixed in ((torch_model, False), (numpy_model, True)):
        predict, chunk, _ = predictor(model, "cpu", mixed_precision=mixed)
        out.append(network_pass(predict, chunk, points, radius, np.random.default_rng(0), 128)[:2])
    (d_t, n_t), (d_n, n_n) = out
    angle = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", n_t, n_n), -1, 1)))
    return float(angle.max()), float(np.abs(d_t - d_n).max() / radius)


def test_expected_tensors_match_the_torch_model():
    from cljn_addon.core import build_model

    for preset in ("tiny", "small", "paper"):
        model = build_model(preset)
        expected = expected_tensors(model.config)
        state = model.state_dict()
        assert set(expected) == set(state), preset
        assert all(tuple(state[k].shape) == expected[k] for k in expected), preset


@needs_shipped
@pytest.mark.parametrize("shape,n", [("fandisk_like", 20000), ("torus", 100000)])
def test_numpy_and_torch_fp32_agree(shape, n):
    from cljn_addon.core import load_model

    name = "stepped_block" if shape == "fandisk_like" else shape      # the demo's CAD shape
    noisy, _, _ = shapes.sample_shape(name, n, noise=0.01, seed=2)
    angle, disp = _agreement(noisy, load_model(), load_numpy_net())
    assert angle < 0.5, angle
    assert disp < 1e-4, disp


def test_untrained_network_agrees_too(model_path):
    from cljn_addon.core import load_model

    noisy, _, _ = shapes.sample_shape("sphere", 3000, noise=0.01, seed=1)
    angle, disp = _agreement(noisy, load_model(model_path), load_numpy_net(model_path))
    assert angle < 0.5 and disp < 1e-4, (angle, disp)


@needs_shipped
def test_numpy_backend_denoises_like_torch():
    from cljn_addon.core.evaluation.metrics import chamfer

    noisy, clean, _ = shapes.sample_shape("octahedron", 8000, noise=0.01, seed=3)
    results = {}
    for backend in ("torch", "numpy"):
        opts = DenoiseOptions(iterations=2, backend=backend, orientation="outward")
        res = opts.run(noisy, opts.load_model())
        results[backend] = res
        assert backend in res.ran_on
    cd = {b: chamfer(r.points, clean) for b, r in results.items()}
    assert cd["numpy"] < 0.5 * chamfer(noisy, clean)
    assert abs(cd["numpy"] - cd["torch"]) < 0.1 * cd["torch"], cd


def test_backend_choices_and_errors(model_path, tmp_path):
    assert resolve_backend("auto") == "torch"            # torch is installed here
    assert resolve_backend("numpy") == "numpy"
    with pytest.raises(InputError, match="unknown backend"):
        DenoiseOptions(backend="jax")
    net = load_numpy_net(model_path)
    with pytest.raises(InputError, match="numpy backend runs on the CPU only"):
        predictor(net, "cuda")
    # A weights file that does not match its config is refused by name, without torch.
    bad = tmp_path / "bad.safetensors"
    bad.write_bytes(Path(model_path).read_bytes())
    cfg = Path(model_path).with_suffix(".json").read_text().replace('"tiny"', '"tiny"')
    import json

    d = json.loads(cfg)
    d["encoder_channels"] = [c * 2 for c in d["encoder_channels"]]
    (tmp_path / "bad.json").write_text(json.dumps(d))
    with pytest.raises(ModelMismatchError, match="does not match its config"):
        load_numpy_net(bad)


def test_engine_runs_without_torch(model_path):
    """torch made unimportable: auto picks numpy, denoise and normals work, torch never loads."""
    code = f"""
import sys
sys.modules['torch'] = None            # import torch now raises ImportError
sys.path.insert(0, {str(ROOT)!r})
import numpy as np
from cljn_addon.core.options import DenoiseOptions, resolve_backend
from cljn_addon.core.evaluation.shapes import sample_shape
assert resolve_backend('auto') == 'numpy'
noisy, clean, _ = sample_shape('sphere', 3000, noise=0.01, seed=1)
opts = DenoiseOptions(iterations=1, model_path={str(model_path)!r})
res = opts.run(noisy, opts.load_model())
assert res.ran_on == 'cpu (numpy)', res.ran_on
assert res.points.shape == noisy.shape and np.allclose(np.linalg.norm(res.normals, axis=1), 1, atol=1e-5)
try:
    DenoiseOptions(backend='torch').load_model()
except Exception as exc:
    assert 'needs torch' in str(exc), exc
else:
    raise AssertionError('torch backend without torch')
print('ok')
"""
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0 and "ok" in proc.stdout, proc.stderr[-3000:]


def test_command_line_without_torch(tmp_path, model_path):
    """torch unimportable: `denoise` runs on numpy; `train` says it needs torch (exit 2)."""
    from cljn_addon.core.evaluation.shapes import sample_shape
    from cljn_addon.core.formats.points import PointCloud, write_points

    noisy, _, _ = sample_shape("sphere", 2000, noise=0.01, seed=1)
    write_points(tmp_path / "in.ply", PointCloud(noisy))
    runner = ("import runpy, sys; sys.modules['torch'] = None; sys.argv = ['run.py'] + sys.argv[1:]; "
              f"runpy.run_path({str(ROOT / 'standalone' / 'run.py')!r}, run_name='__main__')")
    proc = subprocess.run([sys.executable, "-c", runner, "denoise", str(tmp_path / "in.ply"), "-o",
                           str(tmp_path / "out.ply"), "--model", str(model_path), "--iterations", "1",
                           "--no-progress"], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert "on cpu (numpy)" in proc.stdout and (tmp_path / "out.ply").exists()
    proc = subprocess.run([sys.executable, "-c", runner, "train", "--out", str(tmp_path / "run")],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2 and "`train` needs torch" in proc.stderr, proc.stderr
