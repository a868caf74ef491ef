"""Training batches built with torch on the training device (a GPU).

On a GPU the network trains far faster than numpy and k-d trees can gather its patches (an
H200: ~13K patches/s from 14 worker processes against 1.27M patches/s through the network).
Here every training cloud lives on the device as one (shapes, variants, points, 3) tensor, and a
ball query is a brute-force distance row per centre: work a GPU does in bulk and a CPU does
slowly, so `data.regression_batch` / `data.contrastive_batch` stay the CPU path. The draws
follow theirs: the same ball sampling (uniform without replacement, padded by repetition), the
same PCA frames, the same clean ground truth (nearest-first fallback for an empty ball, the
centre's own side only when asked) with one difference: it is drawn from the whole ball, where
data.py's draws from the ball's 4 x gt_points nearest clean points, a smaller disc wherever a
ball holds more (a thin part's two faces in a dense cloud). The random numbers differ.
"""
from __future__ import annotations

import numpy as np
import torch

from ..config import ROTATION_ANGLES_DEG
from .data import OWN_SIDE_COS, _rotation_about_axis

# Rows of distances computed at once: (rows x points) floats and their gathered coordinates.
ROWS_PER_CHUNK = 128


def _uniform_from_ball(cloud, centres, radius, count, generator, nearest_fallback):
    """`count` indices per centre into `cloud` (B, N, 3): a uniform sample without replacement
    of the points within `radius` (B,) of the centre, padded by repeating random ones of them.
    A ball with no point takes the nearest points (nearest_fallback) or the nearest one."""
    d2 = ((cloud - centres[:, None, :]) ** 2).sum(-1)                       # (B, N)
    inside = d2 <= (radius ** 2)[:, None]
    keys = torch.rand(d2.shape, generator=generator, device=d2.device)
    # Outside the ball: after every inside point, nearest first.
    keys = torch.where(inside, keys, 2.0 + d2 / d2.max(dim=1, keepdim=True).values.clamp_min(1e-30))
    picked = torch.topk(keys, count, dim=1, largest=False, sorted=True).indices   # inside ones first
    inside_count = inside.sum(dim=1, keepdim=True)
    if nearest_fallback:
        fill = torch.arange(count, device=d2.device)[None, :] >= inside_count
        fill &= inside_count > 0
    else:
        fill = torch.arange(count, device=d2.device)[None, :] >= inside_count.clamp_min(1)
    # Padding only where the ball holds fewer than `count`: repeat one of its first columns.
    pad = (torch.rand(picked.shape, generator=generator, device=d2.device)
           * inside_count.clamp(1, count)).long()
    return torch.where(fill, torch.gather(picked, 1, pad), picked)


def pca_frames(local):
    """`patches.pca_frames` in torch: rotations (B, 3, 3), rows the PCA axes (largest variance
    first, the rough normal last), signs by the third moment, det +1."""
    x = local.double()
    cov = torch.einsum("mni,mnj->mij", x, x) / x.shape[1]
    cov = cov + torch.eye(3, dtype=x.dtype, device=x.device) * 1e-12
    _, vecs = torch.linalg.eigh(cov)
    e1, e3 = vecs[:, :, 2], vecs[:, :, 0]
    e1 = e1 * torch.where((torch.einsum("mni,mi->mn", x, e1) ** 3).sum(1) < 0, -1.0, 1.0)[:, None]
    e3 = e3 * torch.where((torch.einsum("mni,mi->mn", x, e3) ** 3).sum(1) < 0, -1.0, 1.0)[:, None]
    return torch.stack([e1, torch.linalg.cross(e3, e1), e3], dim=1)


def to_frame(x, frames):
    """Rotate (B, n, 3) points or (B, 3) vectors into the frames (float32)."""
    frames = frames.to(x.dtype)
    out = torch.einsum("mij,mj->mi", frames, x) if x.dim() == 2 else torch.einsum("mij,mnj->mni", frames, x)
    return out.float()


