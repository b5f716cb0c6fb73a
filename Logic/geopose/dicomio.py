"""Reading DICOM files defensively: bounded parsing and pixel data checked against the header.

One path for the DSA (XA) and the CT readers. A file is read whole (at most
:data:`~geopose.limits.MAX_DICOM_FILE_BYTES`) and parsed from memory, so a damaged element
length cannot make the parser allocate more than the file holds. Pixel data are decoded
frame by frame and checked against Rows, Columns, NumberOfFrames, BitsAllocated and
BitsStored: uncompressed data must hold exactly the declared bytes, compressed streams must
decode completely to the declared matrix (RLE segments to exactly Rows x Columns bytes,
JPEG and JPEG 2000 headers matching the tags). A JPEG 2000 Lossless stream written by
OpenJPEG is re-encoded and must reproduce itself byte for byte (JPEG 2000 has no checksum:
this is what shows a damaged stream); ``pixel_integrity`` in the returned notes says which
check each file got. Every failure is an :class:`~geopose.errors.InputError` naming the file.
"""

from __future__ import annotations

import io
import struct
import warnings
from pathlib import Path
from typing import Callable

import numpy as np
import pydicom
from pydicom.errors import InvalidDicomError
from pydicom import uid as U

from . import limits as L
from .errors import InputError
from .inputpaths import read_bounded

__all__ = ["read_dataset", "decode_frames", "is_image_storage", "is_non_image", "looks_like_dicom", "int_tag", "float_tag",
           "floats_tag", "raw_tag"]

UNCOMPRESSED = {U.ImplicitVRLittleEndian, U.ExplicitVRLittleEndian, U.DeflatedExplicitVRLittleEndian, U.ExplicitVRBigEndian}
JPEG_SYNTAXES = {U.JPEGBaseline8Bit, U.JPEGExtended12Bit, U.JPEGLossless, U.JPEGLosslessSV1, U.JPEGLSLossless, U.JPEGLSNearLossless}
#: pydicom 2.4 (Slicer 5.8, 5.10) names no HTJ2K syntaxes; their UIDs are spelled out.
J2K_SYNTAXES = {U.JPEG2000Lossless, U.JPEG2000, U.UID("1.2.840.10008.1.2.4.201"), U.UID("1.2.840.10008.1.2.4.202"),
                U.UID("1.2.840.10008.1.2.4.203")}
_REMEDY_COPY = "copy the file again from the archive or re-export it"
_REMEDY_DECOMPRESS = "decompress it (e.g. gdcmconv --raw) and load the uncompressed file"


def read_dataset(path: Path, *, stop_before_pixels: bool = False) -> pydicom.Dataset:
    """The dataset of ``path`` with every top-level element parsed, or an :class:`InputError`
    ("not a DICOM file" / "damaged") naming the file."""
    data = read_bounded(path, L.MAX_DICOM_FILE_BYTES, "DICOM file", "export the run or series in smaller files")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ds = pydicom.dcmread(io.BytesIO(data), stop_before_pixels=stop_before_pixels)
            for _ in ds:  # convert every raw element now, inside this guard
                pass
            if hasattr(ds, "file_meta"):
                for _ in ds.file_meta:
                    pass
    except InvalidDicomError:
        raise InputError(f"{path} is not a DICOM file: give a DICOM file, a folder of them or a NIfTI/NRRD/MHA image") from None
    except Exception as exc:  # pydicom raises many types for damaged files
        raise InputError(f"{path.name} is a damaged DICOM file (pydicom: {type(exc).__name__}: {_short(exc)}); {_REMEDY_COPY}") from None
    return ds


def looks_like_dicom(path: Path) -> bool:
    """Whether ``path`` is meant to be DICOM: a .dcm/.dicom/.ima name, 'DICM' at byte 128, or a zero preamble
    (so a damaged slice is refused rather than skipped like a README beside the series)."""
    if path.suffix.lower() in (".dcm", ".dicom", ".ima"):
        return True
    with open(path, "rb") as f:
        head = f.read(132)
    return head[128:132] == b"DICM" or (len(head) >= 128 and not any(head[:128]))


