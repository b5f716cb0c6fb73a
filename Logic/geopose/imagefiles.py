"""What a NIfTI, NRRD or MetaImage file declares, checked against what it holds, before SimpleITK reads it.

SimpleITK zero-fills a truncated file and turns NaN/Inf into 0 in some readers, so the
CT(A) and DSA readers call :func:`check_image_file` first: it parses the header itself,
bounds the declared grid, and reads the voxel block (decompressing ``.gz``/zlib/bzip2 data
in chunks) to check that it holds exactly the declared number of bytes and, for float
types, only finite values. Failures are :class:`~geopose.errors.InputError` lines naming
the file, the problem and the remedy.
"""

from __future__ import annotations

import bz2
import gzip
import math
import re
import struct
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO, Callable, Iterator

import numpy as np

from . import limits as L
from .errors import InputError
from .inputpaths import regular_file

__all__ = ["DeclaredImage", "check_image_file", "image_extension", "IMAGE_EXTENSIONS"]

#: File name endings with a header this module parses.
IMAGE_EXTENSIONS = (".nii", ".nii.gz", ".nrrd", ".nhdr", ".mha", ".mhd")
_CHUNK_BYTES = 1 << 24
_MAX_HEADER_BYTES = 1 << 20
_REMEDY = "re-export the image or copy the complete file again"


@dataclass
class DeclaredImage:
    """A header's grid: ``shape`` fastest axis first (x, y, z, ...), the voxel ``dtype`` (None when
    not a scalar type this module checks), the header and data ``files`` and what was checked."""

    shape: tuple[int, ...]
    dtype: np.dtype | None
    files: list[Path]
    checks: list[str] = field(default_factory=list)
    #: NIfTI only: the voxel -> RAS (mm) affines the header sets, by name ("qform", "sform"), those with a nonzero code.
    xforms: dict[str, np.ndarray] = field(default_factory=dict)


def image_extension(path: Path) -> str:
    name = path.name.lower()
    return ".nii.gz" if name.endswith(".nii.gz") else path.suffix.lower()


def check_image_file(path: Path, max_voxels: int) -> DeclaredImage:
    """Parse ``path``'s header, refuse more than ``max_voxels`` voxels, and check its voxel data
    (byte count; finite values for float types). Returns the declared grid and the files read."""
    ext = image_extension(path)
    regular_file(path, "image file")
    if path.stat().st_size > L.MAX_IMAGE_FILE_BYTES:
        raise InputError(f"{path.name} has {path.stat().st_size} bytes, more than the {L.MAX_IMAGE_FILE_BYTES} read here")
    if ext in (".nii", ".nii.gz"):
        return _nifti(path, max_voxels)
    if ext in (".nrrd", ".nhdr"):
        return _nrrd(path, max_voxels)
    return _metaimage(path, max_voxels)


# ---------------------------------------------------------------------- common


def _grid(path: Path, shape: list[int], max_voxels: int) -> tuple[int, ...]:
    if not shape or any(s < 1 for s in shape):
        raise InputError(f"{path.name} declares the grid {tuple(shape)}: every size must be at least 1; the header is damaged; {_REMEDY}")
    if math.prod(shape) > max_voxels:
        raise InputError(f"{path.name} declares {' x '.join(map(str, shape))} = {math.prod(shape)} voxels, more than the "
                         f"{max_voxels} an image may have here: the header is damaged; {_REMEDY}")
    return tuple(shape)


def _check_block(path: Path, chunks: Iterator[bytes], expected: int, dtype: np.dtype | None, what: str) -> None:
    """Consume ``chunks`` (the voxel bytes): exactly ``expected`` bytes, all finite for float ``dtype``."""
    total, carry, bad = 0, b"", 0
    item = dtype.itemsize if dtype is not None else 1
    try:
        for chunk in chunks:
            total += len(chunk)
            if total > expected:
                break
            if dtype is not None and dtype.kind == "f":
                data = carry + chunk
                cut = len(data) - len(data) % item
                values = np.frombuffer(data[:cut], dtype=dtype)
                bad += int(values.size - np.count_nonzero(np.isfinite(values)))
                carry = data[cut:]
    except (OSError, EOFError, zlib.error, ValueError) as exc:
        raise InputError(f"{path.name}: the {what} is damaged or truncated ({' '.join(str(exc).split())[:100]}); {_REMEDY}") from None
    if total < expected:
        raise InputError(f"{path.name} is truncated: its {what} holds {total} of the {expected} bytes its header declares; {_REMEDY}")
    if total > expected:
        raise InputError(f"{path.name} holds more {what} than its header declares ({expected} bytes): the header's sizes or "
                         f"voxel type are damaged; {_REMEDY}")
    if bad:
        raise InputError(f"{path.name} has {bad} NaN/infinite voxels: replace them (e.g. with -1024 HU for a CT) and export again")


