"""Loss formulas against independent calculations on small cases."""
import math

import numpy as np
import torch

from cljn_addon.core.config import LossConfig
from cljn_addon.core.training.losses import fixed_target_loss, joint_loss, normal_loss, nt_xent, squared_angle_loss


def brute_force_nt_xent(zp, zq, tau):
    z = np.concatenate([zp, zq])
    n2 = len(z)
    n = n2 // 2
    total = 0.0
    for a in range(n2):
        pos = a + n if a < n else a - n
        denom = sum(math.exp(z[a] @ z[b] / tau) for b in range(n2) if b != a)
        total += -math.log(math.exp(z[a] @ z[pos] / tau) / denom)
    return total / n2


def test_nt_xent_matches_brute_force_loop():
    rng = np.random.default_rng(0)
    zp = rng.normal(size=(5, 4))
    zq = zp + 0.3 * rng.normal(size=(5, 4))
    zp /= np.linalg.norm(zp, axis=1, keepdims=True)
    zq /= np.linalg.norm(zq, axis=1, keepdims=True)
    for tau in (0.5, 0.1):
        got = nt_xent(torch.tensor(zp), torch.tensor(zq), tau).item()
        assert abs(got - brute_force_nt_xent(zp, zq, tau)) < 1e-6 * max(1, abs(got))


def test_nt_xent_prefers_matching_pairs():
    rng = np.random.default_rng(1)
    z = torch.nn.functional.normalize(torch.tensor(rng.normal(size=(8, 16))), dim=1)
    shuffled = z[torch.randperm(8)]
    assert nt_xent(z, z, 0.1) < nt_xent(z, shuffled, 0.1)


def disc_patch(m=400, seed=0):
    """Clean points filling a unit disc in the z=0 plane (radius-normalised patch)."""
    rng = np.random.default_rng(seed)
    r = np.sqrt(rng.random(m))
    t = rng.random(m) * 2 * np.pi
    pts = np.c_[r * np.cos(t), r * np.sin(t), np.zeros(m)]
    pts[0] = 0.0                   # the centre itself is a ground-truth point
    pts[1] = [1.0, 0.0, 0.0]       # and one on the rim, so max distance is exactly r = 1
    return torch.tensor(pts[None], dtype=torch.float64), torch.tensor(np.tile([0, 0, 1.0], (1, m, 1)))


def test_joint_loss_centre_of_disc_costs_r_squared_regulariser():
    gt, gt_n = disc_patch()
    cfg = LossConfig()
    pred = torch.zeros(1, 3, dtype=torch.float64)
    normal = torch.tensor([[0, 0, 1.0]], dtype=torch.float64)
    loss, parts = joint_loss(pred, normal, gt, gt_n, cfg)
    assert parts["l1pos"] == 0.0
    assert abs(parts["l2pos"] - 1.0) < 1e-12          # r^2 with r = 1 in patch units
    assert abs(loss.item() - cfg.alpha * cfg.beta * 1.0) < 1e-12


def test_joint_loss_flipped_normal_is_free_and_perpendicular_costs_one():
    gt, gt_n = disc_patch()
    cfg = LossConfig()
    pred = torch.zeros(1, 3, dtype=torch.float64)
    up = joint_loss(pred, torch.tensor([[0, 0, 1.0]], dtype=torch.float64), gt, gt_n, cfg)[1]["normal"]
    down = joint_loss(pred, torch.tensor([[0, 0, -1.0]], dtype=torch.float64), gt, gt_n, cfg)[1]["normal"]
    side = joint_loss(pred, torch.tensor([[1.0, 0, 0]], dtype=torch.float64), gt, gt_n, cfg)[1]["normal"]
    assert up == 0.0 and down == 0.0
    assert abs(side - 1.0) < 1e-12


def test_joint_loss_lifted_point_pays_its_height_squared():
    gt, gt_n = disc_patch()
    cfg = LossConfig(beta=0.0)
    pred = torch.tensor([[0.0, 0.0, 0.3]], dtype=torch.float64)
    loss, parts = joint_loss(pred, torch.tensor([[0, 0, 1.0]], dtype=torch.float64), gt, gt_n, cfg)
    assert abs(parts["l1pos"] - 0.09) < 1e-12
    assert abs(loss.item() - cfg.alpha * 0.09) < 1e-12


def test_normal_loss_shape():
    cfg = LossConfig()
    theta = torch.tensor([0.0, math.pi / 4, math.pi / 2, math.pi])
    values = normal_loss(torch.cos(theta), cfg)
    expected = [1 - (0.3 * math.cos(t) ** 2 + 0.7 * math.cos(t) ** 12) for t in theta.tolist()]
    assert torch.allclose(values, torch.tensor(expected, dtype=values.dtype), atol=1e-6)


def test_fixed_target_loss():
    cfg = LossConfig()
    pred = torch.tensor([[0.1, 0.0, 0.0]])
    loss, parts = fixed_target_loss(pred, torch.tensor([[0, 1.0, 0]]), torch.zeros(1, 3),
                                    torch.tensor([[0, -1.0, 0]]), cfg)
    assert abs(parts["pos"] - 0.01) < 1e-7 and parts["normal"] == 0.0
    assert abs(loss.item() - cfg.alpha * 0.01) < 1e-7


def test_squared_angle_loss_is_msae_sign_ignored():
    theta = torch.tensor([0.0, 0.3, math.pi / 2, math.pi - 0.3, math.pi], dtype=torch.float64)
    values = squared_angle_loss(torch.cos(theta))
    expected = torch.tensor([0.0, 0.09, (math.pi / 2) ** 2, 0.09, 0.0], dtype=torch.float64)
    assert torch.allclose(values, expected, atol=1e-5)


def _best_angle(loss_of_cos):
    """Angle from face A (normal x) towards face B (normal y) minimising the loss of a point
    that belongs to either face with equal chance."""
    phi = torch.linspace(0.0, math.pi / 2, 901, dtype=torch.float64)
    expected = 0.5 * loss_of_cos(torch.cos(phi)) + 0.5 * loss_of_cos(torch.sin(phi))
    return float(phi[expected.argmin()])


def test_squared_angle_blends_an_ambiguous_edge_where_the_paper_loss_picks_a_side():
    assert abs(_best_angle(squared_angle_loss) - math.pi / 4) < 1e-3
    paper_choice = _best_angle(lambda c: normal_loss(c, LossConfig()))
    assert min(paper_choice, math.pi / 2 - paper_choice) < 1e-3


def test_joint_loss_normal_target_override_and_kind():
    gt = torch.tensor([[[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]])
    gt_n = torch.tensor([[[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]]])
    pred = torch.zeros(1, 3)
    tilted = torch.tensor([[0.0, math.sin(0.2), math.cos(0.2)]])
    nearest = joint_loss(pred, tilted, gt, gt_n, normal_loss_kind="squared_angle")[1]["normal"]
    assert abs(nearest - 0.04) < 1e-5
    own = joint_loss(pred, tilted, gt, gt_n, normal_target=tilted, normal_loss_kind="squared_angle")[1]["normal"]
    assert own < 1e-5
    try:
        joint_loss(pred, tilted, gt, gt_n, normal_loss_kind="nope")
    except ValueError as exc:
        assert "nope" in str(exc)
    else:
        raise AssertionError("unknown normal loss accepted")
