"""Import published GeoPose Lightning checkpoints without executing pickled code.

A zip-format torch checkpoint holds ``<root>/data.pkl`` (the pickled object tree)
and ``<root>/data/<key>`` (raw tensor storages). :class:`_TensorOnlyUnpickler`
resolves only torch tensor-rebuild functions, storage types and plain containers;
every other global (Lightning classes, callbacks, ``os.system``, ...) becomes an
inert :class:`ForeignObject` that records nothing and runs nothing. Only the
``state_dict`` is used. Sizes are bounded before anything is read or allocated: every
storage's size in the zip directory (:data:`~geopose.limits.MAX_CHECKPOINT_STORAGE_BYTES`,
all together :data:`~geopose.limits.MAX_CHECKPOINT_TOTAL_BYTES`) and every rebuilt tensor
(:data:`~geopose.limits.MAX_CHECKPOINT_TENSOR_ELEMENTS`).
"""

from __future__ import annotations

import collections
import math
import os
import pickle
import zipfile
from pathlib import Path
from typing import Any

import torch

from .. import limits as L
from ..checksums import file_sha256
from ..errors import InputError
from ..jsonio import read_json
from ..resources import default_models_dir
from .model_io import MODEL_SUFFIX, save_model
from .models import InitNet, NetConfig, RefineNet, build_model
from .resnet import BLOCKS_PER_STAGE, BackboneConfig

#: Copy of shared/reference/geopose_checkpoints.json (MIT), shipped in Resources/Models.
PUBLISHED_MANIFEST_NAME = "published_checkpoints.json"


def published_manifest_path() -> Path:
    return default_models_dir() / PUBLISHED_MANIFEST_NAME
#: State-dict prefixes of the published Refine checkpoint that are training-only.
IGNORED_PREFIXES = ("criterion.",)

_STORAGE_DTYPES: dict[str, torch.dtype] = {
    "DoubleStorage": torch.float64,
    "FloatStorage": torch.float32,
    "HalfStorage": torch.float16,
    "BFloat16Storage": torch.bfloat16,
    "LongStorage": torch.int64,
    "IntStorage": torch.int32,
    "ShortStorage": torch.int16,
    "CharStorage": torch.int8,
    "ByteStorage": torch.uint8,
    "BoolStorage": torch.bool,
}


