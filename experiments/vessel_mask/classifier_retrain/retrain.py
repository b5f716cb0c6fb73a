"""Retrain the artery classifier on today's contrast-threshold tree, with and without the HU read against the subject's
own contrast, and score each on validation phantoms with ``benchmarks/bench_vessels.py``'s ``score``.

Features and labels of every phantom are cached (``--cache``); classifiers are trained with the product's
``train_artery_classifier``; each variant is cut at several probabilities. Written for the product's eleven features
and its classifier before session 56: run it from a worktree of commit d3853a1 (the product now computes the three
extra features itself, and ships the classifier trained on them).

    .venv/bin/python experiments/vessel_mask/classifier_retrain/retrain.py --train 100-115 --more 116-131 --val 6020-6039 \
        --cache /tmp/cls_cache --json rows.jsonl
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[3] / "benchmarks"))
from bench_vessels import write_scored  # noqa: E402

from geopose.bench.cases import seed_range  # noqa: E402
from geopose.cta.arteries import ArteryClassifier, load_artery_classifier  # noqa: E402
from geopose.cta.masks import _back_to_full  # noqa: E402
from geopose.phantom import labels as L  # noqa: E402
from geopose.phantom import make_subject  # noqa: E402
from geopose.training import arteries as training  # noqa: E402
from geopose.training.arteries import train_artery_classifier  # noqa: E402

CUTS = (0.2, 0.3, 0.4, 0.5)


def cached(cache: Path, seed: int, spacing_mm: float, subject=None) -> dict:
    """Features (the product's eleven), labels, indices and tree shape of phantom ``seed`` at ``spacing_mm``."""
    path = cache / f"{seed}_{spacing_mm:g}.npz"
    if not path.exists():
        subject = subject or make_subject(seed, spacing_mm=spacing_mm)
        from geopose.cta.arteries import artery_features
        from geopose.cta.masks import cranium_mask_from_cta, vessel_candidates
        work, tree, _ = vessel_candidates(subject.cta)
        features, idx = artery_features(work, tree, np.asarray(cranium_mask_from_cta(work).array) > 0)
        arteries = L.vessel_mask(subject.labels.array)
        factors = np.asarray(arteries.shape) // np.asarray(tree.shape)
        centre = np.minimum(idx * factors + factors // 2, np.asarray(arteries.shape) - 1)
        labels = arteries[tuple(centre.T)].astype(np.float32)
        np.savez(path, features=features, labels=labels, idx=idx, shape=np.asarray(tree.shape))
    d = np.load(path)
    return {k: d[k] for k in d.files}


def normalised(features: np.ndarray) -> np.ndarray:
    """The eleven features and the three HU columns divided by the tree's median HU (the subject's contrast)."""
    ref = max(float(np.median(features[:, 0])), 0.3)
    return np.concatenate([features, features[:, :3] / ref], axis=1).astype(np.float32)


EXTRA = {"plain": lambda f: f, "normalised": normalised}


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--train", default="100-115")
    ap.add_argument("--more", default="116-131", help="more training seeds for the 'more' variants")
    ap.add_argument("--val", default="6010-6039")
    ap.add_argument("--cache", type=Path, default=Path("/tmp/cls_cache"))
    ap.add_argument("--json", required=True)
    args = ap.parse_args()
    args.cache.mkdir(parents=True, exist_ok=True)
    train = [cached(args.cache, s, sp) for s in seed_range(args.train) for sp in (1.0, 2.0)]
    more = [cached(args.cache, s, sp) for s in seed_range(args.more) for sp in (1.0, 2.0)] if args.more else []
    print("cached training", time.strftime("%X"), flush=True)
    classifiers = {"shipped": ("plain", load_artery_classifier())}
    for name, kind, data in (("retrained", "plain", train), ("retrained+norm", "normalised", train),
                             ("more+norm", "normalised", train + more)):
        t = time.time()
        rows = [(EXTRA[kind](d["features"]), d["labels"]) for d in data]
        training.FEATURES = tuple(range(rows[0][0].shape[1]))  # the trainer sizes its input layer by the feature names
        c = train_artery_classifier(rows)
        classifiers[name] = (kind, c)
        print(name, f"trained in {time.time() - t:.0f} s, loss {c.training['final_loss']:.4f}", flush=True)
        (args.cache / f"{name}.json").write_text(json.dumps(c.as_json()))
    with open(args.json, "w") as f:
        for seed in seed_range(args.val):
            subject = make_subject(seed, spacing_mm=1.0)
            d = cached(args.cache, seed, 1.0, subject)
            work_shape = tuple(d["shape"])
            for name, (kind, c) in classifiers.items():
                p = c.probability(EXTRA[kind](d["features"]))
                for cut in CUTS:
                    kept = np.zeros(work_shape, bool)
                    kept[tuple(d["idx"][p >= cut].T)] = True
                    mask = _back_to_full(subject.cta.like(kept.astype(np.uint8)), subject.cta) > 0
                    write_scored(f, {"seed": seed, "variant": name, "cut": cut}, mask, subject)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