#: Words of SOP class names that hold no image (skipped beside a series).
NON_IMAGE_CLASSES = ("SR", "Report", "Presentation State", "Key Object", "Directory", "Waveform", "Raw Data", "Spectroscopy")


def is_non_image(ds: pydicom.Dataset) -> bool:
    """Whether the SOP class is known and holds no image (a report, presentation state, DICOMDIR...)."""
    sop = ds.get("SOPClassUID") or (ds.file_meta.get("MediaStorageSOPClassUID") if hasattr(ds, "file_meta") else None)
    name = getattr(pydicom.uid.UID(str(sop)), "name", "") if sop else ""
    return bool(name) and "Image Storage" not in name and any(word in name for word in NON_IMAGE_CLASSES)


def is_image_storage(ds: pydicom.Dataset) -> bool:
    """Whether the SOP class (dataset or file meta) names an image storage class or image tags are present."""
    sop = ds.get("SOPClassUID") or (ds.file_meta.get("MediaStorageSOPClassUID") if hasattr(ds, "file_meta") else None)
    name = getattr(pydicom.uid.UID(str(sop)), "name", "") if sop else ""
    return "Image Storage" in name or "Rows" in ds or "Columns" in ds


def _short(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    return text[:160] + ("..." if len(text) > 160 else "")


def int_tag(ds: pydicom.Dataset, keyword: str, name: str, default: int | None = None) -> int:
    """A whole-number tag, ``default`` when absent; a damaged value is an :class:`InputError`."""
    value = ds.get(keyword)
    if value is None or value == "":
        if default is None:
            raise InputError(f"{name} has no {keyword}: the file is truncated or damaged; {_REMEDY_COPY}")
        return default
    try:
        number = float(value)
        if not number.is_integer():
            raise ValueError
        return int(number)
    except (TypeError, ValueError, OverflowError):
        raise InputError(f"{name} has a damaged {keyword} ({str(value)[:40]!r}); {_REMEDY_COPY}") from None


def raw_tag(ds: pydicom.Dataset, keyword: str) -> object | None:
    """A tag's value as stored, ``None`` when absent or empty."""
    value = ds.get(keyword)
    return None if value is None or value == "" else value


def floats_tag(ds: pydicom.Dataset, keyword: str, name: str) -> list[float] | None:
    """A (multi-valued) number tag as finite floats, ``None`` when absent; a damaged value is an :class:`InputError`."""
    value = raw_tag(ds, keyword)
    if value is None:
        return None
    items = value if isinstance(value, (list, tuple, pydicom.multival.MultiValue)) else [value]
    try:
        out = [float(v) for v in items]
    except (TypeError, ValueError, OverflowError):
        out = []
    if not out or not all(np.isfinite(out)):
        raise InputError(f"{name} has a damaged {keyword} ({str(value)[:40]!r}, not finite numbers); {_REMEDY_COPY}")
    return out


def float_tag(ds: pydicom.Dataset, keyword: str, name: str) -> float | None:
    """A one-number tag as a finite float, ``None`` when absent; a damaged value is an :class:`InputError`."""
    values = floats_tag(ds, keyword, name)
    if values is not None and len(values) != 1:
        raise InputError(f"{name} has {len(values)} values in {keyword}, not one; {_REMEDY_COPY}")
    return None if values is None else values[0]


# --------------------------------------------------------------------- decoding


def decode_frames(
    ds: pydicom.Dataset, name: str, check_shape: Callable[[tuple[int, int, int]], None], *, padding_value: float | None = None,
) -> tuple[np.ndarray, dict]:
    """Frames ``(T, H, W)`` float32 with the linear modality LUT (RescaleSlope/Intercept) applied,
    and notes (``pixel_integrity``; ``pixel_padding`` when padding was found). ``check_shape((T, H, W))``
    bounds the declared matrix before anything is decoded; the float32 frames are then the one
    allocation of the run's size (compressed frames are decoded one at a time into it).

    Signed data (PixelRepresentation 1) are read as two's complement of the stored bits whatever type a
    decoder returns (JPEG and JPEG-LS decoders return the unsigned bit pattern). With ``padding_value``
    (output units, e.g. air in HU), pixels whose stored value is PixelPaddingValue (or within
    PixelPaddingValue..PixelPaddingRangeLimit) get that value: they lie outside the scanned field."""
    if "PixelData" not in ds:
        if is_image_storage(ds):
            raise InputError(f"{name} declares an image but holds no pixel data: the file is truncated or damaged; {_REMEDY_COPY}")
        raise InputError(f"{name} holds no pixel data (a report or structure?): give the image file itself")
    for keyword in ("SamplesPerPixel", "PhotometricInterpretation", "Rows", "Columns", "BitsAllocated", "BitsStored",
                    "HighBit", "PixelRepresentation"):  # Type 1 attributes of the Image Pixel module
        if raw_tag(ds, keyword) is None:
            raise InputError(f"{name} has no {keyword}, which every image must have: the file is truncated or damaged; {_REMEDY_COPY}")
    if not hasattr(ds, "file_meta") or raw_tag(ds.file_meta, "TransferSyntaxUID") is None:
        raise InputError(f"{name} has no TransferSyntaxUID in its file meta information: the file is damaged; {_REMEDY_COPY}")
    samples = int_tag(ds, "SamplesPerPixel", name)
    photometric = str(ds.get("PhotometricInterpretation")).strip()
    if samples != 1 or photometric not in ("MONOCHROME1", "MONOCHROME2"):
        raise InputError(f"{name} is a colour image (SamplesPerPixel {samples}, {photometric}): export it as greyscale")
    rows, cols = int_tag(ds, "Rows", name), int_tag(ds, "Columns", name)
    n = int_tag(ds, "NumberOfFrames", name, 1)
    check_shape((n, rows, cols))
    allocated = int_tag(ds, "BitsAllocated", name)
    stored = int_tag(ds, "BitsStored", name)
    signed = int_tag(ds, "PixelRepresentation", name)
    if allocated not in (8, 16, 32) or not 1 <= stored <= allocated or signed not in (0, 1):
        raise InputError(f"{name} has BitsAllocated {allocated}, BitsStored {stored}, PixelRepresentation {signed}: "
                         f"not a greyscale image this reader knows (8/16/32 bits); the header is damaged or {_REMEDY_DECOMPRESS}")
    high = int_tag(ds, "HighBit", name)
    if high != stored - 1:
        raise InputError(f"{name} has HighBit {high} with BitsStored {stored}: only HighBit = BitsStored - 1 is read; "
                         "the header is damaged or the file needs conversion (gdcmconv --raw)")
    syntax = U.UID(str(ds.file_meta.TransferSyntaxUID))
    data = ds.PixelData
    if not isinstance(data, (bytes, bytearray)):
        raise InputError(f"{name}: the pixel data element is damaged; {_REMEDY_COPY}")
    bits = _StoredBits(allocated, stored, signed)
    frames = np.empty((n, rows, cols), dtype=np.float32)
    if syntax in UNCOMPRESSED:
        raw = _native(bytes(data), n, rows, cols, allocated, signed, syntax == U.ExplicitVRBigEndian, name)
        bits.check(raw, name)
        frames[...] = raw
        integrity = "uncompressed: byte count checked"
    elif syntax in JPEG_SYNTAXES or syntax in J2K_SYNTAXES or syntax == U.RLELossless:
        integrity = _encapsulated(bytes(data), syntax, frames, bits, name)
    else:
        raise InputError(f"{name} uses transfer syntax {getattr(syntax, 'name', syntax)}, which this reader does not decode: {_REMEDY_DECOMPRESS}")
    notes: dict = {"pixel_integrity": integrity}
    padding = _padding_pixels(ds, frames, bits, name) if padding_value is not None else None
    slope, intercept = float_tag(ds, "RescaleSlope", name), float_tag(ds, "RescaleIntercept", name)
    if slope is not None or intercept is not None:
        frames *= np.float32(1.0 if slope is None else slope)
        frames += np.float32(intercept or 0.0)
        if not np.isfinite(frames).all():
            raise InputError(f"{name}: RescaleSlope {slope} / RescaleIntercept {intercept} make the pixel values overflow; {_REMEDY_COPY}")
    if padding is not None:
        mask, (lo, hi) = padding
        frames[mask] = np.float32(padding_value)
        notes["pixel_padding"] = {"stored_values": [lo, hi], "pixels": int(mask.sum()), "set_to": float(padding_value)}
    return frames, notes


class _StoredBits:
    """BitsAllocated / BitsStored / PixelRepresentation of an image and the stored-value range they allow."""

    def __init__(self, allocated: int, stored: int, signed: int) -> None:
        self.allocated, self.stored, self.signed = allocated, stored, signed
        self.lo, self.hi = (-(1 << (stored - 1)), (1 << (stored - 1)) - 1) if signed else (0, (1 << stored) - 1)

    def check(self, values: np.ndarray, where: str) -> None:
        """Values outside the range BitsStored allows are an :class:`InputError` (the header or the data are
        damaged: masking them would silently change the image)."""
        lo, hi = int(values.min()), int(values.max())
        if lo < self.lo or hi > self.hi:
            raise InputError(f"{where}: pixel values reach {lo}..{hi}, outside the {self.lo}..{self.hi} that BitsStored "
                             f"{self.stored}{' (signed)' if self.signed else ''} allows: the header or the pixel data are damaged; "
                             f"{_REMEDY_COPY}")

    def signed_values(self, array: np.ndarray, precision: int) -> np.ndarray:
        """A decoder's output as stored values: an unsigned bit pattern of a signed image is read as two's
        complement of its ``precision`` bits (the stream's sample precision)."""
        if not self.signed or array.dtype.kind != "u":
            return array
        values = array.astype(np.int64)
        values[values >= 1 << (precision - 1)] -= 1 << precision
        return values


def _padding_pixels(ds: pydicom.Dataset, frames: np.ndarray, bits: _StoredBits, name: str) -> tuple[np.ndarray, tuple[int, int]] | None:
    """The pixels (mask) whose stored value (``frames`` before rescale) is PixelPaddingValue or lies within
    PixelPaddingValue..PixelPaddingRangeLimit, and that stored range; ``None`` without the tag."""
    if raw_tag(ds, "PixelPaddingValue") is None:
        return None
    values = []
    for keyword in ("PixelPaddingValue", "PixelPaddingRangeLimit"):
        if raw_tag(ds, keyword) is not None:
            v = int_tag(ds, keyword, name)
            if bits.signed and bits.hi < v < 1 << bits.allocated:  # read as unsigned (ambiguous VR US/SS)
                v -= 1 << bits.allocated
            values.append(v)
    lo, hi = min(values), max(values)
    mask = (frames >= lo) & (frames <= hi)
    return mask, (lo, hi)


def _native(data: bytes, n: int, rows: int, cols: int, allocated: int, signed: int, big: bool, name: str) -> np.ndarray:
    expected = n * rows * cols * allocated // 8
    if len(data) < expected:
        raise InputError(f"{name}: the pixel data is truncated ({len(data)} of the {expected} bytes that {n} frame(s) of "
                         f"{rows} x {cols} x {allocated} bits declare); {_REMEDY_COPY}")
    if len(data) > expected + 1:
        raise InputError(f"{name}: the pixel data holds {len(data)} bytes but NumberOfFrames {n}, Rows {rows}, Columns {cols} "
                         f"and BitsAllocated {allocated} declare {expected}: the header is damaged; {_REMEDY_COPY}")
    dtype = np.dtype(f"{'>' if big else '<'}{'i' if signed else 'u'}{allocated // 8}")
    return np.frombuffer(data[:expected], dtype=dtype).reshape(n, rows, cols)


def _encapsulated(data: bytes, syntax: U.UID, out: np.ndarray, bits: _StoredBits, name: str) -> str:
    """Decode every compressed frame into ``out`` ``(n, rows, cols)``, one frame at a time, each checked against
    the stored bits; returns which integrity check the frames got."""
    n, rows, cols = out.shape
    try:
        frames = []
        for frame in pydicom.encaps.generate_frames(data, number_of_frames=n):
            frames.append(bytes(frame))
            if len(frames) > n:
                break
    except Exception as exc:
        raise InputError(f"{name}: the compressed pixel data is damaged ({_short(exc)}); {_REMEDY_COPY}") from None
    if len(frames) != n:
        raise InputError(f"{name} holds {len(frames)} compressed frame(s) but NumberOfFrames says {n}: the file is truncated "
                         f"or damaged; {_REMEDY_COPY}")
    checks = set()
    for k, frame in enumerate(frames):
        where = f"{name}: frame {k + 1} of {n} ({syntax.name})"
        if syntax == U.RLELossless:
            values, check = _rle(frame, rows, cols, bits.allocated, bits.signed, where)
        elif syntax in JPEG_SYNTAXES:
            values, check = _jpeg(frame, rows, cols, bits, where)
        else:
            values, check = _j2k(frame, syntax, rows, cols, bits, where)
        bits.check(values, where)
        out[k] = values
        checks.add(check)
    return "; ".join(sorted(checks))


def _decoder_failure(where: str, exc: BaseException) -> InputError:
    return InputError(f"{where} cannot be decoded ({_short(exc) or type(exc).__name__}): the compressed stream is damaged; {_REMEDY_COPY}")


def _plugin(module: str, where: str):
    try:
        return __import__(module)
    except ImportError:
        raise InputError(f"{where} needs the {module} decoder: install the pylibjpeg plugins (pip install pylibjpeg "
                         f"pylibjpeg-libjpeg pylibjpeg-openjpeg), or {_REMEDY_DECOMPRESS}") from None


def _checked_shape(array: np.ndarray, rows: int, cols: int, where: str) -> np.ndarray:
    if array.ndim != 2 or array.shape != (rows, cols):
        raise InputError(f"{where} decodes to {array.shape} pixels, not the {rows} x {cols} the header declares: "
                         f"the stream or the header is damaged; {_REMEDY_COPY}")
    return array


def _decode_checked(
    kind: str, module: str, frame: bytes, header: tuple[int, int, int, int], rows: int, cols: int, bits: _StoredBits,
    where: str,
) -> np.ndarray:
    """Decode one compressed frame with a pylibjpeg plugin after checking its own header (rows, columns,
    components, precision) against the DICOM header; decoder failures become InputError."""
    h, w, components, precision = header
    allocated = bits.allocated
    if (h, w) != (rows, cols) or components != 1 or precision > allocated:
        raise InputError(f"{where}: the {kind} header says {h} x {w} x {components} component(s) at {precision} bits but "
                         f"the DICOM header {rows} x {cols}, 1 component, {allocated} bits allocated: the stream or the "
                         f"header is damaged; {_REMEDY_COPY}")
    decoder = _plugin(module, where)
    try:
        array = decoder.decode(frame)
    except (KeyboardInterrupt, SystemExit):
        raise
    except BaseException as exc:  # the decoders raise RuntimeError; bindings can raise BaseException subclasses
        raise _decoder_failure(where, exc) from None
    return _checked_shape(np.asarray(array), rows, cols, where)


# ------------------------------------------------------------------------ RLE


def _rle_segment(src: bytes, length: int, where: str) -> bytes:
    """One PackBits segment decoded to exactly ``length`` bytes, all input used (one pad byte allowed)."""
    out = bytearray()
    pos, end = 0, len(src)
    while len(out) < length and pos < end:
        header = src[pos]
        pos += 1
        if header < 128:
            count = header + 1
            if pos + count > end:
                break
            out += src[pos:pos + count]
            pos += count
        elif header > 128:
            if pos >= end:
                break
            out += src[pos:pos + 1] * (257 - header)
            pos += 1
    if len(out) != length or end - pos > 1:
        raise InputError(f"{where}: an RLE segment decodes to {len(out)} bytes (expected {length}) with {end - pos} byte(s) "
                         f"left over: the stream is damaged; {_REMEDY_COPY}")
    return bytes(out)


def _rle(frame: bytes, rows: int, cols: int, allocated: int, signed: int, where: str) -> tuple[np.ndarray, str]:
    nbytes = allocated // 8
    if len(frame) < 64:
        raise InputError(f"{where}: the RLE header is truncated; {_REMEDY_COPY}")
    header = struct.unpack("<16I", frame[:64])
    count, offsets = header[0], list(header[1:])
    if count != nbytes or offsets[0] != 64 or any(o for o in offsets[count:]):
        raise InputError(f"{where}: the RLE header declares {count} segment(s) at {offsets[:count]} (expected {nbytes} "
                         f"from byte 64): the stream is damaged; {_REMEDY_COPY}")
    bounds = offsets[:count] + [len(frame)]
    if any(b <= a for a, b in zip(bounds, bounds[1:])):
        raise InputError(f"{where}: the RLE segment offsets {bounds[:-1]} do not fit the {len(frame)}-byte frame; {_REMEDY_COPY}")
    planes = [np.frombuffer(_rle_segment(frame[a:b], rows * cols, where), np.uint8) for a, b in zip(bounds, bounds[1:])]
    value = np.zeros(rows * cols, np.int64)
    for plane in planes:  # most significant byte first
        value = (value << 8) | plane
    if signed:
        top = 1 << (allocated - 1)
        value = np.where(value >= top, value - (1 << allocated), value)
    return value.reshape(rows, cols), "RLE: segment lengths checked"


# ----------------------------------------------------------------------- JPEG


def _jpeg_frame_header(frame: bytes, where: str) -> tuple[int, int, int, int]:
    """(precision, rows, cols, components) of the first SOF segment; the stream must start with SOI."""
    if frame[:2] != b"\xff\xd8":
        raise InputError(f"{where} does not start with a JPEG SOI marker: the stream is damaged; {_REMEDY_COPY}")
    pos = 2
    while pos + 4 <= len(frame):
        if frame[pos] != 0xFF:
            break
        marker = frame[pos + 1]
        if marker == 0xFF:
            pos += 1
            continue
        length = struct.unpack(">H", frame[pos + 2:pos + 4])[0]
        if (0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC)) or marker == 0xF7:  # SOFn, SOF55 (JPEG-LS)
            if pos + 10 > len(frame):
                break
            precision, rows, cols, components = struct.unpack(">BHHB", frame[pos + 4:pos + 10])
            return precision, rows, cols, components
        if marker == 0xDA:
            break
        pos += 2 + length
    raise InputError(f"{where} has no readable JPEG frame header (SOF): the stream is damaged; {_REMEDY_COPY}")