def _read_chunks(stream: BinaryIO, limit: int) -> Iterator[bytes]:
    """Up to ``limit + 1`` bytes of ``stream`` in chunks (one byte more shows surplus data)."""
    left = limit + 1
    while left > 0:
        chunk = stream.read(min(_CHUNK_BYTES, left))
        if not chunk:
            return
        left -= len(chunk)
        yield chunk


def _file_chunks(files: list[Path], skip: Callable[[Path], int], opener: Callable[[Path], BinaryIO], limit: int) -> Iterator[bytes]:
    for f in files:
        if not f.exists():
            raise InputError(f"data file {f} named by the header does not exist: keep the data files next to the header")
        regular_file(f, "data file named by the header")
        with opener(f) as stream:
            offset = skip(f)
            if offset:
                stream.seek(offset) if opener is _open_raw else stream.read(offset)
            yield from _read_chunks(stream, limit)


def _open_raw(path: Path) -> BinaryIO:
    return open(path, "rb")


# ----------------------------------------------------------------------- NIfTI

_NIFTI_TYPES = {2: "u1", 4: "i2", 8: "i4", 16: "f4", 64: "f8", 256: "i1", 512: "u2", 768: "u4", 1024: "i8", 1280: "u8"}
_NIFTI_OTHER_BITS = {128: 24, 2304: 32, 32: 64, 1792: 128, 1536: 128, 2048: 256, 1: 1}


def _nifti(path: Path, max_voxels: int) -> DeclaredImage:
    gz = image_extension(path) == ".nii.gz"
    opener = (lambda p: gzip.open(p, "rb")) if gz else _open_raw
    try:
        with opener(path) as f:
            head = f.read(540)
    except (OSError, EOFError, zlib.error) as exc:
        raise InputError(f"cannot read {path.name} as NIfTI ({' '.join(str(exc).split())[:100]}): check that the file is complete") from None
    if len(head) < 348:
        raise InputError(f"{path.name} is truncated: a NIfTI header has at least 348 bytes, the file {len(head)}; {_REMEDY}")
    endian = next((e for e in "<>" if struct.unpack(e + "i", head[:4])[0] in (348, 540)), None)
    if endian is None:
        raise InputError(f"cannot read {path.name} as NIfTI (header size field {struct.unpack('<i', head[:4])[0]}, not 348 or 540): "
                         "check that the file is complete and in the format its name says")
    if struct.unpack(endian + "i", head[:4])[0] == 348:
        dims = list(struct.unpack(endian + "8h", head[40:56]))
        datatype, bitpix = struct.unpack(endian + "hh", head[70:74])
        vox_offset, slope, inter = struct.unpack(endian + "fff", head[108:120])
        magic, minimum = head[344:348], 352
    else:
        if len(head) < 540:
            raise InputError(f"{path.name} is truncated inside its NIfTI-2 header; {_REMEDY}")
        magic, minimum = head[4:8], 544
        datatype, bitpix = struct.unpack(endian + "hh", head[12:16])
        dims = list(struct.unpack(endian + "8q", head[16:80]))
        vox_offset, slope, inter = struct.unpack(endian + "qdd", head[168:192])
    if magic not in (b"n+1\x00", b"n+2\x00"):
        raise InputError(f"{path.name} has NIfTI magic {magic!r}, not a single-file NIfTI ('n+1'): the header is damaged; {_REMEDY}")
    if not 1 <= dims[0] <= 7:
        raise InputError(f"{path.name} declares {dims[0]} dimensions (dim[0]), not 1..7: the header is damaged; {_REMEDY}")
    shape = _grid(path, dims[1:1 + dims[0]], max_voxels)
    code = _NIFTI_TYPES.get(datatype)
    dtype = np.dtype(endian + code) if code else None
    bits = dtype.itemsize * 8 if dtype is not None else _NIFTI_OTHER_BITS.get(datatype)
    if bits is None or bitpix != bits or bits % 8:
        raise InputError(f"{path.name} has NIfTI datatype {datatype} with bitpix {bitpix}: not a voxel type read here or a "
                         f"damaged header; {_REMEDY}")
    if not (math.isfinite(vox_offset) and float(vox_offset).is_integer() and minimum <= vox_offset <= L.MAX_IMAGE_FILE_BYTES):
        raise InputError(f"{path.name} has voxel offset {vox_offset}, not a whole number of bytes after the header: "
                         f"the header is damaged; {_REMEDY}")
    if not (math.isfinite(slope) and math.isfinite(inter)):
        raise InputError(f"{path.name} has a non-finite intensity scaling (scl_slope {slope}, scl_inter {inter}): "
                         f"set scl_slope 0 or 1 and scl_inter 0 in the header, or {_REMEDY}")
    expected = math.prod(shape) * bits // 8
    offset = int(vox_offset)
    _check_block(path, _file_chunks([path], lambda _: offset, opener, expected), expected, dtype, "voxel data")
    return DeclaredImage(shape, dtype, [path], ["NIfTI: byte count and finite values checked"], _nifti_xforms(head, endian))