class ForeignObject:
    """Stand-in for any non-tensor object of a checkpoint; accepts and ignores all arguments."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        pass

    def __setstate__(self, state: Any) -> None:
        pass

    def __setitem__(self, key: Any, value: Any) -> None:
        pass

    def append(self, value: Any) -> None:
        pass

    def extend(self, values: Any) -> None:
        pass


class _StorageType:
    def __init__(self, dtype: torch.dtype) -> None:
        self.dtype = dtype


def _rebuild_tensor(storage: Any, offset: int, size: tuple, stride: tuple, *_ignored: Any) -> torch.Tensor:
    if not isinstance(storage, torch.Tensor):
        raise pickle.UnpicklingError("a tensor refers to a storage that is not in the checkpoint")
    if not all(isinstance(v, int) and v >= 0 for v in (*size, *stride, offset)):
        raise pickle.UnpicklingError(f"a tensor has an invalid size/stride/offset {size}/{stride}/{offset}")
    if math.prod(size) > L.MAX_CHECKPOINT_TENSOR_ELEMENTS:
        raise pickle.UnpicklingError(f"a tensor of {math.prod(size)} elements exceeds {L.MAX_CHECKPOINT_TENSOR_ELEMENTS}")
    return storage.as_strided(tuple(size), tuple(stride), int(offset)).clone()


def _rebuild_parameter(data: Any, *_ignored: Any) -> Any:
    return data


_ALLOWED: dict[tuple[str, str], Any] = {
    ("torch._utils", "_rebuild_tensor_v2"): _rebuild_tensor,
    ("torch._utils", "_rebuild_parameter"): _rebuild_parameter,
    ("collections", "OrderedDict"): collections.OrderedDict,
    ("torch", "Size"): tuple,
    ("builtins", "set"): set,
    ("builtins", "frozenset"): frozenset,
}


class _TensorOnlyUnpickler(pickle.Unpickler):
    def __init__(self, file: Any, archive: zipfile.ZipFile, root: str, little_endian: bool) -> None:
        super().__init__(file)
        self._archive = archive
        self._root = root
        self._little_endian = little_endian
        self._storages: dict[str, torch.Tensor] = {}

    def find_class(self, module: str, name: str) -> Any:
        if (module, name) in _ALLOWED:
            return _ALLOWED[(module, name)]
        if module == "torch" and name in _STORAGE_DTYPES:
            return _StorageType(_STORAGE_DTYPES[name])
        return type(name, (ForeignObject,), {"foreign_module": module})

    def persistent_load(self, pid: Any) -> Any:
        if not (isinstance(pid, tuple) and len(pid) >= 3 and pid[0] == "storage"):
            return ForeignObject()
        storage_type, key = pid[1], str(pid[2])
        if not isinstance(storage_type, _StorageType):
            return ForeignObject()
        if key not in self._storages:
            try:
                info = self._archive.getinfo(f"{self._root}/data/{key}")
            except KeyError:
                raise pickle.UnpicklingError(f"storage {key} is missing from the checkpoint") from None
            if info.file_size > L.MAX_CHECKPOINT_STORAGE_BYTES:
                raise pickle.UnpicklingError(f"storage {key} declares {info.file_size} bytes, more than the "
                                             f"{L.MAX_CHECKPOINT_STORAGE_BYTES} a GeoPose network's tensor may have")
            raw = bytearray(self._archive.read(info))
            flat = torch.frombuffer(raw, dtype=torch.uint8) if raw else torch.empty(0, dtype=torch.uint8)
            if flat.numel() % torch.empty((), dtype=storage_type.dtype).element_size():
                raise pickle.UnpicklingError(f"storage {key} has a size that does not fit its dtype")
            values = flat.view(storage_type.dtype)
            if not self._little_endian and values.element_size() > 1:
                values = values.view(torch.uint8).view(-1, values.element_size()).flip(1).reshape(-1).view(storage_type.dtype)
            self._storages[key] = values
        return self._storages[key]


def read_checkpoint_state_dict(path: str | os.PathLike) -> dict[str, torch.Tensor]:
    """The ``state_dict`` tensors of a zip-format torch/Lightning checkpoint, without running its code.

    A bare state dict (a file holding only ``{name: tensor}``) is accepted too.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"checkpoint {path} does not exist")
    problem = f"{path} is not a PyTorch checkpoint"
    remedy = "pass the .ckpt file of a GeoPose release"
    if not zipfile.is_zipfile(path):
        raise InputError(f"{problem} (not a zip-format torch.save file); {remedy}")
    try:
        with zipfile.ZipFile(path) as archive:
            infos = archive.infolist()
            total = sum(i.file_size for i in infos)
            if total > L.MAX_CHECKPOINT_TOTAL_BYTES:
                raise InputError(f"{path} declares {total} bytes of content, more than the {L.MAX_CHECKPOINT_TOTAL_BYTES} a "
                                 f"GeoPose checkpoint may have; {remedy}")
            pickles = [i for i in infos if i.filename.endswith("/data.pkl") and i.filename.count("/") == 1]
            if len(pickles) != 1 or pickles[0].file_size > L.MAX_CHECKPOINT_STORAGE_BYTES:
                raise InputError(f"{problem} (no single data.pkl of a plausible size in the archive); {remedy}")
            root = pickles[0].filename.split("/")[0]
            big = [i for i in infos if i.filename.startswith(f"{root}/data/") and i.file_size > L.MAX_CHECKPOINT_STORAGE_BYTES]
            if big:
                raise InputError(f"{path}: storage {big[0].filename} declares {big[0].file_size} bytes, more than the "
                                 f"{L.MAX_CHECKPOINT_STORAGE_BYTES} a GeoPose network's tensor may have; {remedy}")
            names = {i.filename: i for i in infos}
            order = names.get(f"{root}/byteorder")
            byteorder = archive.read(order).decode(errors="replace").strip() if order and order.file_size < 64 else "little"
            with archive.open(pickles[0]) as stream:
                obj = _TensorOnlyUnpickler(stream, archive, root, byteorder == "little").load()
    except InputError:
        raise
    except (pickle.UnpicklingError, EOFError, ValueError, TypeError, RuntimeError, AttributeError, IndexError, KeyError,
            OverflowError, RecursionError, MemoryError, zipfile.BadZipFile, zipfile.LargeZipFile, OSError) as exc:
        raise InputError(f"{problem} (unreadable: {type(exc).__name__}: {' '.join(str(exc).split())[:200]}); {remedy}") from None
    state = obj.get("state_dict") if isinstance(obj, dict) and "state_dict" in obj else obj
    if not isinstance(state, dict) or not state or not all(
        isinstance(k, str) and isinstance(v, torch.Tensor) for k, v in state.items()
    ):
        raise InputError(f"{path} holds no state_dict of tensors; pass a GeoPose Lightning checkpoint")
    return dict(state)


def load_manifest(path: str | os.PathLike | None = None) -> dict[str, Any]:
    """The published checkpoints' manifest (file names, sizes, SHA-256)."""
    path = Path(published_manifest_path() if path is None else path)
    if not path.is_file():
        raise InputError(f"the published checkpoint manifest {path} is missing; reinstall GeoPose")
    manifest = read_json(path, "reinstall GeoPose")
    if not isinstance(manifest, dict) or not isinstance(manifest.get("files"), dict):
        raise InputError(f"{path} is not the published checkpoint manifest; reinstall GeoPose")
    return manifest


def official_entry(path: str | os.PathLike, manifest: dict[str, Any]) -> tuple[str, dict[str, Any]] | None:
    """``(official name, manifest entry)`` if the file name is a published release or source name."""
    name = Path(path).name
    for official, entry in manifest["files"].items():
        if name in (official, entry.get("source_filename")):
            return official, entry
    return None


