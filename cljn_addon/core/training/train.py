"""Two-stage training (METHOD.md): contrastive pretraining of encoder + projection head,
then the regressor on the joint loss with the encoder frozen.

`train_model` is what the command line (`run.py train`, cli/train.py) and Blender's Train
Model button call; it reports through two callbacks, progress(fraction, message) and
log(line), and prints nothing. A run writes checkpoints every few minutes into its output
folder and `resume=True` continues from the last one with its step counters, optimiser state
and random state.
"""
from __future__ import annotations

import dataclasses
import json
import math
import os
import time
from pathlib import Path

import numpy as np
import torch

from ..config import NOISE_LEVEL_SETS, LossConfig, get_preset
from ..device import autocast, pick_device
from ..errors import Cancelled, InputError
from ..formats.meshes import find_meshes
from ..model import build_model, save_model
from .config import DEFAULT_CACHE, QUICK, TrainConfig  # noqa: F401 (re-exported)
from .data import contrastive_batch, load_clean_cloud, make_training_shape, regression_batch
from .losses import NORMAL_LOSSES, fixed_target_loss, joint_loss, nt_xent

STAGES = ("contrastive", "regression", "done")
BATCH_BUILDERS = ("auto", "numpy", "device")


def _quiet(_message):
    pass


def _rng_state(rng):
    return json.dumps(rng.bit_generator.state)


def _restore_rng(text):
    rng = np.random.default_rng()
    rng.bit_generator.state = json.loads(text)
    return rng


def load_training_shapes(sources, cfg: TrainConfig, model_cfg, cache_dir=DEFAULT_CACHE, log=None):
    log = log or _quiet
    shapes = []
    for i, source in enumerate(sources):
        if isinstance(source, tuple):
            name = f"mesh{i + 1}"
        elif str(source).startswith("shape:"):
            name = f"{str(source)[6:]} (synthetic)"
        elif str(source).startswith("thin:"):
            name = f"thin part {str(source)[5:]} (synthetic)"
        elif str(source).startswith("relief:"):
            name = f"carved solid {str(source)[7:]} (synthetic)"
        else:
            name = Path(source).stem
        clean, normals = load_clean_cloud(source, cfg.points_per_shape, cfg.seed + i, cache_dir)
        shapes.append(make_training_shape(str(name), clean, normals, model_cfg.points_per_patch,
                                          model_cfg.patch_radius_fraction, cfg.seed + 1000 + i,
                                          noise_levels=NOISE_LEVEL_SETS[cfg.noise_levels]))
        log(f"  shape {i + 1}/{len(sources)}: {name} ({len(clean)} points)")
    return shapes


def _make_optimizer(model, cfg, stage, total_steps, time_fraction=None):
    if stage == "contrastive":
        params = list(model.encoder.parameters()) + list(model.head.parameters())
        opt = torch.optim.Adam(params, lr=cfg.contrastive_lr, weight_decay=cfg.weight_decay)
    else:
        params = list(model.regressor.parameters())
        if cfg.finetune_encoder:
            params += list(model.encoder.parameters())
        if cfg.regression_optimizer == "sgd":
            opt = torch.optim.SGD(params, lr=cfg.regression_lr, momentum=cfg.momentum)
        elif cfg.regression_optimizer == "adam":
            opt = torch.optim.Adam(params, lr=cfg.regression_lr)
        else:
            raise InputError(f"unknown optimizer {cfg.regression_optimizer!r} (sgd or adam)")
    if time_fraction is not None:        # cosine over the wall-clock budget
        sched = torch.optim.lr_scheduler.LambdaLR(
            opt, lambda _step: 0.5 * (1.0 + math.cos(math.pi * min(time_fraction(), 1.0))))
    else:
        sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=max(total_steps, 1))
    return opt, sched


class _RegressionBatches(torch.utils.data.Dataset):
    """Batch i of the regressor stage, drawn with its own seeded generator so worker
    processes make the same batches in any order and a resumed run continues the sequence."""

    def __init__(self, shapes, cfg):
        self.shapes, self.cfg = shapes, cfg

    def __getitem__(self, step):
        cfg = self.cfg
        return regression_batch(self.shapes, cfg.regression_batch, cfg.gt_points,
                                np.random.default_rng([cfg.seed, 2, int(step)]), own_side=cfg.gt_side == "own")