def _nifti_xforms(head: bytes, endian: str) -> dict[str, np.ndarray]:
    """The qform (quaternion, pixdim, qfac) and sform (srow) affines, voxel -> RAS mm, of a NIfTI-1 or -2 header,
    those whose code is nonzero."""
    if struct.unpack(endian + "i", head[:4])[0] == 348:
        f, pixdim = "f", struct.unpack(endian + "8f", head[76:108])
        qcode, scode = struct.unpack(endian + "hh", head[252:256])
        quat = struct.unpack(endian + "6f", head[256:280])
        srows = struct.unpack(endian + "12f", head[280:328])
    else:
        f, pixdim = "d", struct.unpack(endian + "8d", head[104:168])
        qcode, scode = struct.unpack(endian + "ii", head[344:352])
        quat = struct.unpack(endian + "6d", head[352:400])
        srows = struct.unpack(endian + "12d", head[400:496])
    out: dict[str, np.ndarray] = {}
    if qcode > 0:
        b, c, d = quat[:3]
        a = math.sqrt(max(0.0, 1.0 - (b * b + c * c + d * d)))
        rot = np.array([[a * a + b * b - c * c - d * d, 2 * (b * c - a * d), 2 * (b * d + a * c)],
                        [2 * (b * c + a * d), a * a + c * c - b * b - d * d, 2 * (c * d - a * b)],
                        [2 * (b * d - a * c), 2 * (c * d + a * b), a * a + d * d - c * c - b * b]])
        qfac = -1.0 if pixdim[0] < 0 else 1.0
        affine = np.eye(4)
        affine[:3, :3] = rot @ np.diag([pixdim[1], pixdim[2], qfac * pixdim[3]])
        affine[:3, 3] = quat[3:]
        out["qform"] = affine
    if scode > 0:
        out["sform"] = np.vstack([np.reshape(srows, (3, 4)), [0, 0, 0, 1]])
    return {k: v for k, v in out.items() if np.isfinite(v).all()}


# ------------------------------------------------------------------------ NRRD

_NRRD_TYPES = {
    **dict.fromkeys(("signed char", "int8", "int8_t"), "i1"),
    **dict.fromkeys(("uchar", "unsigned char", "uint8", "uint8_t"), "u1"),
    **dict.fromkeys(("short", "short int", "signed short", "signed short int", "int16", "int16_t"), "i2"),
    **dict.fromkeys(("ushort", "unsigned short", "unsigned short int", "uint16", "uint16_t"), "u2"),
    **dict.fromkeys(("int", "signed int", "int32", "int32_t"), "i4"),
    **dict.fromkeys(("uint", "unsigned int", "uint32", "uint32_t"), "u4"),
    **dict.fromkeys(("longlong", "long long", "long long int", "signed long long", "signed long long int", "int64", "int64_t"), "i8"),
    **dict.fromkeys(("ulonglong", "unsigned long long", "unsigned long long int", "uint64", "uint64_t"), "u8"),
    "float": "f4",
    "double": "f8",
}


