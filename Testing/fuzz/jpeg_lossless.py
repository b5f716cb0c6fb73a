"""A minimal JPEG Lossless encoder (process 14, first-order prediction: DICOM JPEG Lossless SV1),
to make test files: neither pydicom nor the pylibjpeg plugins can encode this syntax.

One greyscale component, predictor 1 (left neighbour; the first row predicts from the left, the
first column from above, the first pixel from ``2**(P-1)``), no point transform, one Huffman
table with fixed code lengths for the 17 difference categories.
"""

from __future__ import annotations

import struct

import numpy as np

__all__ = ["encode_jpeg_lossless"]

#: Code length of difference category 0..16 (Kraft sum < 1, so no all-ones code).
_LENGTHS = (2, 3, 3, 3, 3, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14)


def _codes() -> dict[int, tuple[int, int]]:
    """Canonical Huffman codes: category -> (code, length), assigned in order of increasing length."""
    order = sorted(range(17), key=lambda s: (_LENGTHS[s], s))
    codes, code, length = {}, 0, _LENGTHS[order[0]]
    for symbol in order:
        code <<= _LENGTHS[symbol] - length
        length = _LENGTHS[symbol]
        codes[symbol] = (code, length)
        code += 1
    return codes


def encode_jpeg_lossless(image: np.ndarray, precision: int) -> bytes:
    """``image`` (rows, cols) of unsigned integers below ``2**precision`` as a JPEG Lossless SV1 stream."""
    img = np.asarray(image, dtype=np.int64)
    rows, cols = img.shape
    pred = np.empty_like(img)
    pred[0, 0] = 1 << (precision - 1)
    pred[0, 1:] = img[0, :-1]
    pred[1:, 0] = img[:-1, 0]
    pred[1:, 1:] = img[1:, :-1]
    diff = (img - pred) % 65536
    diff = np.where(diff > 32768, diff - 65536, diff)
    codes = _codes()
    bits = bytearray()
    acc, nacc = 0, 0

    def put(value: int, n: int) -> None:
        nonlocal acc, nacc
        acc = (acc << n) | (value & ((1 << n) - 1))
        nacc += n
        while nacc >= 8:
            nacc -= 8
            byte = (acc >> nacc) & 0xFF
            bits.append(byte)
            if byte == 0xFF:
                bits.append(0x00)
        acc &= (1 << nacc) - 1

    for d in diff.ravel().tolist():
        category = 0 if d == 0 else (16 if d == 32768 else abs(d).bit_length())
        code, length = codes[category]
        put(code, length)
        if 0 < category < 16:
            put(d if d > 0 else d - 1, category)
    if nacc:
        put((1 << (8 - nacc)) - 1, 8 - nacc)
    counts = [sum(1 for s in range(17) if _LENGTHS[s] == n) for n in range(1, 17)]
    values = sorted(range(17), key=lambda s: (_LENGTHS[s], s))
    dht = bytes([0x00]) + bytes(counts) + bytes(values)
    out = bytearray(b"\xff\xd8")
    out += b"\xff\xc3" + struct.pack(">HBHHB", 11, precision, rows, cols, 1) + bytes([1, 0x11, 0])
    out += b"\xff\xc4" + struct.pack(">H", 2 + len(dht)) + dht
    out += b"\xff\xda" + struct.pack(">HB", 8, 1) + bytes([1, 0x00, 1, 0, 0])
    out += bits + b"\xff\xd9"
    return bytes(out)
