"""The training loop of ``geopose train init|refine``: AdamW + cosine, gradient accumulation,
mixed precision on CUDA, resumable checkpoints, CSV logs, a progress bar, and
multi-process data parallelism through ``torch.distributed`` (torchrun / DDP).

Under torchrun (``WORLD_SIZE`` > 1) every process renders its own batches with
its own seed (``seed + rank``); rank 0 writes logs, checkpoints and the model.
"""

from __future__ import annotations

import csv
import gc
import math
import os
import sys
import time
from collections.abc import Callable
from contextlib import nullcontext
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import torch
import torch.distributed as dist
from torch import Tensor, nn

from ..contract import MODEL_DETECTOR_PX
from ..errors import InputError
from ..images import normalize_minmax
from ..nets import BackboneConfig, InitNet, NetConfig, RefineNet, build_model, load_model, save_model
from . import recipe as R
from .augment import augment
from .data import BankSource, OnTheFlySource, Renderer
from .losses import CRANIUM, TOTAL, VESSELS, LossWeights, init_loss, refine_loss
from .population import TrainingSubject
from .poses import PerturbationScale

CHECKPOINT_NAME = "checkpoint.pt"
LOG_NAME = "log.csv"
#: Fraction of the optimiser steps used for a linear learning-rate warm-up.
WARMUP_FRACTION = 0.03
#: The cosine schedule ends at this fraction of the peak learning rate.
FINAL_LR_FRACTION = 0.01


@dataclass(frozen=True)
class TrainConfig:
    """Everything that defines a training run (recorded in checkpoints and model files).

    ``steps`` counts optimiser steps of ``batch_size x accumulation`` samples per process.
    ``render_px`` is the rendered detector resolution (resized to ``image_px``, the network's input
    size on the model detector's field of view). ``bank_size`` > 0 pre-renders that many samples
    per process and draws from them. ``pairing``: how Refine sees its image pair (``nets.models``).
    """

    kind: str
    steps: int = 1000
    batch_size: int = R.BATCH_SIZE
    accumulation: int = 0
    lr: float = R.LEARNING_RATE
    weight_decay: float = R.WEIGHT_DECAY
    depth: int = 18
    base_width: int = 64
    render_px: int = 256
    image_px: int = 256
    bank_size: int = 0
    seed: int = 0
    amp: bool = True
    weights: LossWeights = field(default_factory=LossWeights)
    init_model: str | None = None
    calibration_samples: int = 64
    checkpoint_every: int = 100
    log_every: int = 10
    #: Percentiles the network's MAP input is clipped to at inference (recorded in the model file
    #: and the manifest); ``dsa_look_p`` of the training images get that chain (``augment.dsa_map``).
    input_clip: tuple[float, float] = R.INPUT_CLIP_PERCENTILES
    dsa_look_p: float = R.DSA_LOOK_P
    #: A model file of the same kind and architecture whose weights start the run (fine-tuning).
    start_from: str | None = None
    pairing: str = "siamese"

    def __post_init__(self) -> None:
        if self.kind not in ("init", "refine"):
            raise ValueError(f"training kind must be 'init' or 'refine', got {self.kind!r}")
        if self.steps < 1 or self.batch_size < 1 or self.accumulation < 0:
            raise ValueError("steps and batch_size must be positive and accumulation >= 0")
        if self.image_px < 32 or MODEL_DETECTOR_PX % self.image_px:
            raise ValueError(f"image_px must be a divisor of {MODEL_DETECTOR_PX} of at least 32 (the model detector is "
                             f"downsampled to it at inference), got {self.image_px}")
        if self.kind == "refine" and self.init_model is None and self.calibration_samples > 0:
            raise ValueError("Refine training needs --init-model (encoder initialisation and calibration)")

    @property
    def accumulation_steps(self) -> int:
        if self.accumulation:
            return self.accumulation
        return R.INIT_ACCUMULATION if self.kind == "init" else R.REFINE_ACCUMULATION

    def net_config(self) -> NetConfig:
        channels = 2 if self.pairing == "stacked" else 1
        return NetConfig(self.kind, BackboneConfig(depth=self.depth, base_width=self.base_width, in_channels=channels),
                         pairing=self.pairing)

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> "TrainConfig":
        values = dict(data)
        values["weights"] = LossWeights(**values.get("weights", {}))
        if "input_clip" in values:
            values["input_clip"] = tuple(float(v) for v in values["input_clip"])
        return cls(**values)