def _header_bytes(path: Path, end: Callable[[bytes], int | None], what: str) -> tuple[bytes, int]:
    """The header text of ``path`` and where the data start (``end(head)`` finds it)."""
    with open(path, "rb") as f:
        head = f.read(_MAX_HEADER_BYTES)
    stop = end(head)
    if stop is None:
        raise InputError(f"cannot read {path.name} as {what}: no complete header in its first {_MAX_HEADER_BYTES} bytes; "
                         "check that the file is complete and in the format its name says")
    return head[:stop], stop


def _nrrd_end(head: bytes) -> int | None:
    m = re.search(rb"\r?\n\r?\n", head)
    return m.end() if m else (len(head) if len(head) < _MAX_HEADER_BYTES else None)


def _int_list(path: Path, key: str, text: str) -> list[int]:
    try:
        return [int(v) for v in text.split()]
    except ValueError:
        raise InputError(f"{path.name} has a damaged '{key}' field ({text[:40]!r}); {_REMEDY}") from None


def _require_files(header: Path, files: list[Path]) -> None:
    missing = [f.name for f in files if not f.exists()]
    if missing:
        raise InputError(f"{header.name} names data file(s) that do not exist ({', '.join(missing[:3])}): keep the data files "
                         "next to the header, or check its data-file field")
    for f in files:
        regular_file(f, f"data file named by {header.name}")


def _check_counts(path: Path, fields: dict[str, str], counts: dict[str, int]) -> None:
    """Each present numeric field holds exactly ``counts[key]`` finite numbers."""
    for key, n in counts.items():
        if key not in fields:
            continue
        try:
            values = [float(v) for v in fields[key].split()]
        except ValueError:
            values = []
        if len(values) != n or not all(math.isfinite(v) for v in values):
            raise InputError(f"{path.name} has a damaged '{key}' field ({fields[key][:60]!r}; {n} finite numbers expected); {_REMEDY}")


def _one_int(path: Path, key: str, text: str) -> int:
    values = _int_list(path, key, text)
    if len(values) != 1:
        raise InputError(f"{path.name} has a damaged '{key}' field ({text[:40]!r}, not one whole number); {_REMEDY}")
    return values[0]


def _data_files(header: Path, spec: str, rest: list[str], what: str) -> list[Path]:
    """Files of a detached header's data-file field: one name, ``LIST`` (names follow) or a pattern ``fmt min max step``."""
    parts = spec.split()
    if parts and parts[0].upper() == "LIST":
        return [header.parent / name for name in rest if name.strip()]
    if len(parts) >= 3 and "%" in parts[0]:
        try:
            start, stop = int(parts[1]), int(parts[2])
            step = int(parts[3]) if len(parts) > 3 else 1
            if step == 0 or abs(stop - start) // abs(step) > L.CTA_VOXELS_PER_AXIS[1]:
                raise ValueError
            return [header.parent / (parts[0] % k) for k in range(start, stop + (1 if step > 0 else -1), step)]
        except (ValueError, TypeError):
            raise InputError(f"{header.name} has a damaged {what} pattern {spec!r}; {_REMEDY}") from None
    return [header.parent / spec]