class DeviceBatches:
    """The training shapes (`data.TrainingShape`, equal point counts) on `device`, and the two
    stages' batches drawn there. `generator(step)` seeds batch `step` of a stage, so a resumed
    run continues the sequence."""

    def __init__(self, shapes, device, seed=0):
        counts = {len(v.points) for s in shapes for v in s.variants}
        if len(counts) != 1:
            raise ValueError(f"device batches need every training cloud the same size, not {sorted(counts)}")
        self.device = torch.device(device)
        self.seed = int(seed)
        as_tensor = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float32, device=self.device)  # noqa: E731
        self.clouds = torch.stack([torch.stack([as_tensor(v.points) for v in s.variants]) for s in shapes])
        self.radius = torch.tensor([[v.radius for v in s.variants] for s in shapes], device=self.device)
        self.clean = torch.stack([as_tensor(s.clean) for s in shapes])
        self.normals = torch.stack([as_tensor(s.normals) for s in shapes])
        self.n = shapes[0].variants[0].n
        self.shapes, self.variants, self.points = self.clouds.shape[:3]

    def generator(self, stage, step):
        g = torch.Generator(device=self.device)
        g.manual_seed(int(np.random.SeedSequence([self.seed, 7 if stage == "contrastive" else 8, int(step)])
                          .generate_state(1)[0]))
        return g

    def _draw(self, batch, g):
        dev = self.device
        shape = torch.randint(0, self.shapes, (batch,), generator=g, device=dev)
        centre = torch.randint(0, self.points, (batch,), generator=g, device=dev)
        variant = torch.randint(0, self.variants, (batch,), generator=g, device=dev)
        return shape, centre, variant

    def _patches(self, shape, variant, centres, g):
        """(B, n, 3) noisy patches in radius units about `centres`, not yet rotated."""
        out = torch.empty((len(shape), self.n, 3), device=self.device)
        for rows in torch.arange(len(shape), device=self.device).split(ROWS_PER_CHUNK):
            cloud = self.clouds[shape[rows], variant[rows]]
            r = self.radius[shape[rows], variant[rows]]
            idx = _uniform_from_ball(cloud, centres[rows], r, self.n, g, nearest_fallback=False)
            picked = torch.gather(cloud, 1, idx[..., None].expand(-1, -1, 3))
            out[rows] = (picked - centres[rows, None, :]) / r[:, None, None]
        return out

    def regression(self, batch, gt_points, g, own_side=False):
        """What `data.regression_batch` returns, as float32 tensors on the device."""
        shape, centre, variant = self._draw(batch, g)
        centres = self.clouds[shape, variant, centre]
        radius = self.radius[shape, variant]
        local = self._patches(shape, variant, centres, g)
        gt = torch.empty((batch, gt_points, 3), device=self.device)
        gt_n = torch.empty_like(gt)
        for rows in torch.arange(batch, device=self.device).split(ROWS_PER_CHUNK):
            clean = self.clean[shape[rows]]
            normals = self.normals[shape[rows]]
            idx = _uniform_from_ball(clean, centres[rows], radius[rows], gt_points, g, nearest_fallback=True)
            if own_side:
                idx = self._keep_own_side(idx, normals, self.normals[shape[rows], centre[rows]], g)
            gt[rows] = (torch.gather(clean, 1, idx[..., None].expand(-1, -1, 3)) - centres[rows, None, :]) \
                / radius[rows, None, None]
            gt_n[rows] = torch.gather(normals, 1, idx[..., None].expand(-1, -1, 3))
        target = (self.clean[shape, centre] - centres) / radius[:, None]
        target_n = self.normals[shape, centre]
        frames = pca_frames(local)
        return (to_frame(local, frames), to_frame(gt, frames), to_frame(gt_n, frames),
                to_frame(target, frames), to_frame(target_n, frames))

    @staticmethod
    def _keep_own_side(idx, normals, own_normal, g):
        """`data._keep_own_side` on indices: far-side picks replaced by random own-side picks
        of the same ball; a ball with no own-side point is left as it is."""
        picked_normals = torch.gather(normals, 1, idx[..., None].expand(-1, -1, 3))
        same = torch.einsum("bmc,bc->bm", picked_normals, own_normal) > OWN_SIDE_COS
        count = same.sum(dim=1, keepdim=True)
        keys = torch.where(same, torch.rand(same.shape, generator=g, device=idx.device), torch.full_like(idx, 2, dtype=torch.float32))
        order = torch.argsort(keys, dim=1)                                     # own side first
        pick = (torch.rand(same.shape, generator=g, device=idx.device) * count.clamp_min(1)).long()
        donor = torch.gather(idx, 1, torch.gather(order, 1, pick))
        return torch.where(~same & (count > 0), donor, idx)

    def contrastive(self, batch_pairs, g):
        """What `data.contrastive_batch` returns: positive pairs (P, Q), float32 on the device."""
        shape, centre, v1 = self._draw(batch_pairs, g)
        v2 = torch.randint(0, self.variants, (batch_pairs,), generator=g, device=self.device)
        centres = self.clouds[shape, v1, centre]
        p_local = self._patches(shape, v1, centres, g)
        q_local = self._patches(shape, v2, centres, g)
        frames = pca_frames(p_local)
        p, q = to_frame(p_local, frames), to_frame(q_local, frames)
        # The rotations are (B, 3, 3): drawn here, built by data.py's function, sent back.
        angles = np.deg2rad(np.asarray(ROTATION_ANGLES_DEG, np.float64))[
            torch.randint(0, len(ROTATION_ANGLES_DEG), (batch_pairs,), generator=g, device=self.device).cpu().numpy()]
        axis = torch.randint(0, 3, (batch_pairs,), generator=g, device=self.device).cpu().numpy()
        rot = torch.as_tensor(_rotation_about_axis(axis, angles), dtype=torch.float32, device=self.device)
        return p, torch.einsum("bij,bnj->bni", rot, q)