def verify_official(path: str | os.PathLike, official: str, entry: dict[str, Any]) -> None:
    """Refuse a file carrying an official name whose size or SHA-256 differs from the manifest."""
    size = Path(path).stat().st_size
    remedy = f"download {official} again from the GeoPose release, or rename the file if it is your own model"
    if size != entry["bytes"]:
        raise InputError(f"{path} is named like the published {official} but has {size} bytes, not {entry['bytes']}; {remedy}")
    digest = file_sha256(path)
    if digest != entry["sha256"]:
        raise InputError(f"{path} is named like the published {official} but its SHA-256 is {digest}, not {entry['sha256']}; {remedy}")


def infer_config(state: dict[str, torch.Tensor]) -> NetConfig:
    """Architecture from state-dict key names and shapes (Init: ``net.fc.*``; Refine: ``net.backbone.*``)."""
    if "net.fc.pose.weight" in state:
        kind, trunk = "init", "net."
    elif "net.head.weight" in state:
        kind, trunk = "refine", "net.backbone."
    else:
        raise InputError("the state_dict is neither a GeoPose-Init (net.fc.*) nor a GeoPose-Refine (net.head.*) network")
    conv1 = state.get(f"{trunk}conv1.weight")
    if conv1 is None or conv1.ndim != 4:
        raise InputError(f"the state_dict lacks the stem convolution {trunk}conv1.weight")
    blocks = tuple(
        len({k[len(f"{trunk}layer{s}."):].split(".")[0] for k in state if k.startswith(f"{trunk}layer{s}.")})
        for s in range(1, 5)
    )
    depths = [d for d, b in BLOCKS_PER_STAGE.items() if b == blocks]
    if not depths:
        raise InputError(f"ResNet stages with {blocks} blocks match no supported depth {sorted(BLOCKS_PER_STAGE)}")
    backbone = BackboneConfig(depth=depths[0], base_width=conv1.shape[0], in_channels=conv1.shape[1])
    if kind == "init":
        return NetConfig("init", backbone, embedding_dim=state["net.fc.role_embedding.weight"].shape[1])
    return NetConfig(
        "refine", backbone, embedding_dim=state["net.view_emb.weight"].shape[1], fusion_dim=state["net.fusion.0.weight"].shape[0]
    )


def module_from_state_dict(state: dict[str, torch.Tensor]) -> InitNet | RefineNet:
    """Build the matching module and load ``state`` strictly (training-only ``criterion.*`` dropped)."""
    kept = {k: v for k, v in state.items() if not k.startswith(IGNORED_PREFIXES)}
    try:
        config = infer_config(kept)
    except (KeyError, IndexError) as exc:
        raise InputError(f"the state_dict lacks or misshapes the tensor {exc} of a GeoPose network") from None
    module = build_model(config)
    try:
        module.load_state_dict(kept, strict=True)
    except RuntimeError as exc:
        raise InputError(f"the checkpoint does not match the GeoPose {module.config.kind} layout: {exc}") from None
    return module.eval()


def import_checkpoint(
    checkpoint: str | os.PathLike, out: str | os.PathLike, *, dtype: str = "float32", manifest_path: str | os.PathLike | None = None
) -> Path:
    """Convert a Lightning ``.ckpt`` into a GeoPose model file; official names are verified first.

    ``out`` is a ``.pt`` file or a directory (then ``<kind>.pt`` inside it).
    """
    checkpoint, out = Path(checkpoint), Path(out)
    if not checkpoint.is_file():
        raise InputError(f"checkpoint {checkpoint} does not exist")
    if out.suffix not in ("", MODEL_SUFFIX) and not out.is_dir():
        raise InputError(f"--out {out} must be a {MODEL_SUFFIX} file or a directory")
    manifest = load_manifest(manifest_path)
    official = official_entry(checkpoint, manifest)
    if official is not None:
        verify_official(checkpoint, *official)
    module = module_from_state_dict(read_checkpoint_state_dict(checkpoint))
    metadata: dict[str, Any] = {"source_file": checkpoint.name}
    if official is not None:
        name, entry = official
        metadata.update(
            published=name, sha256=entry["sha256"], contract=entry.get("contract"), doi=manifest.get("zenodo_doi")
        )
    if out.is_dir() or out.suffix == "":
        out = out / f"{module.config.kind}{MODEL_SUFFIX}"
    return save_model(module, out, metadata, dtype=dtype)


def register(subparsers: Any) -> None:
    """``geopose import-checkpoint FILE --out OUT``."""
    parser = subparsers.add_parser(
        "import-checkpoint",
        help="convert a published GeoPose Lightning checkpoint into a GeoPose model file (no pickled code is run)",
    )
    parser.add_argument("checkpoint", help="the .ckpt file (geopose_init.ckpt / geopose_refine.ckpt)")
    parser.add_argument("--out", required=True, help="output .pt file, or a directory (then <init|refine>.pt)")
    parser.add_argument("--dtype", choices=("float32", "float16"), default="float32", help="storage dtype of the weights")
    parser.set_defaults(func=_run)


def _run(args: Any) -> int:
    path = import_checkpoint(args.checkpoint, args.out, dtype=args.dtype)
    print(f"wrote {path}")
    return 0
