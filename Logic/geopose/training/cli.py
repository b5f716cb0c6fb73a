"""``geopose train``: build a canonical population, train Init/Refine, evaluate, ship models.

Sub-commands: ``population`` (canonicalise phantoms or a CTA folder -> cache ``.pt``), ``arteries`` (the
artery classifier of the computed CTA vessel mask -> ``.json``),
``init`` and ``refine`` (train from a cache), ``evaluate`` (held-out metrics JSON),
``ship`` (fp16 torch and ONNX model files + manifest into a models folder).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


from . import recipe as R
from ..contract import MODEL_DETECTOR_PX
from .losses import LossWeights
from .manifest import file_entry, model_entry, verify_manifest, write_manifest
from ..nets.manifest import read_manifest
from .population import folder_population, load_population, phantom_population, phantom_template, save_population
from .arteries import THRESHOLD as ARTERY_THRESHOLD
from .trainer import TrainConfig, train
from ..errors import InputError
from ..phantom.real_head import DEFORM_AMPLITUDE_MM, DEFORM_SCALE_SD


def _seeds(text: str) -> list[int]:
    """``"100-107"`` or ``"1,2,5"`` -> seeds."""
    try:
        if "-" in text:
            lo, hi = (int(v) for v in text.split("-"))
            return list(range(lo, hi + 1))
        return [int(v) for v in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"seeds must look like 100-107 or 1,2,5, got {text!r}") from None


def _say(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def _population(args: argparse.Namespace) -> int:
    if (args.phantoms is None) == (args.folder is None):
        raise InputError("give exactly one of --phantoms SEEDS or --folder DIR")
    if args.phantoms is not None:
        subjects, report = phantom_population(args.phantoms, args.spacing, args.template_seed, progress=_say, workers=args.workers)
        recipe = {"source": "phantom", "seeds": args.phantoms, "spacing_mm": args.spacing, "template_seed": args.template_seed, "canonicalisation_error": report}
    else:
        template = args.template if args.template else phantom_template(args.template_seed, args.spacing)
        subjects = folder_population(args.folder, template, progress=_say)
        recipe = {"source": "folder", "folder": str(args.folder),
                  "template": str(args.template) if args.template else {"phantom_seed": args.template_seed, "spacing_mm": args.spacing}}
    save_population(args.out, subjects, recipe)
    if args.phantoms is not None:
        rot = [r["rotation_deg"] for r in report]
        _say(f"canonicalisation error vs truth: rotation max {max(rot):.2f} deg, mean {sum(rot) / len(rot):.2f} deg")
    _say(f"wrote {len(subjects)} subjects to {args.out}")
    return 0


def _variants(args: argparse.Namespace) -> int:
    from ..cta import cranium_mask_from_cta, load_cta, save_volume
    from ..phantom import labels as L
    from ..phantom.real_head import deformed_head, load_headsq, with_arteries

    if args.headsq:
        cta, name = load_headsq(args.headsq), "headsq"
    else:
        cta, name = load_cta(args.cta), args.cta.name.split(".")[0]
    cranium = cranium_mask_from_cta(cta)
    args.out.mkdir(parents=True, exist_ok=True)
    for seed in args.arteries:
        with_vessels, labels, _ = with_arteries(cta, seed, cranium=cranium)
        ct, lab = deformed_head(with_vessels, labels, seed, amplitude_mm=args.amplitude_mm, scale_sd=args.scale_sd)
        save_volume(ct, args.out / f"{name}-{seed}.nii.gz")
        save_volume(lab.like(L.vessel_mask(lab.array).astype("uint8")), args.out / f"{name}-{seed}_vessels.nii.gz")
        _say(f"{name}-{seed}: arteries of phantom {seed}, deformed")
    _say(f"wrote {len(args.arteries)} variants to {args.out}; next: geopose train population --folder {args.out}")
    return 0


def _train(args: argparse.Namespace) -> int:
    loaded = [load_population(path) for path in args.population]
    subjects = [subject for population, _ in loaded for subject in population]
    recipe = loaded[0][1] if len(loaded) == 1 else {"populations": [r for _, r in loaded]}
    config = TrainConfig(
        kind=args.kind,
        steps=args.steps,
        batch_size=args.batch_size,
        accumulation=args.accumulation,
        lr=args.lr,
        depth=args.depth,
        base_width=args.width,
        render_px=args.render_px,
        bank_size=args.bank_size,
        seed=args.seed,
        amp=not args.no_amp,
        weights=LossWeights(render=args.render_loss, param=args.param_weight),
        init_model=str(args.init_model) if getattr(args, "init_model", None) else None,
        checkpoint_every=args.checkpoint_every,
        input_clip=tuple(args.input_clip),
        dsa_look_p=args.dsa_look_p,
        calibration_samples=getattr(args, "calibration_samples", 64),
        start_from=str(args.start_from) if args.start_from else None,
        image_px=args.image_px,
        pairing=getattr(args, "pairing", "siamese"),
    )
    max_seconds = args.max_minutes * 60 if args.max_minutes else None
    path = train(config, subjects, args.out, device=args.device, data_recipe=recipe, max_seconds=max_seconds)
    _say(f"wrote {path}")
    return 0


def _evaluate(args: argparse.Namespace) -> int:
    from ..nets import load_model
    from .evaluate import evaluate

    subjects, _ = load_population(args.population, args.device or "cpu")
    init = load_model(args.init, args.device or "cpu")
    refine = load_model(args.refine, args.device or "cpu") if args.refine else None
    metrics = evaluate(init, subjects, samples=args.samples, seed=args.seed, render_px=args.render_px, refine=refine)
    text = json.dumps(metrics, indent=2)
    if args.out:
        Path(args.out).write_text(text + "\n")
    print(text)
    return 0


def _arteries(args: argparse.Namespace) -> int:
    from .arteries import folder_artery_data, phantom_artery_data, save_artery_classifier, train_artery_classifier

    if args.phantoms is None and args.folder is None:
        raise InputError("give --phantoms SEEDS, --folder DIR or both: CTAs whose arteries are known")
    data, recipe = [], {}
    if args.phantoms is not None:
        for spacing in args.spacing:
            data += phantom_artery_data(args.phantoms, spacing, progress=_say)
        recipe["phantoms"] = {"seeds": args.phantoms, "spacing_mm": args.spacing}
    if args.folder is not None:
        data += folder_artery_data(args.folder, progress=_say)
        recipe["folder"] = str(args.folder)
    classifier = train_artery_classifier(data, epochs=args.epochs, seed=args.seed, threshold=args.threshold, recipe=recipe)
    save_artery_classifier(classifier, args.out)
    _say(f"wrote {args.out} ({classifier.training['voxels']} voxels, final loss {classifier.training['final_loss']:.3f}); "
         f"ship it as Resources/Models/artery_classifier.json")
    return 0


def _ship(args: argparse.Namespace) -> int:
    from ..nets import export_onnx, load_model, read_model_header, save_model

    models_dir = Path(args.models_dir)
    metrics = json.loads(Path(args.metrics).read_text()) if args.metrics else {}
    given = {kind: source for kind, source in (("init", args.init), ("refine", args.refine)) if source is not None}
    if not given:
        raise InputError("give --init, --refine or both: the networks to ship")
    entries, notes = {}, {"validation": metrics}
    if len(given) == 1:
        # The other network stays as shipped: its entry (verified first) is kept as it is, and the
        # note and validation of the ship it came with are kept beside the new ones.
        kept = "refine" if "init" in given else "init"
        verify_manifest(models_dir)
        previous = read_manifest(models_dir)
        entries[kept] = previous["models"][kept]
        notes["previous_ship"] = {k: previous[k] for k in ("note", "validation", "previous_ship") if previous.get(k)}
    for kind, source in given.items():
        header = read_model_header(source)
        module = load_model(source)
        if module.config.kind != kind:
            raise InputError(f"{source} holds a {module.config.kind} network, expected {kind}")
        target = save_model(module, models_dir / f"geopose_{kind}.pt", header["metadata"], dtype="float16")
        image_px = int(header["metadata"].get("training", {}).get("config", {}).get("image_px", MODEL_DETECTOR_PX))
        graph = export_onnx(load_model(target), models_dir / f"geopose_{kind}.onnx", image_px=image_px, weights="float16")
        entries[kind] = model_entry(target, onnx=file_entry(graph), training=header["metadata"].get("training", {}))
    if args.note:
        notes["note"] = args.note
    write_manifest(models_dir, {kind: entries[kind] for kind in ("init", "refine")}, notes)
    total = sum(entries[kind]["bytes"] + entries[kind]["onnx"]["bytes"] for kind in given)
    _say(f"shipped {' and '.join(given)} ({total / 1e6:.1f} MB) with manifest to {models_dir}")
    return 0


def _training_options(p: argparse.ArgumentParser, kind: str) -> None:
    p.add_argument("--population", required=True, type=Path, nargs="+",
                   help="population cache(s) from `geopose train population` (several: their subjects together)")
    p.add_argument("--out", required=True, type=Path, help="run folder (checkpoint, log.csv, model); reruns resume")
    p.add_argument("--steps", type=int, default=1000, help="optimiser steps")
    p.add_argument("--max-minutes", type=float, default=None, help="stop (with a checkpoint) after this wall time")
    p.add_argument("--batch-size", type=int, default=R.BATCH_SIZE)
    p.add_argument("--accumulation", type=int, default=0, help=f"micro-batches per step (0: recipe, {R.INIT_ACCUMULATION} Init / {R.REFINE_ACCUMULATION} Refine)")
    p.add_argument("--lr", type=float, default=R.LEARNING_RATE)
    p.add_argument("--depth", type=int, default=18, choices=(18, 34))
    p.add_argument("--width", type=int, default=64, help="ResNet stem width (64 = standard)")
    p.add_argument("--render-px", type=int, default=256, help="rendered detector pixels (resized to --image-px)")
    p.add_argument("--image-px", type=int, default=256,
                   help="the network's input size on the model detector's field of view (256: the published models; "
                        "a divisor of 256 such as 128 trains about 4x faster on a CPU; inference downsamples to it)")
    p.add_argument("--bank-size", type=int, default=0, help="pre-render this many samples (CPU); 0 renders every batch")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--device", default=None, help="cpu, cuda, cuda:1 (default: CUDA if available)")
    p.add_argument("--no-amp", action="store_true", help="disable bfloat16 mixed precision on CUDA")
    p.add_argument("--render-loss", action="store_true", help="Init: add -mNCC and vessel Dice at the predicted pose")
    p.add_argument("--param-weight", type=float, default=1.0, help="weight of the supervised raw-output term")
    p.add_argument("--checkpoint-every", type=int, default=100)
    p.add_argument("--input-clip", type=float, nargs=2, metavar=("LO", "HI"), default=R.INPUT_CLIP_PERCENTILES,
                   help="percentiles the MAP input is clipped to at inference (recorded in the model and manifest)")
    p.add_argument("--dsa-look-p", type=float, default=R.DSA_LOOK_P,
                   help="share of training images made to look like a preprocessed DSA MAP (augment.dsa_map)")
    p.add_argument("--start-from", type=Path, default=None,
                   help=f"a {kind} model file (same --depth/--width) whose weights start the run: fine-tuning")
    if kind == "refine":
        p.add_argument("--init-model", required=True, type=Path, help="trained Init model (encoder init, calibration)")
        p.add_argument("--calibration-samples", type=int, default=64, help="renders used to measure Init's residuals (0: recipe sd)")
        p.add_argument("--pairing", choices=("siamese", "stacked"), default="siamese",
                       help="siamese: one encoder pass per image (the published layout); stacked: target and render "
                            "as two channels of one encoder")
    p.set_defaults(func=_train, kind=kind)


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("train", help="build a training population, train, evaluate and ship GeoPose networks")
    sub = parser.add_subparsers(dest="train_command", required=True)
    p = sub.add_parser("population", help="canonicalise phantoms or a CTA folder into a population cache (.pt)")
    p.add_argument("--phantoms", type=_seeds, default=None, help="phantom seeds, e.g. 100-131")
    p.add_argument("--folder", type=Path, default=None, help="folder of CTAs NAME.nii.gz with NAME_vessels.nii.gz")
    p.add_argument("--template", type=Path, default=None,
                   help="template CTA (folder mode; default: the phantom template, the shipped models' frame)")
    p.add_argument("--template-seed", type=int, default=0, help="phantom whose canonical CTA is the template")
    p.add_argument("--spacing", type=float, default=2.0, help="phantom voxel size (mm)")
    p.add_argument("--workers", type=int, default=1, help="parallel processes for phantom subjects")
    p.add_argument("--out", required=True, type=Path)
    p.set_defaults(func=_population)
    p = sub.add_parser("variants", help="random smooth variants of a real head CT with phantom arteries: a training folder")
    source = p.add_mutually_exclusive_group(required=True)
    source.add_argument("--cta", type=Path, help="a head CT without contrast (any format `geopose register` reads)")
    source.add_argument("--headsq", type=Path, help="VTK's headsq sample (quarter_sidecar.mhd: raw values, upside down)")
    p.add_argument("--arteries", type=_seeds, required=True, help="phantom seeds whose arteries are fitted in, one variant each")
    p.add_argument("--amplitude-mm", type=float, default=DEFORM_AMPLITUDE_MM, help="sd of the B-spline control points (mm)")
    p.add_argument("--scale-sd", type=float, default=DEFORM_SCALE_SD, help="sd of each axis' scale factor")
    p.add_argument("--out", required=True, type=Path, help="folder for NAME-SEED.nii.gz and NAME-SEED_vessels.nii.gz")
    p.set_defaults(func=_variants)
    _training_options(sub.add_parser("init", help="train GeoPose-Init"), "init")
    _training_options(sub.add_parser("refine", help="train GeoPose-Refine from a trained Init"), "refine")
    p = sub.add_parser("arteries", help="train the artery classifier of the computed CTA vessel mask (JSON)")
    p.add_argument("--phantoms", type=_seeds, default=None, help="phantom seeds, e.g. 100-115")
    p.add_argument("--spacing", type=float, nargs="+", default=[1.0], help="phantom voxel sizes (mm), each seed at each")
    p.add_argument("--folder", type=Path, default=None, help="folder of CTAs NAME.nii.gz with artery segmentations NAME_vessels.nii.gz")
    p.add_argument("--epochs", type=int, default=30)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threshold", type=float, default=ARTERY_THRESHOLD, help="probability from which a voxel is kept as artery")
    p.add_argument("--out", required=True, type=Path, help="the classifier file (.json) to write")
    p.set_defaults(func=_arteries)
    p = sub.add_parser("evaluate", help="held-out metrics of trained models (JSON)")
    p.add_argument("--population", required=True, type=Path, help="held-out population cache")
    p.add_argument("--init", required=True, type=Path)
    p.add_argument("--refine", type=Path, default=None)
    p.add_argument("--samples", type=int, default=96)
    p.add_argument("--seed", type=int, default=12345)
    p.add_argument("--render-px", type=int, default=256)
    p.add_argument("--device", default=None)
    p.add_argument("--out", type=Path, default=None)
    p.set_defaults(func=_evaluate)
    p = sub.add_parser("ship", help="write fp16 model files (torch and ONNX) and manifest.json into a models folder")
    p.add_argument("--init", type=Path, default=None, help="Init model file (default: keep the folder's shipped Init)")
    p.add_argument("--refine", type=Path, default=None, help="Refine model file (default: keep the folder's shipped Refine)")
    p.add_argument("--metrics", type=Path, default=None, help="JSON from `geopose train evaluate`")
    p.add_argument("--models-dir", type=Path, default=Path("Resources/Models"))
    p.add_argument("--note", default=None, help="free text recorded in the manifest")
    p.set_defaults(func=_ship)
