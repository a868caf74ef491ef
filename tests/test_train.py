"""Training end to end on a tiny synthetic set, and resuming after an interruption."""
import json
import threading

import numpy as np
import pytest
import torch

from cljn_addon.core import Cancelled, load_model
from cljn_addon.core.evaluation.shapes import shape_mesh
from cljn_addon.core.training.train import train_model

TINY_RUN = dict(preset="tiny", points_per_shape=3000, patches_per_shape=384, contrastive_epochs=1,
                contrastive_batch=64, regression_epochs=3, regression_batch=64,
                regression_optimizer="adam", regression_lr=3e-3, finetune_encoder=True,
                checkpoint_minutes=0.0, bf16=True, device="cpu")
SHAPES = ["shape:box", "shape:sphere"]


def read_log(folder):
    return [json.loads(line) for line in (folder / "log.jsonl").read_text().splitlines()]


def held_out_joint_loss(model):
    """Joint loss on a fixed batch from fresh noise variants of the training shapes."""
    from cljn_addon.core.training.data import load_clean_cloud, make_training_shape, regression_batch
    from cljn_addon.core.training.losses import joint_loss

    shapes = [make_training_shape(s, *load_clean_cloud(s, 3000, 99), 64, 0.05, 123) for s in SHAPES]
    patches, gt, gt_n, _, _ = regression_batch(shapes, 512, 128, np.random.default_rng(7))
    with torch.no_grad():
        disp, normal = model.eval()(torch.from_numpy(patches))
        return joint_loss(disp, normal, torch.from_numpy(gt), torch.from_numpy(gt_n))[0].item()


def test_tiny_training_runs_and_the_losses_fall(tmp_path):
    from cljn_addon.core import build_model

    torch.manual_seed(0)
    untrained = build_model("tiny")
    held_out = tmp_path / "validation"
    held_out.mkdir()
    v, f = shape_mesh("octahedron")
    (held_out / "octa.off").write_text(
        f"OFF\n{len(v)} {len(f)} 0\n" + "".join(f"{x} {y} {z}\n" for x, y, z in v)
        + "".join(f"3 {a} {b} {c}\n" for a, b, c in f))
    weights = train_model(SHAPES, tmp_path / "run", cache_dir=None, validation_dir=held_out,
                          validation_points=1500, **TINY_RUN)
    tmp_path = tmp_path / "run"
    log = read_log(tmp_path)
    contrastive = [r["loss"] for r in log if r["stage"] == "contrastive"]
    assert contrastive[-1] < contrastive[0]
    model = load_model(weights)
    assert held_out_joint_loss(model) < 0.9 * held_out_joint_loss(untrained)
    assert model.config.preset == "tiny"
    card = (tmp_path / "MODEL_CARD.md").read_text()
    assert "Stage 2" in card and "box (synthetic)" in card
    assert "## Validation" in card and "| **mean** |" in card


def test_interrupted_run_resumes_from_its_checkpoint(tmp_path):
    straight = train_model(SHAPES, tmp_path / "a", cache_dir=None, **TINY_RUN)

    cancel = threading.Event()

    def stop_midway(fraction, message):
        if fraction > 0.5:
            cancel.set()

    with pytest.raises(Cancelled):
        train_model(SHAPES, tmp_path / "b", cache_dir=None, progress=stop_midway, cancel=cancel, **TINY_RUN)
    assert (tmp_path / "b" / "checkpoint.pt").exists()
    assert not (tmp_path / "b" / "model.safetensors").exists()
    steps_before = [(r["stage"], r["step"]) for r in read_log(tmp_path / "b")]
    resumed = train_model(SHAPES, tmp_path / "b", cache_dir=None, resume=True, **TINY_RUN)
    steps_after = [(r["stage"], r["step"]) for r in read_log(tmp_path / "b")]
    # Counters continue where they stopped: no step is logged twice, none restarts at 0.
    assert steps_after[:len(steps_before)] == steps_before
    assert len(set(steps_after)) == len(steps_after)
    assert steps_after == [(r["stage"], r["step"]) for r in read_log(tmp_path / "a")]
    # Same data, optimiser and random state: the resumed model is the uninterrupted one.
    a, b = load_model(straight).state_dict(), load_model(resumed).state_dict()
    for key in a:
        assert torch.allclose(a[key].float(), b[key].float(), atol=1e-5), key