def _distributed() -> tuple[int, int]:
    """(rank, world size) of the process group (0, 1 without one)."""
    if dist.is_initialized():
        return dist.get_rank(), dist.get_world_size()
    return 0, 1


class Progress:
    """A one-line progress bar on stderr (a plain line every ``log_every`` steps when not a terminal)."""

    def __init__(self, total: int, start: int, enabled: bool) -> None:
        self.total, self.start, self.enabled = total, start, enabled
        self.t0 = time.time()
        self.tty = sys.stderr.isatty()

    def update(self, step: int, text: str, force: bool = False) -> None:
        if not self.enabled or not (self.tty or force):
            return
        done = step / self.total
        bar = "#" * int(30 * done) + "." * (30 - int(30 * done))
        rate = (step - self.start) / max(time.time() - self.t0, 1e-6)
        eta = (self.total - step) / rate if rate > 0 else float("nan")
        line = f"[{bar}] {step}/{self.total} {text} eta {eta:.0f}s"
        print(("\r" + line) if self.tty else line, end="" if self.tty else "\n", file=sys.stderr, flush=True)

    def close(self) -> None:
        if self.enabled and self.tty:
            print(file=sys.stderr)


def _tenths(bar: Progress, text: str) -> Callable[[int, int], None]:
    """A ``progress(done, total)`` callback drawing ``bar``, with a plain line per tenth off a terminal."""
    last = [-1]

    def report(done: int, total: int) -> None:
        tenth = 10 * done // total
        bar.update(done, text, force=tenth != last[0])
        last[0] = tenth

    return report


def _lr_lambda(total: int):
    warm = max(1, int(WARMUP_FRACTION * total))

    def factor(step: int) -> float:
        if step < warm:
            return (step + 1) / warm
        progress = min(1.0, (step - warm) / max(1, total - warm))
        return FINAL_LR_FRACTION + (1 - FINAL_LR_FRACTION) * 0.5 * (1 + math.cos(math.pi * progress))

    return factor


def init_encoder_from(refine: RefineNet, init: InitNet) -> None:
    """Copy the Init trunk (everything but its heads) into Refine's encoder. A stacked encoder's first
    layer gets Init's filters on the target channel and their negatives on the render channel, so it
    starts out seeing where the two images differ."""
    state = {k: v for k, v in init.net.state_dict().items() if not k.startswith("fc.")}
    if refine.config.pairing == "stacked":
        state["conv1.weight"] = torch.cat((state["conv1.weight"], -state["conv1.weight"]), dim=1)
    refine.net.backbone.load_state_dict(state, strict=True)


@torch.no_grad()
def calibrate_perturbation(init: InitNet, renderer: Renderer, samples: int, gen: torch.Generator) -> PerturbationScale:
    """Refine perturbation sd from Init's residuals on ``samples`` fresh renders (views from metadata)."""
    from ..contract import VIEW_PA
    from .poses import calibrated_scale

    from ..nets.predictors import TorchInit

    source = OnTheFlySource(renderer, "init")
    preds, refs, views = [], [], []
    predictor = TorchInit(init)
    for start in range(0, samples, 8):
        batch = source.batch(min(8, samples - start), gen)
        pose, _, _ = predictor.predict(batch.target[:, TOTAL : TOTAL + 1].cpu().numpy(), (batch.view != VIEW_PA).cpu().numpy())
        preds.append(torch.as_tensor(pose, device=batch.pose.device))
        refs.append(batch.pose.double())
        views.append(batch.view)
    return calibrated_scale(torch.cat(preds), torch.cat(refs), torch.cat(views))


def _save_checkpoint(path: Path, model: nn.Module, optimiser, scheduler, step: int, config: TrainConfig, extra: dict) -> None:
    tmp = path.with_suffix(".tmp")
    torch.save(
        {
            "step": step,
            "config": config.to_dict(),
            "model": model.state_dict(),
            "optimiser": optimiser.state_dict(),
            "scheduler": scheduler.state_dict(),
            **extra,
        },
        tmp,
    )
    os.replace(tmp, path)


def _start_weights(config: TrainConfig) -> nn.Module:
    """The model ``config.start_from`` names, refused unless it is of the run's kind and architecture."""
    source = load_model(config.start_from)
    if source.config != config.net_config():
        raise InputError(f"{config.start_from} is a {source.config.kind} network with {source.config.backbone}, but this "
                         f"run trains a {config.kind} network with {config.net_config().backbone}: pass the same "
                         "--depth and --width as that model, or start from another one")
    return source


