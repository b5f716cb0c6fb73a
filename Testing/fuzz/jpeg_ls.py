"""A minimal JPEG-LS lossless encoder (ITU-T T.87, NEAR = 0, one component, default parameters), to make
test files: neither pydicom nor the pylibjpeg plugins installed here can encode this syntax.

Regular mode (median edge predictor, 365 gradient contexts with bias correction, limited-length Golomb
codes) and run mode (run lengths by the J table, run-interruption samples in their two contexts), as in
T.87 annex A; the thresholds T1..T3, RESET 64 and MAXVAL 2**P - 1 are the defaults, so the stream needs
no LSE segment. Checked by decoding with the pylibjpeg-libjpeg plugin (Testing/Python).
"""

from __future__ import annotations

import struct

import numpy as np

__all__ = ["encode_jpeg_ls"]

_J = (0, 0, 0, 0, 1, 1, 1, 1, 2, 2, 2, 2, 3, 3, 3, 3, 4, 4, 5, 5, 6, 6, 7, 7, 8, 9, 10, 11, 12, 13, 14, 15)
_RESET = 64


class _Bits:
    """Bit writer with JPEG-LS marker stuffing (after a 0xFF byte the next byte carries 7 bits)."""

    def __init__(self) -> None:
        self.out = bytearray()
        self.acc, self.n, self.after_ff = 0, 0, False

    def put(self, value: int, count: int) -> None:
        for i in range(count - 1, -1, -1):
            self.acc = (self.acc << 1) | ((value >> i) & 1)
            self.n += 1
            if self.n == (7 if self.after_ff else 8):
                self.out.append(self.acc)
                self.after_ff = self.acc == 0xFF
                self.acc, self.n = 0, 0

    def flush(self) -> bytes:
        if self.n:
            self.put(0, (7 if self.after_ff else 8) - self.n)
        if self.after_ff:
            self.out.append(0)
        return bytes(self.out)


def _quantise(d: int, t1: int, t2: int, t3: int) -> int:
    if d <= -t3:
        return -4
    if d <= -t2:
        return -3
    if d <= -t1:
        return -2
    if d < 0:
        return -1
    if d == 0:
        return 0
    if d < t1:
        return 1
    if d < t2:
        return 2
    if d < t3:
        return 3
    return 4