def test_index_target_squared_angle_run_trains_and_is_recorded(tmp_path):
    """The MSAE-aligned stage-2 variant: the held-out normal error falls and the card says so."""
    from cljn_addon.core import build_model
    from cljn_addon.core.training.data import load_clean_cloud, make_training_shape, regression_batch
    from cljn_addon.core.training.losses import squared_angle_loss

    shapes = [make_training_shape(s, *load_clean_cloud(s, 3000, 99), 64, 0.05, 123) for s in SHAPES]
    patches, _, _, _, index_normals = regression_batch(shapes, 512, 128, np.random.default_rng(7))

    def held_out_msae(model):
        with torch.no_grad():
            _, normal = model.eval()(torch.from_numpy(patches))
        return squared_angle_loss((normal * torch.from_numpy(index_normals)).sum(dim=1)).mean().item()

    torch.manual_seed(0)
    untrained = build_model("tiny")
    run = dict(TINY_RUN, contrastive_epochs=0, normal_target="index", normal_loss="squared_angle")
    weights = train_model(SHAPES, tmp_path / "run", cache_dir=None, **run)
    assert held_out_msae(load_model(weights)) < 0.8 * held_out_msae(untrained)
    assert "normal target index, normal loss squared_angle" in (tmp_path / "run" / "MODEL_CARD.md").read_text()


def test_unknown_normal_target_is_refused(tmp_path):
    from cljn_addon.core import InputError

    with pytest.raises(InputError, match="normal target"):
        train_model(SHAPES, tmp_path / "run", cache_dir=None, **dict(TINY_RUN, normal_target="furthest"))


def test_own_side_ground_truth_drops_the_far_side_of_a_thin_plate():
    from cljn_addon.core.training.data import load_clean_cloud, make_training_shape, regression_batch

    clean, normals = load_clean_cloud("shape:thin_plate", 20000, seed=0)
    shape = make_training_shape("plate", clean, normals, 64, 0.05, seed=1, noise_levels=(0.0, 0.005))
    rng = np.random.default_rng(0)
    _, gt_all, n_all, _, tgt_n = regression_batch([shape], 256, 128, rng)
    rng = np.random.default_rng(0)
    _, gt_own, n_own, _, tgt_n2 = regression_batch([shape], 256, 128, rng, own_side=True)
    cos_all = np.einsum("bmc,bc->bm", n_all, tgt_n)
    cos_own = np.einsum("bmc,bc->bm", n_own, tgt_n2)
    assert (cos_all < -0.9).mean() > 0.2            # a 1.5% plate: the far side is in every ball
    assert (cos_own < -0.5).sum() == 0               # ... and gone from the own-side truth
    assert np.allclose(np.linalg.norm(n_own, axis=2), 1.0, atol=1e-5)


def test_worker_batches_are_the_seeded_batches_of_their_steps():
    """Batches built in worker processes are those of their step's own generator: the same in
    any process and order, so a resumed run continues the same sequence."""
    from cljn_addon.core.training.data import load_clean_cloud, make_training_shape
    from cljn_addon.core.training.train import _RegressionBatches, make_config

    shapes = [make_training_shape(s, *load_clean_cloud(s, 3000, 99), 64, 0.05, 123) for s in SHAPES]
    cfg = make_config(None, regression_batch=32, gt_points=64, gt_side="own")
    loader = torch.utils.data.DataLoader(_RegressionBatches(shapes, cfg), batch_size=None, sampler=[3, 1],
                                         num_workers=2, multiprocessing_context="fork")
    third, first = list(loader)
    again = _RegressionBatches(shapes, cfg)
    for got, want in zip(third, again[3]):
        assert np.array_equal(np.asarray(got), want)
    assert np.array_equal(np.asarray(first[0]), again[1][0])
    assert not np.array_equal(again[1][0], again[3][0])


def test_a_run_on_a_clock_stops_when_its_minutes_are_spent(tmp_path):
    """max_minutes bounds the run (the steps done are recorded, the cosine reaches ~0 on the
    clock) and data workers feed the regressor."""
    run = dict(TINY_RUN, contrastive_epochs=0, regression_epochs=10_000, max_minutes=0.1, data_workers=2)
    weights = train_model(SHAPES, tmp_path / "run", cache_dir=None, **run)
    card = json.loads((tmp_path / "run" / "training.json").read_text())
    log = read_log(tmp_path / "run")
    planned = 10_000 * len(SHAPES) * TINY_RUN["patches_per_shape"] // TINY_RUN["regression_batch"]
    assert 10 < card["regression_steps"] < planned
    assert abs(log[-1]["step"] - card["regression_steps"]) < 10
    assert 5.5 < card["wall_seconds"] < 20
    budget, base = 6.0, TINY_RUN["regression_lr"]
    for rec in log:            # the learning rate is the cosine of the clock, not of the steps
        assert abs(rec["lr"] - base * 0.5 * (1 + np.cos(np.pi * min(rec["time"] / budget, 1.0)))) < 0.05 * base
    assert log[-1]["lr"] < 0.1 * base
    assert load_model(weights).config.preset == "tiny"


def _plate_and_box():
    from cljn_addon.core.training.data import load_clean_cloud, make_training_shape

    # Balls of ~250-1,000 points for 64-point patches: a biased pick would show.
    return [make_training_shape(s, *load_clean_cloud(s, 20000, 5), 64, 0.08, 11, noise_levels=(0.0, 0.005, 0.01))
            for s in ("shape:thin_plate", "shape:box")]