def train(
    config: TrainConfig,
    subjects: list[TrainingSubject],
    out_dir: str | os.PathLike,
    *,
    device: str | torch.device | None = None,
    data_recipe: dict | None = None,
    max_seconds: float | None = None,
    progress: bool = True,
) -> Path:
    """Train (or resume from ``out_dir/checkpoint.pt``) and write ``out_dir/<kind>.pt``; returns that path.

    ``subjects`` are moved to ``device`` (default: CUDA of this rank if available).
    ``max_seconds`` stops early (after a checkpoint) when the wall-clock budget is spent;
    the model file then records the steps actually run. Launched by torchrun (``WORLD_SIZE``
    > 1) without a process group, it creates one and destroys it after a successful run.
    """
    owns_group = int(os.environ.get("WORLD_SIZE", "1")) > 1 and not dist.is_initialized()
    if owns_group:
        dist.init_process_group("nccl" if torch.cuda.is_available() else "gloo")
    path = _train(config, subjects, out_dir, device=device, data_recipe=data_recipe, max_seconds=max_seconds,
                  progress=progress)
    if owns_group:
        # The DDP wrapper's reducer holds the group; collect it first, so that no backend thread
        # outlives the group into interpreter shutdown (an abort at exit otherwise).
        gc.collect()
        dist.destroy_process_group()
    return path