def _nrrd(path: Path, max_voxels: int) -> DeclaredImage:
    text, start = _header_bytes(path, _nrrd_end, "NRRD")
    lines = text.decode("latin-1").splitlines()
    if not lines or not lines[0].startswith("NRRD"):
        raise InputError(f"cannot read {path.name} as NRRD (no NRRD magic): check that the file is complete and in the format its name says")
    fields: dict[str, str] = {}
    rest: list[str] = []
    for i, line in enumerate(lines[1:], start=1):
        if line.startswith("#") or ":=" in line or not line.strip():
            continue
        if ":" not in line:
            rest = lines[i:]
            break
        key, value = line.split(":", 1)
        fields[key.strip().lower()] = value.strip()
        if key.strip().lower() in ("data file", "datafile") and value.strip().upper().startswith("LIST"):
            rest = lines[i + 1:]
            break
    for key in ("type", "dimension", "sizes", "encoding"):
        if key not in fields:
            raise InputError(f"{path.name} has no '{key}' field: the NRRD header is damaged; {_REMEDY}")
    shape = _grid(path, _int_list(path, "sizes", fields["sizes"]), max_voxels)
    if _int_list(path, "dimension", fields["dimension"]) != [len(shape)] or len(shape) > 16:
        raise InputError(f"{path.name} has dimension {fields['dimension']!r} and sizes {fields['sizes']!r}: they do not agree; "
                         f"the NRRD header is damaged; {_REMEDY}")
    code = _NRRD_TYPES.get(fields["type"].lower())
    if code is None:
        raise InputError(f"{path.name} has NRRD type {fields['type']!r}, not a voxel type read here; {_REMEDY}")
    endian = ">" if fields.get("endian", "little").lower() == "big" else "<"
    dtype = np.dtype(endian + code)
    encoding = fields["encoding"].lower()
    expected = math.prod(shape) * dtype.itemsize
    spec = fields.get("data file", fields.get("datafile"))
    files = [path] if spec is None else _data_files(path, spec, rest, "data file")
    _require_files(path, files)
    byte_skip = _one_int(path, "byte skip", fields.get("byte skip", "0"))
    line_skip = _one_int(path, "line skip", fields.get("line skip", "0"))
    checks = [f"NRRD ({encoding}): byte count and finite values checked"]
    if encoding in ("ascii", "txt", "text", "hex"):
        return DeclaredImage(shape, dtype, [path] + ([] if spec is None else files), [f"NRRD ({encoding}): not checked"])
    openers = {"raw": _open_raw, "gzip": lambda p: gzip.open(p, "rb"), "gz": lambda p: gzip.open(p, "rb"),
               "bzip2": lambda p: bz2.open(p, "rb"), "bz2": lambda p: bz2.open(p, "rb")}
    if encoding not in openers:
        raise InputError(f"{path.name} has NRRD encoding {encoding!r}, not one read here (raw, gzip, bzip2); {_REMEDY}")
    if byte_skip < -1 or line_skip < 0 or (byte_skip == -1 and (encoding != "raw" or len(files) != 1)):
        raise InputError(f"{path.name} has a damaged 'byte skip'/'line skip' ({byte_skip}/{line_skip}); {_REMEDY}")
    attached = spec is None

    def skip(f: Path) -> int:
        base = start if attached else 0
        if line_skip:
            with open(f, "rb") as handle:
                handle.seek(base)
                for _ in range(line_skip):
                    handle.readline()
                base = handle.tell()
        if byte_skip == -1:
            return max(0, f.stat().st_size - expected)
        return base + byte_skip

    opener = openers[encoding]
    if encoding != "raw":  # the skips count in the compressed file: open it there
        def opener(f: Path, _o=openers[encoding]) -> BinaryIO:  # type: ignore[misc]
            handle = open(f, "rb")
            handle.seek(skip(f))
            return _o(handle)  # type: ignore[arg-type]

        _check_block(path, _file_chunks(files, lambda _: 0, opener, expected), expected, dtype, "voxel data")
    else:
        _check_block(path, _file_chunks(files, skip, _open_raw, expected), expected, dtype, "voxel data")
    return DeclaredImage(shape, dtype, [path] + ([] if attached else files), checks)


# ------------------------------------------------------------------- MetaImage

_MET_TYPES = {"MET_CHAR": "i1", "MET_UCHAR": "u1", "MET_SHORT": "i2", "MET_USHORT": "u2", "MET_INT": "i4", "MET_UINT": "u4",
              "MET_LONG": "i4", "MET_ULONG": "u4", "MET_LONG_LONG": "i8", "MET_ULONG_LONG": "u8", "MET_FLOAT": "f4",
              "MET_DOUBLE": "f8"}


#: MetaIO keys read here (exact case) -> the lower-case name used below.
_MET_KEYS = {k: k.lower() for k in (
    "NDims", "DimSize", "ElementType", "ElementDataFile", "ElementSpacing", "ElementSize", "Offset", "Position", "Origin",
    "CenterOfRotation", "TransformMatrix", "Rotation", "Orientation", "ElementNumberOfChannels", "HeaderSize",
    "CompressedData", "CompressedDataSize", "BinaryDataByteOrderMSB", "ElementByteOrderMSB")}


def _mha_end(head: bytes) -> int | None:
    m = re.search(rb"^[ \t]*ElementDataFile[ \t]*=[^\n]*\n", head, flags=re.MULTILINE)
    return m.end() if m else None