def test_device_batches_draw_what_the_cpu_batches_draw():
    """The torch batch builder (for GPUs; run here on the CPU) against data.py's: the same
    shapes and frames, patches uniform over the ball (not its nearest points), ground truth
    from the whole ball and from the centre's own side when asked, each step its own seeded batch."""
    from cljn_addon.core.patches import pca_frames
    from cljn_addon.core.training import device_batches
    from cljn_addon.core.training.data import contrastive_batch, regression_batch

    shapes = _plate_and_box()
    builder = device_batches.DeviceBatches(shapes, "cpu", seed=3)
    ours = [a.numpy() for a in builder.regression(512, 128, builder.generator("regression", 0))]
    theirs = regression_batch(shapes, 512, 128, np.random.default_rng(0))
    for a, b in zip(ours, theirs):
        assert a.shape == b.shape and a.dtype == b.dtype == np.float32
    patches, gt, gt_n, target, target_n = ours
    assert np.linalg.norm(patches, axis=2).max() <= 1 + 1e-5
    assert np.linalg.norm(gt, axis=2).max() <= 1 + 1e-5
    # Uniform over the ball: the mean distance from the centre matches the CPU path's (a
    # nearest-first pick would be far closer), and so does the spread across the surface.
    for pick in (lambda x: np.linalg.norm(x, axis=2).mean(), lambda x: np.abs(x[..., 2]).mean()):
        assert abs(pick(patches) / pick(theirs[0]) - 1) < 0.05
    # The truth is the whole ball's clean surface: as far out on average as the patches. (data.py
    # takes the 4 x 128 nearest clean points, a smaller disc where the plate's ball holds ~800.)
    assert abs(np.linalg.norm(gt, axis=2).mean() / np.linalg.norm(patches, axis=2).mean() - 1) < 0.05
    assert np.linalg.norm(theirs[1], axis=2).mean() < 0.95 * np.linalg.norm(gt, axis=2).mean()
    # PCA frames: the rough normal is z, and the torch frames are data.py's frames.
    cov = np.einsum("bni,bnj->bij", patches, patches)
    assert np.all(cov[:, 2, 2] <= cov[:, 1, 1] + 1e-4) and np.all(cov[:, 1, 1] <= cov[:, 0, 0] + 1e-4)
    assert np.allclose(np.abs(cov[:, 0, 1]) + np.abs(cov[:, 0, 2]) + np.abs(cov[:, 1, 2]), 0, atol=1e-3)
    local = torch.randn(64, 100, 3, generator=torch.Generator().manual_seed(0)) * torch.tensor([1.0, 0.5, 0.1])
    assert np.allclose(device_batches.pca_frames(local).numpy(), pca_frames(local.numpy()), atol=1e-6)
    assert np.allclose(np.linalg.norm(target_n, axis=1), 1, atol=1e-5)
    # The centre's own side: a 1.5% plate's far face is in the plain truth, not in the own-side one.
    plate = device_batches.DeviceBatches(shapes[:1], "cpu")
    _, _, n_all, _, t_all = plate.regression(256, 128, plate.generator("regression", 1))
    _, _, n_own, _, t_own = plate.regression(256, 128, plate.generator("regression", 1), own_side=True)
    assert (torch.einsum("bmc,bc->bm", n_all, t_all) < -0.9).float().mean() > 0.2
    assert (torch.einsum("bmc,bc->bm", n_own, t_own) < -0.5).sum() == 0
    # Seeded per step; contrastive pairs like data.py's (Q rotated by one of the paper's angles).
    again = builder.regression(512, 128, builder.generator("regression", 0))
    assert torch.equal(again[0], torch.from_numpy(patches))
    assert not torch.equal(builder.regression(512, 128, builder.generator("regression", 1))[0], again[0])
    p, q = builder.contrastive(256, builder.generator("contrastive", 0))
    p_cpu, _ = contrastive_batch(shapes, 256, np.random.default_rng(0))
    assert p.shape == q.shape == p_cpu.shape
    assert torch.allclose(p.norm(dim=2).mean(), torch.tensor(float(np.linalg.norm(p_cpu, axis=2).mean())), rtol=0.05)


def test_a_run_with_device_batches_trains(tmp_path):
    """Both stages from the device builder (here the CPU: batch_builder="device"); an unknown
    builder is refused."""
    from cljn_addon.core import InputError

    run = dict(TINY_RUN, batch_builder="device", contrastive_epochs=1, regression_epochs=2)
    weights = train_model(SHAPES, tmp_path / "run", cache_dir=None, **run)
    log = read_log(tmp_path / "run")
    assert {r["stage"] for r in log} == {"contrastive", "regression"}
    assert all(np.isfinite(r["loss"]) for r in log)
    regression = [r["loss"] for r in log if r["stage"] == "regression"]
    assert regression[-1] < regression[0]
    assert load_model(weights).config.preset == "tiny"
    with pytest.raises(InputError, match="batch builder"):
        train_model(SHAPES, tmp_path / "bad", cache_dir=None, **dict(TINY_RUN, batch_builder="gpu"))