def _train(
    config: TrainConfig,
    subjects: list[TrainingSubject],
    out_dir: str | os.PathLike,
    *,
    device: str | torch.device | None,
    data_recipe: dict | None,
    max_seconds: float | None,
    progress: bool,
) -> Path:
    """:func:`train`'s body, inside the process group when there is one."""
    rank, world = _distributed()
    if device is None:
        device = torch.device(f"cuda:{rank % torch.cuda.device_count()}") if torch.cuda.is_available() else torch.device("cpu")
    device = torch.device(device)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    ckpt_path = out / CHECKPOINT_NAME
    resume = torch.load(ckpt_path, map_location="cpu", weights_only=True) if ckpt_path.is_file() else None
    if resume is not None:
        saved = TrainConfig.from_dict(resume["config"])
        if replace(saved, steps=config.steps) != replace(config, steps=config.steps):
            raise ValueError(f"{ckpt_path} was written by a different configuration; use a new output folder or the same options")
    torch.manual_seed(config.seed + rank)
    subjects = [s.to(device) for s in subjects]
    renderer = Renderer(subjects, config.render_px, config.image_px)
    data_gen = torch.Generator(device).manual_seed(config.seed * 7919 + rank)
    aug_gen = torch.Generator(device).manual_seed(config.seed * 104729 + rank + 1)

    model = build_model(config.net_config()).to(device)
    if config.start_from is not None and resume is None:
        model.load_state_dict(_start_weights(config).state_dict())
    perturbation = PerturbationScale()
    if config.kind == "init":
        model.net.fc.domain.requires_grad_(False)  # the domain classifier is not trained here
    elif config.init_model is not None:
        init_net = load_model(config.init_model, device)
        if resume is None and config.start_from is None:
            init_encoder_from(model, init_net)
        if config.calibration_samples > 0:
            perturbation = (
                PerturbationScale.from_dict(resume["perturbation"])
                if resume is not None
                else calibrate_perturbation(init_net, renderer, config.calibration_samples, data_gen)
            )
        del init_net
    source = OnTheFlySource(renderer, config.kind, perturbation)
    if config.bank_size:
        bank_bar = Progress(config.bank_size, 0, enabled=progress and rank == 0)
        source = BankSource(source, config.bank_size, data_gen, progress=_tenths(bank_bar, "samples pre-rendered"))
        bank_bar.close()

    params = [p for p in model.parameters() if p.requires_grad]
    optimiser = torch.optim.AdamW(params, lr=config.lr, weight_decay=config.weight_decay)
    scheduler = torch.optim.lr_scheduler.LambdaLR(optimiser, _lr_lambda(config.steps))
    step = 0
    if resume is not None:
        model.load_state_dict(resume["model"])
        optimiser.load_state_dict(resume["optimiser"])
        scheduler.load_state_dict(resume["scheduler"])
        step = int(resume["step"])
        if len(resume["data_rng"]) != world:
            raise ValueError(f"{ckpt_path} was written by {len(resume['data_rng'])} processes; resume with as many")
        data_gen.set_state(resume["data_rng"][rank])
        aug_gen.set_state(resume["aug_rng"][rank])
    wrapped: nn.Module = model
    if world > 1:
        wrapped = nn.parallel.DistributedDataParallel(model, device_ids=[device.index] if device.type == "cuda" else None)
    use_amp = config.amp and device.type == "cuda"
    autocast = (lambda: torch.autocast("cuda", dtype=torch.bfloat16)) if use_amp else nullcontext

    log_path = out / LOG_NAME
    log_file = None
    writer = None
    bar = Progress(config.steps, step, enabled=progress and rank == 0)
    t_start = time.time()
    extra_state = lambda: {  # noqa: E731
        "perturbation": perturbation.to_dict(),
        "data_rng": _gather_states(data_gen, world),
        "aug_rng": _gather_states(aug_gen, world),
    }
    try:
        model.train()
        while step < config.steps:
            t0 = time.time()
            terms_sum: dict[str, float] = {}
            loss_sum = 0.0
            for micro in range(config.accumulation_steps):
                batch = source.batch(config.batch_size, data_gen)
                image = augment(batch.target[:, TOTAL : TOTAL + 1], aug_gen, batch.target[:, CRANIUM : CRANIUM + 1],
                                vessels=batch.target[:, VESSELS : VESSELS + 1], dsa_p=config.dsa_look_p,
                                clip=tuple(config.input_clip))
                sync = nullcontext() if (world == 1 or micro == config.accumulation_steps - 1) else wrapped.no_sync()
                with sync:
                    with autocast():
                        if config.kind == "init":
                            raw, logits = wrapped(image, batch.view)
                        else:
                            raw = wrapped(image, normalize_minmax(batch.render), batch.view)
                    if config.kind == "init":
                        loss, terms = init_loss(raw, logits, batch, renderer, config.weights)
                    else:
                        loss, terms = refine_loss(raw, batch, config.weights)
                    (loss / config.accumulation_steps).backward()
                loss_sum += float(loss.detach()) / config.accumulation_steps
                for k, v in terms.items():
                    terms_sum[k] = terms_sum.get(k, 0.0) + v / config.accumulation_steps
            nn.utils.clip_grad_norm_(params, 10.0)
            optimiser.step()
            optimiser.zero_grad(set_to_none=True)
            scheduler.step()
            step += 1
            dt = time.time() - t0
            images_per_s = config.batch_size * config.accumulation_steps * world / dt
            out_of_time = max_seconds is not None and time.time() - t_start > max_seconds
            if rank == 0:
                row = {"step": step, "loss": loss_sum, **terms_sum, "lr": scheduler.get_last_lr()[0], "images_per_s": images_per_s, "elapsed_s": time.time() - t_start}
                if writer is None:
                    new = not log_path.is_file()
                    log_file = open(log_path, "a", newline="")
                    writer = csv.DictWriter(log_file, fieldnames=list(row))
                    if new:
                        writer.writeheader()
                writer.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in row.items()})
                log_file.flush()
                bar.update(step, f"loss {loss_sum:.4f} {images_per_s:.1f} img/s", force=step % config.log_every == 0)
            stop = _agree(out_of_time, device, world)
            if step % config.checkpoint_every == 0 or step == config.steps or stop:
                states = extra_state()
                if rank == 0:
                    _save_checkpoint(ckpt_path, model, optimiser, scheduler, step, config, states)
            if stop:
                break
    finally:
        bar.close()
        if log_file is not None:
            log_file.close()
    model_path = out / f"{config.kind}.pt"
    if rank == 0:
        metadata = {
            "training": {
                "config": config.to_dict(),
                "steps_run": step,
                "world_size": world,
                "device": device.type,
                "mixed_precision": "bfloat16" if use_amp else "none",
                "perturbation": perturbation.to_dict() if config.kind == "refine" else None,
                "data": data_recipe or {},
                "seconds": time.time() - t_start,
            }
        }
        save_model(model, model_path, metadata)
    if world > 1:
        dist.barrier()
    return model_path


def _gather_states(gen: torch.Generator, world: int) -> list[Tensor]:
    """Every rank's generator state (rank order), so a resumed run continues each stream."""
    state = gen.get_state()
    if world == 1:
        return [state]
    out = [torch.empty_like(state) for _ in range(world)]
    dist.all_gather_object(out, state)
    return out


def _agree(flag: bool, device: torch.device, world: int) -> bool:
    """True on every rank if any rank says so (keeps ranks in step when stopping early)."""
    if world == 1:
        return flag
    t = torch.tensor([1.0 if flag else 0.0], device=device)
    dist.all_reduce(t, op=dist.ReduceOp.MAX)
    return bool(t.item() > 0)
