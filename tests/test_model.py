"""Networks as METHOD.md specifies them, and safe weights I/O."""
import json

import numpy as np
import pytest
import torch

from cljn_addon.core import ModelMismatchError, ModelNotFoundError, build_model, load_model, save_model
from cljn_addon.core.config import PAPER


def linear_shapes(module):
    return [(m.in_features, m.out_features) for m in module.modules() if isinstance(m, torch.nn.Linear)]


def test_paper_preset_matches_method():
    net = build_model("paper")
    assert linear_shapes(net.encoder) == [(3, 64), (64, 128), (128, 256), (256, 512), (512, 1024)]
    assert linear_shapes(net.head) == [(1024, 1024), (1024, 512), (512, 256)]
    assert linear_shapes(net.regressor) == [(1024, 512), (512, 256), (256, 128), (128, 64), (64, 6)]
    dropouts = [m.p for m in net.regressor.modules() if isinstance(m, torch.nn.Dropout)]
    assert dropouts == [0.3] * 4
    assert PAPER.points_per_patch == 500


def test_untrained_regressor_starts_at_the_pca_baseline():
    net = build_model("small").eval()
    with torch.no_grad():
        disp, normal = net(torch.randn(8, 128, 3))
    assert disp.abs().max() < 0.05
    assert torch.all(normal[:, 2] > 0.99)


def test_encoder_is_permutation_invariant():
    net = build_model("tiny").eval()
    x = torch.randn(4, 64, 3)
    with torch.no_grad():
        a = net.encoder(x)
        b = net.encoder(x[:, torch.randperm(64)])
    assert torch.allclose(a, b, atol=1e-6)


def test_save_and_load_round_trip(tmp_path):
    net = build_model("tiny").eval()
    path = save_model(net, tmp_path / "m.safetensors")
    assert (tmp_path / "m.json").exists()
    loaded = load_model(path)
    x = torch.randn(3, 64, 3)
    with torch.no_grad():
        assert torch.equal(net(x)[0], loaded(x)[0])


def test_mismatched_config_is_refused_with_the_tensor_named(tmp_path):
    path = save_model(build_model("tiny"), tmp_path / "m.safetensors")
    cfg = json.loads((tmp_path / "m.json").read_text())
    cfg["encoder_channels"] = [32, 64, 256]
    (tmp_path / "m.json").write_text(json.dumps(cfg))
    with pytest.raises(ModelMismatchError, match=r"encoder\.mlp\.6\.weight.*shape"):
        load_model(path)
    cfg["encoder_channels"] = [32, 64]
    (tmp_path / "m.json").write_text(json.dumps(cfg))
    with pytest.raises(ModelMismatchError, match="does not match its config"):
        load_model(path)


def test_missing_files_give_clear_errors(tmp_path, monkeypatch):
    with pytest.raises(ModelNotFoundError, match="not found"):
        load_model(tmp_path / "nope.safetensors")
    path = save_model(build_model("tiny"), tmp_path / "m.safetensors")
    (tmp_path / "m.json").unlink()
    with pytest.raises(ModelMismatchError, match="config missing"):
        load_model(path)
    (tmp_path / "bad.safetensors").write_bytes(b"not a weights file")
    (tmp_path / "bad.json").write_text(build_model("tiny").config.to_json())
    with pytest.raises(ModelMismatchError, match="not a readable"):
        load_model(tmp_path / "bad.safetensors")
    from cljn_addon.core import weights
    from cljn_addon.core.numpy_net import load_numpy_net

    monkeypatch.setattr(weights, "DEFAULT_WEIGHTS", tmp_path / "absent.safetensors")
    for loader in (load_model, load_numpy_net):          # both backends refuse alike
        with pytest.raises(ModelNotFoundError, match="No trained default model"):
            loader()


def test_weights_file_holds_no_pickle(tmp_path):
    path = save_model(build_model("tiny"), tmp_path / "m.safetensors")
    header_len = int(np.frombuffer(path.read_bytes()[:8], dtype="<u8")[0])
    header = json.loads(path.read_bytes()[8:8 + header_len])
    assert "__metadata__" in header and "config" in header["__metadata__"]


def test_folded_inference_net_matches_the_eval_model():
    from cljn_addon.core.model import inference_net
    torch.manual_seed(0)
    net = build_model("tiny")
    net.train()
    with torch.no_grad():                     # give BatchNorm non-trivial running statistics
        for _ in range(5):
            net(torch.randn(32, 64, 3) * 2 + 0.5)
    net.eval()
    x = torch.randn(16, 64, 3)
    with torch.no_grad():
        d1, n1 = net(x)
        d2, n2 = inference_net(net)(x)
    assert torch.allclose(d1, d2, atol=1e-5) and torch.allclose(n1, n2, atol=1e-5)