def _jpeg(frame: bytes, rows: int, cols: int, bits: _StoredBits, where: str) -> tuple[np.ndarray, str]:
    precision, h, w, components = _jpeg_frame_header(frame, where)
    array = _decode_checked("JPEG", "libjpeg", frame, (h, w, components, precision), rows, cols, bits, where)
    return bits.signed_values(array, precision), "JPEG: headers and complete decoding checked"


# ------------------------------------------------------------------- JPEG 2000


def _j2k_codestream(frame: bytes, where: str) -> bytes:
    """The raw codestream (a JP2 file's ``jp2c`` box, or the frame itself)."""
    if frame[:2] == b"\xff\x4f":
        return frame
    pos = 0
    while pos + 8 <= len(frame):
        length, box = struct.unpack(">I4s", frame[pos:pos + 8])
        header = 8
        if length == 1 and pos + 16 <= len(frame):
            length, header = struct.unpack(">Q", frame[pos + 8:pos + 16])[0], 16
        if box == b"jp2c":
            return frame[pos + header:pos + length] if length else frame[pos + header:]
        if length < header:
            break
        pos += length
    raise InputError(f"{where} is not a JPEG 2000 codestream (no SOC marker): the stream is damaged; {_REMEDY_COPY}")


def _j2k_segments(cs: bytes) -> dict[int, bytes]:
    """Main-header marker segments up to the first SOT: marker -> segment body (first occurrence)."""
    segments: dict[int, bytes] = {}
    pos = 2
    while pos + 4 <= len(cs) and cs[pos] == 0xFF and cs[pos + 1] != 0x90:
        marker = cs[pos + 1]
        length = struct.unpack(">H", cs[pos + 2:pos + 4])[0]
        segments.setdefault(marker, cs[pos + 4:pos + 2 + length])
        pos += 2 + length
    return segments