def _quiet_worker(_worker_id):
    torch.set_num_threads(1)


def _as_built(batch):
    """Batches cross from the workers as the numpy arrays they were built as."""
    return batch


def _worker_batches(run, shapes):
    """The regressor's remaining batches from cfg.data_workers processes (fork: the shapes
    and their k-d trees are shared, not copied)."""
    steps = range(run.step, run.stage_total)
    loader = torch.utils.data.DataLoader(
        _RegressionBatches(shapes, run.cfg), batch_size=None, sampler=steps, collate_fn=_as_built,
        num_workers=run.cfg.data_workers, worker_init_fn=_quiet_worker, prefetch_factor=4,
        multiprocessing_context="fork" if os.name == "posix" else None)
    return iter(loader)


def _on(device, array):
    """A batch array (numpy from the CPU builders, a tensor from the device's) on `device`."""
    return array.to(device) if isinstance(array, torch.Tensor) else torch.from_numpy(array).to(device)


def _device_batches(run, builder):
    """The stage's remaining batches from `builder` (a `device_batches.DeviceBatches`, the
    clouds on the training device), each from its step's own seeded generator, like the worker
    processes' batches."""
    cfg, stage = run.cfg, run.stage
    for step in range(run.step, run.stage_total):
        g = builder.generator(stage, step)
        if stage == "contrastive":
            yield builder.contrastive(cfg.contrastive_batch, g)
        else:
            yield builder.regression(cfg.regression_batch, cfg.gt_points, g, own_side=cfg.gt_side == "own")


def uses_device_batches(cfg, device) -> bool:
    """Whether batches are built on the training device: asked for, or "auto" on a CUDA GPU
    (not MPS, whose torch lacks some of the ops: eigh for the frames)."""
    return cfg.batch_builder == "device" or (cfg.batch_builder == "auto" and torch.device(device).type == "cuda")


def make_config(config: TrainConfig | None = None, quick=False, **overrides) -> TrainConfig:
    """config (or the defaults), then QUICK when quick, then overrides; checked."""
    base = dataclasses.asdict(config) if config is not None else {}
    if quick:
        base.update(QUICK)
    base.update(overrides)
    cfg = TrainConfig(**base)
    if cfg.normal_target not in ("nearest", "index"):
        raise InputError(f"unknown normal target {cfg.normal_target!r} (nearest or index)")
    if cfg.normal_loss not in NORMAL_LOSSES:
        raise InputError(f"unknown normal loss {cfg.normal_loss!r} ({' or '.join(NORMAL_LOSSES)})")
    if cfg.gt_side not in ("all", "own"):
        raise InputError(f"unknown ground-truth side {cfg.gt_side!r} (all or own)")
    if cfg.batch_builder not in BATCH_BUILDERS:
        raise InputError(f"unknown batch builder {cfg.batch_builder!r} ({' or '.join(BATCH_BUILDERS)})")
    if cfg.noise_levels not in NOISE_LEVEL_SETS:
        raise InputError(f"unknown noise levels {cfg.noise_levels!r} ({' or '.join(NOISE_LEVEL_SETS)})")
    return cfg


