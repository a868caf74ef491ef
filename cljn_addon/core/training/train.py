"""Two-stage training (METHOD.md): contrastive pretraining of encoder + projection head,
then the regressor on the joint loss with the encoder frozen.

`train_model` is what the CLI (`run.py train`) and Blender's Train Model button call. A run
writes checkpoints every few minutes into its output folder and `resume=True` continues
from the last one with its step counters, optimiser state and random state.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ..config import NOISE_LEVEL_SETS, LossConfig, get_preset
from .data import contrastive_batch, load_clean_cloud, make_training_shape, regression_batch
from ..device import autocast, pick_device
from ..errors import Cancelled, InputError
from .losses import NORMAL_LOSSES, fixed_target_loss, joint_loss, nt_xent
from ..formats.meshes import find_meshes
from ..model import build_model, save_model

REPO_ROOT = Path(__file__).resolve().parents[2]
DEFAULT_TRAIN_DIR = REPO_ROOT.parent / "shared" / "data" / "meshes" / "train"
DEFAULT_VALIDATION_DIR = REPO_ROOT.parent / "shared" / "data" / "meshes" / "validation"
DEFAULT_CACHE = Path(os.environ.get("CLJN_CACHE", Path.home() / ".cache" / "cljn_denoise"))


@dataclass
class TrainConfig:
    """Paper values are the defaults; the CPU recipe in the model card scales the schedule."""

    preset: str = "small"
    points_per_shape: int = 100_000
    patches_per_shape: int = 8192           # per epoch (paper code)
    contrastive_epochs: float = 150
    contrastive_batch: int = 512            # pairs
    contrastive_lr: float = 3e-4
    weight_decay: float = 1e-4
    regression_epochs: float = 30
    regression_batch: int = 12
    regression_optimizer: str = "sgd"       # paper: SGD lr 1e-2, momentum 0.9
    regression_lr: float = 1e-2
    momentum: float = 0.9
    finetune_encoder: bool = False          # paper: encoder frozen in stage 2
    loss: str = "joint"                     # or "fixed" (the ablation)
    normal_target: str = "nearest"          # paper: clean point nearest the prediction; or "index"
    normal_loss: str = "paper"              # paper: 1 - d cos^2 - (1-d) cos^g; or "squared_angle"
    gt_points: int = 256                    # clean points per ground-truth patch
    noise_levels: str = "paper"             # paper: 0, .25, .5, 1, 1.5, 2.5%; or "dense" (9 levels)
    seed: int = 0
    init_weights: str = ""                  # start from a trained model (e.g. to fine-tune further)
    checkpoint_minutes: float = 5.0
    bf16: bool = True
    device: str = "auto"

    def stage_steps(self, n_shapes):
        patches = n_shapes * self.patches_per_shape
        return (math.ceil(self.contrastive_epochs * patches / self.contrastive_batch),
                math.ceil(self.regression_epochs * patches / self.regression_batch))


# Small sane defaults for Blender's Train Model button and for tests.
QUICK = dict(points_per_shape=20_000, patches_per_shape=1024, contrastive_epochs=2,
             contrastive_batch=128, regression_epochs=4, regression_batch=128,
             regression_optimizer="adam", regression_lr=1e-3, finetune_encoder=True,
             checkpoint_minutes=2.0)


def _rng_state(rng):
    return json.dumps(rng.bit_generator.state)


def _restore_rng(text):
    rng = np.random.default_rng()
    rng.bit_generator.state = json.loads(text)
    return rng


class _Progress:
    """tqdm on the CLI (plain lines when not a terminal) plus an optional callback."""

    def __init__(self, total, initial, callback, show):
        self.callback, self.bar = callback, None
        self.total = total
        if show:
            from tqdm import tqdm
            self.bar = tqdm(total=total, initial=initial, unit="step", dynamic_ncols=True,
                            mininterval=1.0 if sys.stderr.isatty() else 30.0)

    def update(self, step, message, postfix=None):
        if self.bar is not None:
            self.bar.set_description(message, refresh=False)
            if postfix:
                self.bar.set_postfix(postfix, refresh=False)
            self.bar.update(step - self.bar.n)   # redraws at most every mininterval
        if self.callback is not None:
            self.callback(step / max(self.total, 1), message)

    def close(self):
        if self.bar is not None:
            self.bar.close()


def load_training_shapes(sources, cfg: TrainConfig, model_cfg, cache_dir=DEFAULT_CACHE, log=print):
    shapes = []
    for i, source in enumerate(sources):
        if isinstance(source, tuple):
            name = f"mesh{i + 1}"
        elif str(source).startswith("shape:"):
            name = f"{str(source)[6:]} (synthetic)"
        elif str(source).startswith("thin:"):
            name = f"thin part {str(source)[5:]} (synthetic)"
        else:
            name = Path(source).stem
        clean, normals = load_clean_cloud(source, cfg.points_per_shape, cfg.seed + i, cache_dir)
        shapes.append(make_training_shape(str(name), clean, normals, model_cfg.points_per_patch,
                                          model_cfg.patch_radius_fraction, cfg.seed + 1000 + i,
                                          noise_levels=NOISE_LEVEL_SETS[cfg.noise_levels]))
        log(f"  shape {i + 1}/{len(sources)}: {name} ({len(clean)} points)")
    return shapes


def _make_optimizer(model, cfg, stage, total_steps):
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
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=max(total_steps, 1))
    return opt, sched


def train_model(sources, out_dir, config: TrainConfig | None = None, *, resume=False,
                progress=None, cancel=None, quick=False, show_progress=False, log=None,
                cache_dir=DEFAULT_CACHE, validation_dir=None, validation_points=20_000, **overrides):
    """Train a model on meshes; returns the path of the written weights.

    sources: mesh files (.off/.obj/.ply), "shape:NAME" synthetic shapes, or (V, F) arrays.
    validation_dir: held-out meshes; when given, the model card gets the eval table.
    overrides: TrainConfig fields (e.g. preset="tiny"). quick=True applies QUICK first.
    """
    log = log or (lambda msg: None)
    base = dataclasses.asdict(config) if config is not None else {}
    if quick:
        base.update(QUICK)
    base.update(overrides)
    cfg = TrainConfig(**base)
    if cfg.normal_target not in ("nearest", "index"):
        raise InputError(f"unknown normal target {cfg.normal_target!r} (nearest or index)")
    if cfg.normal_loss not in NORMAL_LOSSES:
        raise InputError(f"unknown normal loss {cfg.normal_loss!r} ({' or '.join(NORMAL_LOSSES)})")
    if cfg.noise_levels not in NOISE_LEVEL_SETS:
        raise InputError(f"unknown noise levels {cfg.noise_levels!r} ({' or '.join(NOISE_LEVEL_SETS)})")
    if not sources:
        raise InputError("no training meshes given")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    ckpt_path = out / "checkpoint.pt"
    model_cfg = get_preset(cfg.preset)
    device = pick_device(cfg.device)
    torch.manual_seed(cfg.seed)

    state = None
    if resume and ckpt_path.exists():
        state = torch.load(ckpt_path, map_location="cpu", weights_only=True)
        saved = json.loads(state["train_config"])
        if saved != dataclasses.asdict(cfg):
            log("resuming with the checkpoint's training settings, not the ones given")
        cfg = TrainConfig(**saved)
        model_cfg = get_preset(cfg.preset)
    elif resume:
        log(f"no checkpoint in {out}; starting fresh")

    log(f"loading {len(sources)} training shapes")
    shapes = load_training_shapes(sources, cfg, model_cfg, cache_dir, log)
    n_contrastive, n_regression = cfg.stage_steps(len(shapes))
    total = n_contrastive + n_regression

    model = build_model(model_cfg).to(device)
    stage, step, elapsed = "contrastive", 0, 0.0
    rng = np.random.default_rng(cfg.seed)
    if cfg.init_weights and state is None:
        from ..model import load_model
        start = load_model(cfg.init_weights)
        if start.config != model_cfg:
            raise InputError(f"{cfg.init_weights} is a {start.config.preset!r} model, not {cfg.preset!r}")
        model.load_state_dict(start.state_dict())
        log(f"initialised from {cfg.init_weights}")
    if state is not None:
        model.load_state_dict(state["model"])
        stage, step, elapsed = state["stage"], int(state["step"]), float(state["elapsed"])
        rng = _restore_rng(state["rng"])
        torch.set_rng_state(state["torch_rng"])
        log(f"resumed at stage {stage}, step {step}")
    opt, sched = _make_optimizer(model, cfg, stage, n_contrastive if stage == "contrastive" else n_regression)
    if state is not None and stage != "done":
        opt.load_state_dict(state["optimizer"])
        sched.load_state_dict(state["scheduler"])

    def save_checkpoint():
        tmp = ckpt_path.with_name("checkpoint.pt.tmp")
        torch.save({"model": model.state_dict(), "optimizer": opt.state_dict(),
                    "scheduler": sched.state_dict(), "stage": stage, "step": step,
                    "elapsed": elapsed + (time.time() - t_start), "rng": _rng_state(rng),
                    "torch_rng": torch.get_rng_state(),
                    "train_config": json.dumps(dataclasses.asdict(cfg))}, tmp)
        tmp.replace(ckpt_path)

    log_file = open(out / "log.jsonl", "a")
    t_start = time.time()
    last_ckpt = time.time()
    done_before = step + (n_contrastive if stage == "regression" else 0) + (total if stage == "done" else 0)
    bar = _Progress(total, min(done_before, total), progress, show_progress)
    loss_cfg = LossConfig()
    try:
        while stage != "done":
            stage_total = n_contrastive if stage == "contrastive" else n_regression
            if step >= stage_total:
                if stage == "contrastive":
                    stage, step = "regression", 0
                    opt, sched = _make_optimizer(model, cfg, stage, n_regression)
                else:
                    stage = "done"
                save_checkpoint()
                continue
            if cancel is not None and cancel.is_set():
                save_checkpoint()
                raise Cancelled("training cancelled; resume continues from the last checkpoint")
            model.train()
            if stage == "contrastive":
                p, q = contrastive_batch(shapes, cfg.contrastive_batch, rng)
                with autocast(device, cfg.bf16):
                    z = model.project(torch.from_numpy(np.concatenate([p, q])).to(device))
                loss = nt_xent(z[: len(p)], z[len(p):], loss_cfg.temperature)
                parts = {}
            else:
                if not cfg.finetune_encoder:
                    model.encoder.eval()          # frozen: BatchNorm uses its running stats
                patches, gt, gt_n, tgt, tgt_n = regression_batch(shapes, cfg.regression_batch, cfg.gt_points, rng)
                with autocast(device, cfg.bf16):
                    if cfg.finetune_encoder:
                        feats = model.encoder(torch.from_numpy(patches).to(device))
                    else:
                        with torch.no_grad():
                            feats = model.encoder(torch.from_numpy(patches).to(device))
                    out6 = model.regressor(feats).float()
                disp = out6[:, :3]
                normal = torch.nn.functional.normalize(out6[:, 3:], dim=1, eps=1e-8)
                if cfg.loss == "joint":
                    # "index": the normal of the clean point this noisy centre was made from.
                    index_normal = torch.from_numpy(tgt_n).to(device) if cfg.normal_target == "index" else None
                    loss, parts = joint_loss(disp, normal, torch.from_numpy(gt).to(device),
                                             torch.from_numpy(gt_n).to(device), loss_cfg,
                                             normal_target=index_normal, normal_loss_kind=cfg.normal_loss)
                else:
                    loss, parts = fixed_target_loss(disp, normal, torch.from_numpy(tgt).to(device),
                                                    torch.from_numpy(tgt_n).to(device), loss_cfg)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            sched.step()
            step += 1
            done = step + (n_contrastive if stage == "regression" else 0)
            if step % 10 == 0 or step == stage_total:
                rec = {"stage": stage, "step": step, "loss": round(loss.item(), 6),
                       "lr": sched.get_last_lr()[0], "time": round(elapsed + time.time() - t_start, 1)}
                rec.update({k: round(v, 6) for k, v in parts.items()})
                log_file.write(json.dumps(rec) + "\n")
                log_file.flush()
            bar.update(done, f"{stage} {step}/{stage_total}", {"loss": f"{loss.item():.4f}"})
            if time.time() - last_ckpt > cfg.checkpoint_minutes * 60:
                save_checkpoint()
                last_ckpt = time.time()
    finally:
        bar.close()
        log_file.close()

    wall = elapsed + time.time() - t_start
    weights = out / "model.safetensors"
    model.eval()
    card = {"preset": cfg.preset, "shapes": [s.name for s in shapes], "train_config": dataclasses.asdict(cfg),
            "contrastive_steps": n_contrastive, "regression_steps": n_regression,
            "wall_seconds": round(wall, 1), "noise_levels": list(NOISE_LEVEL_SETS[cfg.noise_levels])}
    save_model(model.cpu(), weights, {"training": card})
    (out / "training.json").write_text(json.dumps(card, indent=2))
    table = None
    if validation_dir is not None and Path(validation_dir).is_dir():
        table = validate(weights, validation_dir, validation_points, log)
    write_model_card(out / "MODEL_CARD.md", card, table)
    log(f"wrote {weights} ({wall / 60:.1f} min)")
    return weights


def validate(weights, mesh_dir, n_points, log=print):
    """The eval command's table on held-out meshes, for the model card."""
    from ..evaluation.evaluate import evaluate, format_table
    from ..formats.meshes import read_mesh
    from ..model import load_model

    shapes = [(p.stem, *read_mesh(p)) for p in find_meshes(mesh_dir)]
    log(f"validating on {len(shapes)} meshes from {mesh_dir} ({n_points} points each)")
    result = evaluate(shapes, load_model(weights), n_points=n_points, log=log)
    return format_table(result)


