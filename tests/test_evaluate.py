"""The eval command's protocol on a small synthetic set (no ../shared needed)."""
import numpy as np
import pytest
import torch

from cljn_addon.core import build_model
from cljn_addon.core.evaluation.baselines import jet_smooth, jet_smoothing_available
from cljn_addon.core.evaluation.evaluate import evaluate, format_table, gap_closed
from cljn_addon.core.evaluation.metrics import MeshDistance, chamfer
from cljn_addon.core.evaluation.shapes import sample_shape, shape_mesh


@pytest.fixture(scope="module")
def result():
    torch.manual_seed(0)
    shapes = [(name, *shape_mesh(name)) for name in ("box", "thin_plate")]
    return evaluate(shapes, build_model("tiny").eval(), levels=(0.015,), n_points=4000,
                    iterations=1, log=lambda m: None, tune=False)


def test_evaluate_reports_a_floor_no_method_beats(result):
    row = result["levels"][0]
    for shape in row["shapes"]:
        assert shape["msae_floor"] < shape["msae_pca"], shape
        assert shape["msae_floor"] < shape["msae_ours"], shape
        assert 0.0 < shape["msae_floor"]
    assert np.isclose(row["msae_floor"], np.mean([s["msae_floor"] for s in row["shapes"]]))
    table = format_table(result)
    assert "MSAE floor" in table and f"{row['msae_floor']:.4f}" in table


def test_evaluate_compares_with_every_classic_filter_and_flags_worse_than_input(result):
    row = result["levels"][0]
    expected = ["plane", "jet"] if jet_smoothing_available() else ["plane"]
    assert result["filters"] == expected
    assert row["cd_classic"] == min(row[f"cd_{f}"] for f in expected)
    for shape in row["shapes"]:
        worse = shape["cd_ours"] >= shape["cd_noisy"] or shape["p2s_ours"] >= shape["p2s_noisy"]
        assert (shape["shape"] in row["worse_than_input"]) == worse
        assert 0 < shape["out_msae_classic"] < 1 and 0 < shape["out_msae_ours"]
    assert gap_closed(row) == pytest.approx((row["msae_pca"] - row["msae_ours"]) / (row["msae_pca"] - row["msae_floor"]))
    table = format_table(result)
    assert "out ours/classic" in table and "thin_plate" in table


def test_output_normal_truth_is_the_nearest_face():
    v, f = shape_mesh("box")
    dist = MeshDistance(v, f)
    points = np.array([[0.0, 0.0, 0.3], [0.0, 0.0, -0.3]])
    d, normals = dist.nearest(points)
    assert np.allclose(d, dist.distance(points))
    assert np.allclose(normals[:, 2], [1.0, -1.0])


@pytest.mark.skipif(not jet_smoothing_available(), reason="the cgal package is not installed")
def test_jet_smoothing_baseline_cleans_a_curved_surface():
    noisy, clean, _ = sample_shape("sphere", 20000, noise=0.01, seed=2)
    jet = jet_smooth(noisy, 30)
    assert jet.shape == noisy.shape
    assert chamfer(jet, clean) < 0.5 * chamfer(noisy, clean)
    # Same order as the input: each output point stays near its own noisy point.
    assert np.linalg.norm(jet - noisy, axis=1).max() < 0.05


def test_evaluate_reports_the_sign_ceiling_beside_sign(result):
    """At 1.5% noise a plate 1.5% thick cannot be oriented much past Phi(0.5) ~ 69% by any
    method; a box can be fully."""
    shapes = {s["shape"]: s for s in result["levels"][0]["shapes"]}
    assert shapes["box"]["sign_ceiling"] > 0.98
    assert 0.6 < shapes["thin_plate"]["sign_ceiling"] < 0.85
    for s in shapes.values():
        assert s["sign_ours"] <= s["sign_ceiling"] + 0.01
        assert 0.0 <= s["sign_out"] <= 1.0 and 0.0 <= s["sign_joint"] <= 1.0
    table = format_table(result)
    assert "sign ours (ceiling)" in table and "sign output" in table
    assert f"({shapes['thin_plate']['sign_ceiling'] * 100:.1f}%) / {shapes['thin_plate']['sign_out'] * 100:.1f}%" in table


def test_each_sign_is_scored_where_its_normals_sit(monkeypatch):
    """Normals-only mode against the faces of origin, the denoise's normals against the
    surface nearest their output points. A cube corner's points put back on the other face
    carry that face's normal: at right angles to their origin's (a miss there), right where
    they now sit. Stand-ins for the two modes make the difference exact."""
    import cljn_addon.core.evaluation.evaluate as ev

    v, f = shape_mesh("box")

    def onto_top(points, model, **_):
        # Every point onto the inside of the box's top face, with the top's normal.
        out = points * [0.9, 0.9, 0.0]
        out[:, 2] = v[:, 2].max()
        return type("R", (), dict(points=out, normals=np.tile([0.0, 0.0, 1.0], (len(points), 1)),
                                  noise_sigma=0.01, iterations=1))()

    monkeypatch.setattr(ev, "denoise", onto_top)
    monkeypatch.setattr(ev, "estimate_normals", lambda points, model, **_: type("R", (), dict(
        normals=np.tile([0.0, 0.0, 1.0], (len(points), 1))))())
    row = evaluate([("box", v, f)], None, levels=(0.002,), n_points=3000, iterations=1, log=lambda m: None,
                   tune=False)["levels"][0]["shapes"][0]
    assert row["sign_out"] == 1.0                       # every output point sits on the top face
    assert row["sign_joint"] == row["sign_ours"] < 0.4  # only the top's own points agree


def test_known_noise_hands_the_engine_the_true_sigma():
    """eval --known-noise: each cloud is denoised with noise_sigma = its level (the engine's
    reading is then exactly that), and the table says so; the default run estimates it."""
    torch.manual_seed(0)
    shapes = [("box", *shape_mesh("box"))]
    model = build_model("tiny").eval()
    given = evaluate(shapes, model, levels=(0.01,), n_points=3000, iterations=1, log=lambda m: None,
                     tune=False, known_noise=True)
    blind = evaluate(shapes, model, levels=(0.01,), n_points=3000, iterations=1, log=lambda m: None, tune=False)
    assert given["levels"][0]["shapes"][0]["noise_sigma_est"] == 0.01
    assert blind["levels"][0]["shapes"][0]["noise_sigma_est"] != 0.01
    assert "--known-noise" in format_table(given) and "--known-noise" not in format_table(blind)