class _Run:
    """The mutable state of one run (model, optimiser, stage and step, random state) and its
    steps. Stages: contrastive -> regression -> done."""

    def __init__(self, cfg, device, n_contrastive, n_regression, checkpoint):
        self.cfg, self.device, self.checkpoint = cfg, device, checkpoint
        self.steps = {"contrastive": n_contrastive, "regression": n_regression, "done": 0}
        self.model = build_model(get_preset(cfg.preset)).to(device)
        self.stage, self.step, self.elapsed = "contrastive", 0, 0.0
        self.rng = np.random.default_rng(cfg.seed)
        self.loss_cfg = LossConfig()
        self.t_start = time.time()
        self.opt = self.sched = None

    @property
    def total(self) -> int:
        return self.steps["contrastive"] + self.steps["regression"]

    @property
    def stage_total(self) -> int:
        return self.steps[self.stage]

    @property
    def done_steps(self) -> int:
        """Steps done over both stages."""
        if self.stage == "done":
            return self.total
        return self.step + (self.steps["contrastive"] if self.stage == "regression" else 0)

    def init_weights(self, path, log):
        from ..model import load_model

        start = load_model(path)
        if start.config != get_preset(self.cfg.preset):
            raise InputError(f"{path} is a {start.config.preset!r} model, not {self.cfg.preset!r}")
        self.model.load_state_dict(start.state_dict())
        log(f"initialised from {path}")

    def restore(self, state, log):
        self.model.load_state_dict(state["model"])
        self.stage, self.step, self.elapsed = state["stage"], int(state["step"]), float(state["elapsed"])
        self.rng = _restore_rng(state["rng"])
        torch.set_rng_state(state["torch_rng"])
        log(f"resumed at stage {self.stage}, step {self.step}")

    def time_fraction(self) -> float:
        return self.seconds() / (60.0 * self.cfg.max_minutes)

    def out_of_time(self) -> bool:
        return self.cfg.max_minutes > 0 and self.time_fraction() >= 1.0

    def make_optimizer(self, state=None):
        self.opt, self.sched = _make_optimizer(self.model, self.cfg, self.stage,
                                               self.steps["contrastive" if self.stage == "contrastive"
                                                          else "regression"],
                                               self.time_fraction if self.cfg.max_minutes > 0 else None)
        if state is not None and self.stage != "done":
            self.opt.load_state_dict(state["optimizer"])
            self.sched.load_state_dict(state["scheduler"])

    def save_checkpoint(self):
        tmp = self.checkpoint.with_name("checkpoint.pt.tmp")
        torch.save({"model": self.model.state_dict(), "optimizer": self.opt.state_dict(),
                    "scheduler": self.sched.state_dict(), "stage": self.stage, "step": self.step,
                    "elapsed": self.seconds(), "rng": _rng_state(self.rng),
                    "torch_rng": torch.get_rng_state(),
                    "train_config": json.dumps(dataclasses.asdict(self.cfg))}, tmp)
        tmp.replace(self.checkpoint)

    def seconds(self) -> float:
        return self.elapsed + (time.time() - self.t_start)

    def next_stage(self):
        """The current stage is complete (or the budget spent): move on (a fresh optimiser
        for the regressor)."""
        self.steps[self.stage] = min(self.steps[self.stage], self.step)    # steps actually done
        if self.out_of_time():
            self.stage = "done"
        elif self.stage == "contrastive":
            self.stage, self.step = "regression", 0
            self.make_optimizer()
        else:
            self.stage = "done"
        self.save_checkpoint()

    def contrastive_loss(self, shapes, batch=None):
        """NT-Xent on `batch` (positive pairs P, Q: numpy or device tensors) or on pairs drawn here."""
        p, q = batch if batch is not None else contrastive_batch(shapes, self.cfg.contrastive_batch, self.rng)
        with autocast(self.device, self.cfg.bf16):
            z = self.model.project(torch.cat([_on(self.device, p), _on(self.device, q)]))
        return nt_xent(z[: len(p)], z[len(p):], self.loss_cfg.temperature), {}

    def regression_loss(self, shapes, batch=None):
        """The joint loss on `batch` (regression_batch's arrays) or on a batch drawn here."""
        cfg, model, dev = self.cfg, self.model, self.device
        if not cfg.finetune_encoder:
            model.encoder.eval()          # frozen: BatchNorm uses its running stats
        if batch is None:
            batch = regression_batch(shapes, cfg.regression_batch, cfg.gt_points, self.rng,
                                     own_side=cfg.gt_side == "own")
        patches, gt, gt_n, tgt, tgt_n = (_on(dev, a) for a in batch)
        with autocast(dev, cfg.bf16):
            with torch.enable_grad() if cfg.finetune_encoder else torch.no_grad():
                feats = model.encoder(patches)
            out6 = model.regressor(feats).float()
        disp = out6[:, :3]
        normal = torch.nn.functional.normalize(out6[:, 3:], dim=1, eps=1e-8)
        if cfg.loss != "joint":
            return fixed_target_loss(disp, normal, tgt, tgt_n, self.loss_cfg)
        # "index": the normal of the clean point this noisy centre was made from.
        index_normal = tgt_n if cfg.normal_target == "index" else None
        return joint_loss(disp, normal, gt, gt_n, self.loss_cfg, normal_target=index_normal,
                          normal_loss_kind=cfg.normal_loss)

    def train_step(self, shapes, batch=None):
        """One optimiser step of the current stage; returns (loss, loss parts)."""
        self.model.train()
        if self.stage == "contrastive":
            loss, parts = self.contrastive_loss(shapes, batch)
        else:
            loss, parts = self.regression_loss(shapes, batch)
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        self.opt.step()
        self.sched.step()
        self.step += 1
        return loss.item(), parts

    def log_record(self, loss, parts) -> dict:
        rec = {"stage": self.stage, "step": self.step, "loss": round(loss, 6),
               "lr": self.sched.get_last_lr()[0], "time": round(self.seconds(), 1)}
        rec.update({k: round(v, 6) for k, v in parts.items()})
        return rec


