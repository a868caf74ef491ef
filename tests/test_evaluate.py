"""The eval command's protocol on a small synthetic set (no ../shared needed)."""
import numpy as np
import torch

from cljn_addon.core import build_model
from cljn_addon.core.evaluation.evaluate import evaluate, format_table
from cljn_addon.core.evaluation.shapes import shape_mesh


def test_evaluate_reports_a_floor_no_method_beats():
    torch.manual_seed(0)
    shapes = [(name, *shape_mesh(name)) for name in ("box", "octahedron")]
    result = evaluate(shapes, build_model("tiny").eval(), levels=(0.015,), n_points=4000,
                      iterations=1, log=lambda m: None, tune=False)
    row = result["levels"][0]
    for shape in row["shapes"]:
        assert shape["msae_floor"] < shape["msae_pca"], shape
        assert shape["msae_floor"] < shape["msae_ours"], shape
        assert 0.0 < shape["msae_floor"]
    assert np.isclose(row["msae_floor"], np.mean([s["msae_floor"] for s in row["shapes"]]))
    table = format_table(result)
    assert "MSAE floor" in table and f"{row['msae_floor']:.4f}" in table
