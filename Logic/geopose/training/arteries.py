"""Train the artery classifier of the computed vessel mask (``cta/arteries.py``) on CTAs whose arteries are known.

Each CTA gives the features of every voxel of its contrast-threshold tree (``cta.masks.vessel_candidates``, exactly as
``geopose register`` computes them) and a label: inside the known arteries or not. Phantoms (their artery labels) or a
folder of ``NAME.nii.gz`` with ``NAME_vessels.nii.gz`` (an artery segmentation on the CTA grid, the layout of
``geopose train population --folder``). A two-layer perceptron is fitted with Adam on the logistic loss.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Callable, Iterable

import numpy as np

from ..cta.arteries import FEATURES, ArteryClassifier, artery_features
from ..cta.masks import cranium_mask_from_cta, vessel_candidates
from ..errors import InputError
from ..volume import Volume

__all__ = ["labelled_features", "phantom_artery_data", "folder_artery_data", "train_artery_classifier", "save_artery_classifier",
           "THRESHOLD"]

#: Probability from which a voxel is kept as artery. Tuned on validation phantoms 6010-6019 at 1 mm, with the canal
#: mouths bridged (experiments/vessel_mask/artery_threshold/artery_threshold.md): at 0.5 voxel precision 90.5 %, carotid
#: centreline recall 93.5 %; at 0.4 88 % and 94.8 %; at 0.3 85 % and 95.6 % (issue 30 asks >= 80 % and >= 95 %); at
#: 0.2 81 % and 96.0 %. Kept for the classifier that also reads the HU against the mask's median (session 56,
#: experiments/vessel_mask/classifier_retrain/classifier_retrain.md; validation 6020-6039: at 0.3 86.5 % and 96.4 %, at
#: 0.5 91.3 % and 95.4 %).
THRESHOLD = 0.3


def labelled_features(cta: Volume, arteries: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Features ``(N, 14)`` of the voxels of ``cta``'s contrast-threshold tree and their labels ``(N,)`` (1: inside
    ``arteries``, a [k, j, i] bool on ``cta``'s grid, read on the working grid by the nearest voxel)."""
    work, tree, _ = vessel_candidates(cta)
    features, idx = artery_features(work, tree, np.asarray(cranium_mask_from_cta(work).array) > 0)
    factors = np.asarray(arteries.shape) // np.asarray(tree.shape)
    centre = idx * factors + factors // 2
    return features, arteries[tuple(np.minimum(centre, np.asarray(arteries.shape) - 1).T)].astype(np.float32)


def phantom_artery_data(seeds: Iterable[int], spacing_mm: float,
                        progress: Callable[[str], None] = lambda _: None) -> list[tuple[np.ndarray, np.ndarray]]:
    """:func:`labelled_features` of the phantoms ``seeds`` written at ``spacing_mm``, their artery labels the truth."""
    from ..phantom import labels as L
    from ..phantom import make_subject

    data = []
    for seed in seeds:
        subject = make_subject(seed, spacing_mm=spacing_mm)
        data.append(labelled_features(subject.cta, L.vessel_mask(subject.labels.array)))
        progress(f"phantom {seed}: {len(data[-1][1])} voxels, {100 * data[-1][1].mean():.0f} % artery")
    return data


def folder_artery_data(folder: Path, progress: Callable[[str], None] = lambda _: None) -> list[tuple[np.ndarray, np.ndarray]]:
    """:func:`labelled_features` of every CTA in ``folder`` with its artery label map, paired as ``geopose train
    population --folder`` pairs them (``population.folder_cases``: ``NAME.nii.gz`` + ``NAME_vessels.nii.gz``)."""
    from ..cta import load_cta
    from .population import folder_cases

    data = []
    for cta_path, vessels_path in folder_cases(folder):
        cta, vessels = load_cta(cta_path), load_cta(vessels_path, check_hu=False)
        if vessels.array.shape != cta.array.shape:
            raise InputError(f"{vessels_path.name} is not on {cta_path.name}'s grid: resample the segmentation onto the CTA")
        data.append(labelled_features(cta, np.asarray(vessels.array) > 0))
        progress(f"{cta_path.name}: {len(data[-1][1])} voxels, {100 * data[-1][1].mean():.0f} % artery")
    return data


def train_artery_classifier(data: list[tuple[np.ndarray, np.ndarray]], *, hidden: int = 32, epochs: int = 30,
                            seed: int = 0, threshold: float = THRESHOLD, recipe: dict | None = None) -> ArteryClassifier:
    """A two-layer perceptron (``hidden`` units per layer) fitted to ``data`` (features, labels) by Adam (lr 3e-3,
    batches of 4096, ``epochs`` passes) on the logistic loss; needs PyTorch."""
    import torch

    x = torch.tensor(np.concatenate([f for f, _ in data]), dtype=torch.float32)
    y = torch.tensor(np.concatenate([t for _, t in data]), dtype=torch.float32)
    if not len(x) or y.min() == y.max():
        raise InputError("the training CTAs give no artery voxels or no other voxels in their contrast-threshold trees: "
                         "give CTAs with contrast and their artery segmentations")
    torch.manual_seed(seed)
    net = torch.nn.Sequential(torch.nn.Linear(len(FEATURES), hidden), torch.nn.ReLU(), torch.nn.Linear(hidden, hidden),
                              torch.nn.ReLU(), torch.nn.Linear(hidden, 1))
    optimiser = torch.optim.Adam(net.parameters(), 3e-3)
    for _ in range(epochs):
        order = torch.randperm(len(x))
        for start in range(0, len(x), 4096):
            batch = order[start:start + 4096]
            loss = torch.nn.functional.binary_cross_entropy_with_logits(net(x[batch])[:, 0], y[batch])
            optimiser.zero_grad()
            loss.backward()
            optimiser.step()
    layers = tuple((m.weight.detach().numpy().astype(np.float32), m.bias.detach().numpy().astype(np.float32))
                   for m in net if isinstance(m, torch.nn.Linear))
    training = {**(recipe or {}), "voxels": int(len(x)), "artery_share": float(y.mean()), "hidden": hidden,
                "epochs": epochs, "seed": seed, "final_loss": float(loss.detach())}
    return ArteryClassifier(layers, threshold, "", training)


def save_artery_classifier(classifier: ArteryClassifier, path: Path) -> None:
    """``classifier`` as JSON (weights to 6 significant digits) at ``path``."""
    data = classifier.as_json()
    for layer in data["layers"]:
        layer["weight"] = [[float(f"{v:.6g}") for v in row] for row in layer["weight"]]
        layer["bias"] = [float(f"{v:.6g}") for v in layer["bias"]]
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_text(json.dumps(data, indent=1) + "\n")
