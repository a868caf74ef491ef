"""Training losses: NT-Xent (contrastive), the joint loss and the fixed-target alternative."""
from __future__ import annotations

import torch
from torch.nn import functional as F

from ..config import LossConfig


def nt_xent(z_p: torch.Tensor, z_q: torch.Tensor, temperature: float = 0.01) -> torch.Tensor:
    """Symmetric NT-Xent over 2N projections; (P_k, Q_k) are the positives, no self-pairs.

    z_p, z_q: (N, d), L2-normalised. Mean of L(P_k,Q_k) and L(Q_k,P_k) over the 2N anchors.
    """
    n = z_p.shape[0]
    z = torch.cat([z_p, z_q], dim=0).float()
    logits = z @ z.t() / temperature
    logits.fill_diagonal_(float("-inf"))
    targets = torch.cat([torch.arange(n, 2 * n), torch.arange(0, n)]).to(z.device)
    return F.cross_entropy(logits, targets)


def normal_loss(cos: torch.Tensor, cfg: LossConfig) -> torch.Tensor:
    """1 - [delta cos^2 + (1 - delta) cos^gamma]: zero for a normal or its opposite."""
    return 1.0 - (cfg.delta * cos ** 2 + (1.0 - cfg.delta) * cos ** cfg.gamma)


def squared_angle_loss(cos: torch.Tensor) -> torch.Tensor:
    """theta^2 with theta = arccos|cos|: the evaluation's MSAE itself, sign ignored.

    Unlike the paper's loss (whose cos^12 term rewards committing to one side of an edge),
    its minimiser for a point that may belong to either face is the angle-weighted blend,
    which is what minimises the expected MSAE where the side is ambiguous.
    """
    c = cos.abs().clamp(max=1.0 - 1e-6)     # arccos' slope is infinite at 1
    return torch.arccos(c) ** 2


# The stage-2 normal terms by name: f(cos, LossConfig) -> per-sample loss.
NORMAL_LOSSES = {"paper": normal_loss, "squared_angle": lambda cos, cfg: squared_angle_loss(cos)}


def joint_loss(pred_points, pred_normals, gt_points, gt_normals, cfg: LossConfig = LossConfig(),
               normal_target=None, normal_loss_kind="paper"):
    """The paper's joint loss, in normalised patch units.

    pred_points, pred_normals: (B, 3); gt_points, gt_normals: (B, m, 3), the clean points of
    the same ball in the same frame (padding by repetition changes neither min nor max).
    normal_target: optional (B, 3) normals to use instead of the paper's n(g*) (the clean
    point nearest the prediction), e.g. the normal of the clean point the noisy centre was
    made from, which is what MSAE compares against. normal_loss_kind: 'paper' or
    'squared_angle'. Returns (loss, parts) where parts holds the batch means of each term.
    """
    d2 = ((pred_points[:, None, :] - gt_points) ** 2).sum(dim=2)          # (B, m)
    l1_pos, nearest = d2.min(dim=1)
    l2_pos = d2.max(dim=1).values
    l_pos = (1.0 - cfg.beta) * l1_pos + cfg.beta * l2_pos
    if normal_target is None:
        normal_target = torch.gather(gt_normals, 1, nearest[:, None, None].expand(-1, 1, 3))[:, 0]
    cos = (pred_normals * normal_target).sum(dim=1)
    if normal_loss_kind not in NORMAL_LOSSES:
        raise ValueError(f"unknown normal loss {normal_loss_kind!r}; choose one of {', '.join(NORMAL_LOSSES)}")
    l_normal = NORMAL_LOSSES[normal_loss_kind](cos, cfg)
    loss = cfg.alpha * l_pos + (1.0 - cfg.alpha) * l_normal
    parts = {"pos": l_pos.mean().item(), "normal": l_normal.mean().item(),
             "l1pos": l1_pos.mean().item(), "l2pos": l2_pos.mean().item()}
    return loss.mean(), parts


def fixed_target_loss(pred_points, pred_normals, target_points, target_normals,
                      cfg: LossConfig = LossConfig()):
    """Ablation: regress to the clean point of the same index (no repulsion term)."""
    l_pos = ((pred_points - target_points) ** 2).sum(dim=1)
    cos = (pred_normals * target_normals).sum(dim=1)
    l_normal = normal_loss(cos, cfg)
    loss = cfg.alpha * l_pos + (1.0 - cfg.alpha) * l_normal
    return loss.mean(), {"pos": l_pos.mean().item(), "normal": l_normal.mean().item()}