def _load_checkpoint(ckpt_path, cfg, resume, log):
    """(checkpoint state or None, the training settings to use)."""
    if resume and ckpt_path.exists():
        state = torch.load(ckpt_path, map_location="cpu", weights_only=True)
        saved = json.loads(state["train_config"])
        if saved != dataclasses.asdict(cfg):
            log("resuming with the checkpoint's training settings, not the ones given")
        return state, TrainConfig(**saved)
    if resume:
        log(f"no checkpoint in {ckpt_path.parent}; starting fresh")
    return None, cfg


def _train_loop(run, shapes, out, progress, cancel):
    """Steps until both stages are done; checkpoints on schedule, on stage ends and on cancel."""
    last_ckpt = time.time()
    batches = builder = None
    with open(out / "log.jsonl", "a") as log_file:
        while run.stage != "done":
            if run.step >= run.stage_total or run.out_of_time():
                run.next_stage()
                batches = None
                continue
            if cancel is not None and cancel.is_set():
                run.save_checkpoint()
                raise Cancelled("training cancelled; resume continues from the last checkpoint")
            if batches is None and uses_device_batches(run.cfg, run.device):
                if builder is None:          # the clouds go to the device once, for both stages
                    from .device_batches import DeviceBatches

                    builder = DeviceBatches(shapes, run.device, run.cfg.seed)
                batches = _device_batches(run, builder)
            elif batches is None and run.stage == "regression" and run.cfg.data_workers > 0:
                batches = _worker_batches(run, shapes)
            loss, parts = run.train_step(shapes, next(batches) if batches is not None else None)
            if run.step % 10 == 0 or run.step == run.stage_total:
                log_file.write(json.dumps(run.log_record(loss, parts)) + "\n")
                log_file.flush()
            if progress is not None:
                fraction = run.done_steps / max(run.total, 1)
                if run.cfg.max_minutes > 0:
                    fraction = max(fraction, min(run.time_fraction(), 1.0))
                progress(fraction,
                         f"{run.stage} {run.step}/{run.stage_total}, loss {loss:.4f}")
            if time.time() - last_ckpt > run.cfg.checkpoint_minutes * 60:
                run.save_checkpoint()
                last_ckpt = time.time()


def _write_outputs(run, shapes, out, validation_dir, validation_points, log):
    """Weights, training.json and MODEL_CARD.md (with the validation table when asked)."""
    cfg = run.cfg
    wall = run.seconds()
    weights = out / "model.safetensors"
    model = run.model.eval()
    card = {"preset": cfg.preset, "shapes": [s.name for s in shapes], "train_config": dataclasses.asdict(cfg),
            "contrastive_steps": run.steps["contrastive"], "regression_steps": run.steps["regression"],
            "wall_seconds": round(wall, 1), "noise_levels": list(NOISE_LEVEL_SETS[cfg.noise_levels])}
    save_model(model.cpu(), weights, {"training": card})
    (out / "training.json").write_text(json.dumps(card, indent=2))
    table = None
    if validation_dir is not None and Path(validation_dir).is_dir():
        table = validate(weights, validation_dir, validation_points, log)
    write_model_card(out / "MODEL_CARD.md", card, table)
    log(f"wrote {weights} ({wall / 60:.1f} min)")
    return weights