def _metaimage(path: Path, max_voxels: int) -> DeclaredImage:
    text, start = _header_bytes(path, _mha_end, "MetaImage")
    fields: dict[str, str] = {}
    for line in text.decode("latin-1").splitlines():
        if "=" in line:  # MetaIO keys are case-sensitive: a damaged key is an unknown one
            key, value = line.split("=", 1)
            if key.strip() in _MET_KEYS:
                fields[_MET_KEYS[key.strip()]] = value.strip()
    for key in ("ndims", "dimsize", "elementtype", "elementdatafile"):
        if key not in fields:
            raise InputError(f"{path.name} has no '{key}' field: the MetaImage header is damaged; {_REMEDY}")
    ndims = _int_list(path, "NDims", fields["ndims"])
    shape = _grid(path, _int_list(path, "DimSize", fields["dimsize"]), max_voxels)
    if len(ndims) != 1 or not 1 <= ndims[0] <= 7 or len(shape) != ndims[0]:
        raise InputError(f"{path.name} has NDims {fields['ndims']!r} and DimSize {fields['dimsize']!r}: they do not agree; "
                         f"the MetaImage header is damaged; {_REMEDY}")
    _check_counts(path, fields, {k: len(shape) for k in ("elementspacing", "elementsize", "offset", "position", "origin",
                                                          "centerofrotation")}
                  | {k: len(shape) ** 2 for k in ("transformmatrix", "rotation", "orientation")})
    code = _MET_TYPES.get(fields["elementtype"].upper())
    if code is None:
        raise InputError(f"{path.name} has ElementType {fields['elementtype']!r}, not a voxel type read here; {_REMEDY}")
    big = fields.get("binarydatabyteordermsb", fields.get("elementbyteordermsb", "false")).lower() == "true"
    dtype = np.dtype((">" if big else "<") + code)
    channels = _one_int(path, "ElementNumberOfChannels", fields.get("elementnumberofchannels", "1"))
    if channels < 1:
        raise InputError(f"{path.name} declares {channels} channels; the header is damaged; {_REMEDY}")
    expected = math.prod(shape) * dtype.itemsize * channels
    spec = fields["elementdatafile"]
    local = spec.upper() == "LOCAL"
    names: list[str] = []
    if not local and spec.split()[:1] == ["LIST"]:  # the names follow the header line
        with open(path, "rb") as f:
            f.seek(start)
            names = f.read(_MAX_HEADER_BYTES).decode("latin-1").split()
    files = [path] if local else _data_files(path, spec, names, "ElementDataFile")
    _require_files(path, files)
    header_size = _one_int(path, "HeaderSize", fields.get("headersize", "0"))
    if local and header_size:
        raise InputError(f"{path.name} has HeaderSize {header_size} with its data in the file (LOCAL): not read here; "
                         f"the header is damaged; {_REMEDY}")
    compressed = fields.get("compresseddata", "false").lower() == "true"
    if compressed:
        if len(files) != 1:
            raise InputError(f"{path.name}: compressed MetaImage data in several files is not read here; {_REMEDY}")
        size = _int_list(path, "CompressedDataSize", fields.get("compresseddatasize", ""))
        available = files[0].stat().st_size - (start if local else max(header_size, 0))
        if size != [available]:
            raise InputError(f"{path.name} declares CompressedDataSize {fields.get('compresseddatasize', '')!r} but holds "
                             f"{available} compressed bytes: the file is truncated or its header damaged; {_REMEDY}")

        def chunks() -> Iterator[bytes]:
            inflater = zlib.decompressobj(47)  # zlib or gzip header
            with open(files[0], "rb") as f:
                f.seek(start if local else max(header_size, 0))
                while raw := f.read(_CHUNK_BYTES):
                    yield inflater.decompress(raw, expected + 1)
                    if inflater.unconsumed_tail:
                        yield inflater.unconsumed_tail[:1]
                        return
            if not inflater.eof:
                raise EOFError("the zlib stream ends early")

        _check_block(path, chunks(), expected, dtype, "voxel data")
    else:
        per_file = expected // len(files) if expected % len(files) == 0 else None

        def skip(f: Path) -> int:
            if local:
                return start
            if header_size == -1:
                return max(0, f.stat().st_size - (per_file if per_file is not None else expected))
            return max(header_size, 0)

        _check_block(path, _file_chunks(files, skip, _open_raw, expected), expected, dtype, "voxel data")
    return DeclaredImage(shape, dtype, [path] + ([] if local else files), ["MetaImage: byte count and finite values checked"])