def _strip_comments(cs: bytes) -> bytes:
    """The codestream without COM (0xFF64) segments of the main header."""
    out, pos = bytearray(cs[:2]), 2
    while pos + 4 <= len(cs) and cs[pos] == 0xFF and cs[pos + 1] != 0x90:
        length = struct.unpack(">H", cs[pos + 2:pos + 4])[0]
        if cs[pos + 1] != 0x64:
            out += cs[pos:pos + 2 + length]
        pos += 2 + length
    return bytes(out + cs[pos:])


#: COD segment of OpenJPEG's lossless defaults: no precincts/SOP/EPH, LRCP, 1 layer, no MCT,
#: 5 decompositions, 64 x 64 code-blocks, no code-block style, reversible 5/3 wavelet.
_OPENJPEG_LOSSLESS_COD = bytes([0, 0, 0, 1, 0, 5, 4, 4, 0, 1])


def _j2k(frame: bytes, syntax: U.UID, rows: int, cols: int, bits: _StoredBits, where: str) -> tuple[np.ndarray, str]:
    cs = _j2k_codestream(frame, where)
    siz = _j2k_segments(cs).get(0x51, b"")
    if len(siz) < 39:
        raise InputError(f"{where}: the JPEG 2000 image header (SIZ) is missing or truncated; {_REMEDY_COPY}")
    _, xsiz, ysiz, xo, yo, _, _, _, _, csiz = struct.unpack(">HIIIIIIIIH", siz[:36])
    precision = (siz[36] & 0x7F) + 1
    array = _decode_checked("JPEG 2000", "openjpeg", frame, (ysiz - yo, xsiz - xo, csiz, precision), rows, cols, bits, where)
    segments = _j2k_segments(cs)
    verifiable = (
        syntax == U.JPEG2000Lossless
        and segments.get(0x52) == _OPENJPEG_LOSSLESS_COD
        and b"OpenJPEG" in segments.get(0x64, b"")
    )
    if not verifiable:
        return bits.signed_values(array, precision), "JPEG 2000: headers and complete decoding checked (stream not re-encodable here)"
    try:
        again = _plugin("openjpeg", where).encode(np.ascontiguousarray(array), bits_stored=precision)
    except Exception as exc:
        raise _decoder_failure(where, exc) from None
    if _strip_comments(bytes(again)) != _strip_comments(cs).rstrip(b"\x00"):
        raise InputError(f"{where} does not re-encode to itself: the JPEG 2000 stream is damaged (or was written by another "
                         f"OpenJPEG version); {_REMEDY_COPY}, or {_REMEDY_DECOMPRESS} after checking the images")
    return bits.signed_values(array, precision), "JPEG 2000 Lossless: re-encoded and compared byte for byte"