def train_model(sources, out_dir, config: TrainConfig | None = None, *, resume=False,
                progress=None, cancel=None, quick=False, log=None, cache_dir=DEFAULT_CACHE,
                validation_dir=None, validation_points=20_000, **overrides):
    """Train a model on meshes; returns the path of the written weights.

    sources: mesh files (.off/.obj/.ply), "shape:NAME" synthetic shapes, "thin:I" thin parts,
    or (V, F) arrays. progress(fraction, message) after every step; log(line) for the rest.
    validation_dir: held-out meshes; when given, the model card gets the eval table.
    overrides: TrainConfig fields (e.g. preset="tiny"). quick=True applies QUICK first.
    """
    log = log or _quiet
    cfg = make_config(config, quick, **overrides)
    if not sources:
        raise InputError("no training meshes given")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    device = pick_device(cfg.device)
    torch.manual_seed(cfg.seed)
    state, cfg = _load_checkpoint(out / "checkpoint.pt", cfg, resume, log)

    log(f"loading {len(sources)} training shapes")
    shapes = load_training_shapes(sources, cfg, get_preset(cfg.preset), cache_dir, log)
    run = _Run(cfg, device, *cfg.stage_steps(len(shapes)), out / "checkpoint.pt")
    if cfg.init_weights and state is None:
        run.init_weights(cfg.init_weights, log)
    if state is not None:
        run.restore(state, log)
    run.make_optimizer(state)
    run.t_start = time.time()
    _train_loop(run, shapes, out, progress, cancel)
    return _write_outputs(run, shapes, out, validation_dir, validation_points, log)


def validate(weights, mesh_dir, n_points, log=None):
    """The eval command's table on held-out meshes, for the model card."""
    from ..evaluation.evaluate import evaluate, format_table
    from ..formats.meshes import read_mesh
    from ..model import load_model

    log = log or _quiet
    shapes = [(p.stem, *read_mesh(p)) for p in find_meshes(mesh_dir)]
    log(f"validating on {len(shapes)} meshes from {mesh_dir} ({n_points} points each)")
    result = evaluate(shapes, load_model(weights), n_points=n_points, log=log)
    return format_table(result)


def write_model_card(path, card, validation_table=None):
    cfg = card["train_config"]
    lines = [
        "# CLJN Denoise model card", "",
        f"- Preset: `{card['preset']}` (architecture in the JSON config beside the weights)",
        f"- Training shapes ({len(card['shapes'])}): {', '.join(card['shapes'])}",
        f"- Points per shape: {cfg['points_per_shape']}, noise variants (sigma, fraction of the bbox diagonal): "
        + ", ".join(f"{x:g}" for x in card["noise_levels"]),
        f"- Stage 1 (contrastive): {card['contrastive_steps']} steps of {cfg['contrastive_batch']} pairs "
        f"({cfg['contrastive_epochs']} epochs of {cfg['patches_per_shape']} patches per shape), Adam lr "
        f"{cfg['contrastive_lr']}, weight decay {cfg['weight_decay']}, cosine decay, NT-Xent tau 0.01",
        f"- Stage 2 (regressor, {cfg['loss']} loss): {card['regression_steps']} steps of {cfg['regression_batch']} "
        f"patches ({cfg['regression_epochs']} epochs), {cfg['regression_optimizer']} lr {cfg['regression_lr']}, "
        f"encoder {'fine-tuned' if cfg['finetune_encoder'] else 'frozen (paper)'}, normal target "
        f"{cfg.get('normal_target', 'nearest')}, normal loss {cfg.get('normal_loss', 'paper')}",
        f"- Wall time: {card['wall_seconds'] / 60:.1f} min on {os.cpu_count()} CPU cores, bf16 autocast: {cfg['bf16']}",
        f"- Seed: {cfg['seed']}", "",
    ]
    if cfg.get("init_weights"):
        lines.insert(-1, f"- Initialised from: `{Path(cfg['init_weights']).name}`")
    if validation_table:
        lines += ["## Validation", "", validation_table, ""]
    Path(path).write_text("\n".join(lines))