def encode_jpeg_ls(image: np.ndarray, precision: int) -> bytes:
    """``image`` (rows, cols) of unsigned integers below ``2**precision`` (2..16) as a JPEG-LS lossless stream."""
    img = np.asarray(image, dtype=np.int64)
    rows, cols = img.shape
    maxval = (1 << precision) - 1
    rng = maxval + 1
    qbpp = max(1, (rng - 1).bit_length())
    bpp = max(2, qbpp)
    limit = 2 * (bpp + max(8, bpp))
    factor = (min(maxval, 4095) + 128) >> 8
    t1 = min(max(factor * 1 + 2, 1), maxval)
    t2 = min(max(factor * 4 + 3, t1), maxval)
    t3 = min(max(factor * 17 + 4, t2), maxval)
    a_init = max(2, (rng + 32) >> 6)
    A, B, C, N = {}, {}, {}, {}
    A_run, N_run, Nn = [a_init, a_init], [1, 1], [0, 0]
    run_index = 0
    bits = _Bits()

    def golomb(value: int, k: int, glimit: int) -> None:
        high = value >> k
        if high < glimit - qbpp - 1:
            bits.put(0, high)
            bits.put(1, 1)
            bits.put(value & ((1 << k) - 1), k)
        else:
            bits.put(0, glimit - qbpp - 1)
            bits.put(1, 1)
            bits.put(value - 1, qbpp)

    def reduce(err: int) -> int:
        if err < 0:
            err += rng
        if err >= (rng + 1) // 2:
            err -= rng
        return err

    prev = [0] * (cols + 2)  # index c + 1 holds column c; [0] the left extension, [cols + 1] the right one
    prev_first = 0  # Ra of the previous line's first sample (Rc of this line's first sample)
    for r in range(rows):
        line = img[r].tolist()
        cur = [0] * (cols + 2)
        prev[cols + 1] = prev[cols]
        prev[0] = prev_first
        cur[0] = prev[1]
        prev_first = cur[0]
        c = 0
        while c < cols:
            ra, rb, rc, rd = cur[c], prev[c + 1], prev[c], prev[c + 2]
            x = line[c]
            if rd == rb and rb == rc and rc == ra:  # run mode
                run_val, count = ra, 0
                while c < cols and line[c] == run_val:
                    cur[c + 1] = run_val
                    count += 1
                    c += 1
                while count >= (1 << _J[run_index]):
                    bits.put(1, 1)
                    count -= 1 << _J[run_index]
                    if run_index < 31:
                        run_index += 1
                if c == cols:
                    if count:
                        bits.put(1, 1)
                    break
                bits.put(0, 1)
                bits.put(count, _J[run_index])
                x, ra, rb = line[c], cur[c], prev[c + 1]
                ri_type = 1 if ra == rb else 0
                err = x - ra if ri_type else (x - rb) * (-1 if ra > rb else 1)
                err = reduce(err)
                q = ri_type
                temp = A_run[q] + (N_run[q] >> 1) if ri_type else A_run[q]
                k = 0
                while (N_run[q] << k) < temp:
                    k += 1
                flag = 1 if ((k == 0 and err > 0 and 2 * Nn[q] < N_run[q]) or (err < 0 and 2 * Nn[q] >= N_run[q])
                             or (err < 0 and k != 0)) else 0
                em = 2 * abs(err) - ri_type - flag
                golomb(em, k, limit - _J[run_index] - 1)
                if err < 0:
                    Nn[q] += 1
                A_run[q] += (em + 1 - ri_type) >> 1
                if N_run[q] == _RESET:
                    A_run[q] >>= 1
                    N_run[q] >>= 1
                    Nn[q] >>= 1
                N_run[q] += 1
                if run_index > 0:
                    run_index -= 1
                cur[c + 1] = x
                c += 1
                continue
            q1, q2, q3 = _quantise(rd - rb, t1, t2, t3), _quantise(rb - rc, t1, t2, t3), _quantise(rc - ra, t1, t2, t3)
            sign = 1
            if q1 < 0 or (q1 == 0 and (q2 < 0 or (q2 == 0 and q3 < 0))):
                q1, q2, q3, sign = -q1, -q2, -q3, -1
            q = (q1, q2, q3)
            if q not in A:
                A[q], B[q], C[q], N[q] = a_init, 0, 0, 1
            if rc >= max(ra, rb):
                px = min(ra, rb)
            elif rc <= min(ra, rb):
                px = max(ra, rb)
            else:
                px = ra + rb - rc
            px = min(max(px + sign * C[q], 0), maxval)
            err = reduce((x - px) * sign)
            k = 0
            while (N[q] << k) < A[q]:
                k += 1
            if k == 0 and 2 * B[q] <= -N[q]:
                merr = 2 * err + 1 if err >= 0 else -2 * (err + 1)
            else:
                merr = 2 * err if err >= 0 else -2 * err - 1
            golomb(merr, k, limit)
            B[q] += err
            A[q] += abs(err)
            if N[q] == _RESET:
                A[q] >>= 1
                B[q] >>= 1
                N[q] >>= 1
            N[q] += 1
            if B[q] <= -N[q]:
                B[q] += N[q]
                if C[q] > -128:
                    C[q] -= 1
                if B[q] <= -N[q]:
                    B[q] = -N[q] + 1
            elif B[q] > 0:
                B[q] -= N[q]
                if C[q] < 127:
                    C[q] += 1
                if B[q] > 0:
                    B[q] = 0
            cur[c + 1] = x
            c += 1
        prev = cur
    out = bytearray(b"\xff\xd8")
    out += b"\xff\xf7" + struct.pack(">HBHHB", 11, precision, rows, cols, 1) + bytes([1, 0x11, 0])
    out += b"\xff\xda" + struct.pack(">HB", 8, 1) + bytes([1, 0, 0, 0, 0])
    out += bits.flush() + b"\xff\xd9"
    return bytes(out)