def export_checkpoint(checkpoint, weights_path):
    """Weights + config from a (possibly unfinished) run's checkpoint, e.g. to try it early."""
    state = torch.load(checkpoint, map_location="cpu", weights_only=True)
    cfg = TrainConfig(**json.loads(state["train_config"]))
    model = build_model(get_preset(cfg.preset))
    model.load_state_dict(state["model"])
    return save_model(model.eval(), weights_path, {"checkpoint": {"stage": state["stage"], "step": state["step"]}})


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
    if card.get("history"):
        lines[-1:-1] = ["- Earlier runs this model continues:"] + [f"  - {h}" for h in card["history"]]
    if validation_table:
        lines += ["## Validation", "", validation_table, ""]
    Path(path).write_text("\n".join(lines))


def main(argv=None):
    parser = argparse.ArgumentParser(
        prog="run.py train",
        description="Train a CLJN model (contrastive stage, then the joint-loss regressor). "
                    "Defaults are the paper's hyper-parameters; see the README for the CPU recipe.")
    parser.add_argument("meshes", nargs="*", help="mesh files or folders (.off/.obj/.ply); "
                        f"default: {DEFAULT_TRAIN_DIR}")
    parser.add_argument("--out", "-o", required=True, help="output folder (weights, config, card, log, checkpoint)")
    parser.add_argument("--resume", action="store_true", help="continue from OUT/checkpoint.pt")
    parser.add_argument("--synthetic", nargs="*", default=[], metavar="SHAPE",
                        help="add built-in CAD-like shapes (box, cylinder, star, octahedron, stepped_block, ...)")
    parser.add_argument("--thin-parts", type=int, default=0, metavar="N",
                        help="add N procedural thin-part shapes (plates, plate pairs, tubes, open "
                             "containers, L/T/U/I/Z profiles, gears)")
    parser.add_argument("--quick", action="store_true", help="small schedule (minutes), as Blender's button")
    parser.add_argument("--cache-dir", default=str(DEFAULT_CACHE), help="where sampled clouds are cached")
    parser.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    parser.add_argument("--validation-dir", default=str(DEFAULT_VALIDATION_DIR),
                        help="held-out meshes for the model card's table (skipped if absent; '' to skip)")
    parser.add_argument("--validation-points", type=int, default=20_000)
    for field in dataclasses.fields(TrainConfig):
        flag = "--" + field.name.replace("_", "-")
        if field.type == "bool":
            parser.add_argument(flag, type=lambda s: s.lower() in ("1", "true", "yes"), default=None,
                                metavar="BOOL", help=f"default {field.default}")
        else:
            kind = {"int": int, "float": float}.get(field.type, str)
            parser.add_argument(flag, type=kind, default=None, help=f"default {field.default!r}")
    args = parser.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    sources = []
    try:
        for item in args.meshes or [str(DEFAULT_TRAIN_DIR)]:
            path = Path(item)
            sources += [str(p) for p in find_meshes(path)] if path.is_dir() else [str(path)]
        sources += [f"shape:{name}" for name in args.synthetic]
        sources += [f"thin:{i}" for i in range(args.thin_parts)]
        overrides = {f.name: getattr(args, f.name) for f in dataclasses.fields(TrainConfig)
                     if getattr(args, f.name) is not None}
        train_model(sources, args.out, resume=args.resume, quick=args.quick, show_progress=True,
                    log=lambda m: print(m, flush=True), cache_dir=args.cache_dir,
                    validation_dir=args.validation_dir or None, validation_points=args.validation_points,
                    **overrides)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except Cancelled as exc:
        print(str(exc), file=sys.stderr)
        return 130
    except KeyboardInterrupt:
        print("interrupted; rerun with --resume to continue from the last checkpoint", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
