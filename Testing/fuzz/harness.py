"""A small, library-independent fuzz harness: seeded byte mutations and isolated, bounded case runs.

Cases are numbered; case ``i`` of seed ``s`` draws everything from ``numpy.random.default_rng([s, i])``,
so a run is reproducible case by case. Each case runs in a forked worker process with an
address-space limit (soft ``RLIMIT_AS``: the worker's size at fork plus ``memory_bytes``; verification
code lifts it with :func:`unlimited_memory`) and a
wall-clock timeout; a worker that dies is a *crash*, one that overruns is a *hang*, and either
is replaced by a fresh fork. The case function returns ``(outcome, detail)``; an exception
escaping it is recorded as ``other exception``.
"""

from __future__ import annotations

import contextlib
import faulthandler
import multiprocessing
import multiprocessing.connection as mp_connection
import os
import resource
import signal
import threading
import time
import traceback
from collections import Counter
from dataclasses import dataclass, field
from typing import Callable, Iterable

import numpy as np

__all__ = [
    "OUTCOMES", "FAILURES", "CaseResult", "Report", "run_cases",
    "flip_bits", "truncate", "splice_bytes", "interesting_number", "unlimited_memory",
]

#: Outcome classes, in table order.
OUTCOMES = (
    "clean error",
    "accepted, identical",
    "accepted, faithful",
    "accepted, WRONG",
    "other exception",
    "out of memory",
    "hang",
    "crash",
)
#: Outcomes that count as failures.
FAILURES = ("accepted, WRONG", "other exception", "out of memory", "hang", "crash")


@dataclass
class CaseResult:
    index: int
    target: str
    mutation: str
    outcome: str
    detail: str = ""
    seconds: float = 0.0


@dataclass
class Report:
    results: list[CaseResult] = field(default_factory=list)

    def counts(self) -> dict[str, Counter]:
        table: dict[str, Counter] = {}
        for r in self.results:
            table.setdefault(r.target, Counter())[r.outcome] += 1
        return table

    def failures(self) -> list[CaseResult]:
        return [r for r in self.results if r.outcome in FAILURES]

    def table(self) -> str:
        """Markdown table: one row per target, one column per outcome, and a total row."""
        counts = self.counts()
        total: Counter = Counter()
        lines = ["| target | cases | " + " | ".join(OUTCOMES) + " |", "|---|---:|" + "---:|" * len(OUTCOMES)]
        for target in sorted(counts):
            c = counts[target]
            total.update(c)
            lines.append(f"| {target} | {sum(c.values())} | " + " | ".join(str(c.get(o, 0)) for o in OUTCOMES) + " |")
        lines.append(f"| **all** | **{sum(total.values())}** | " + " | ".join(f"**{total.get(o, 0)}**" for o in OUTCOMES) + " |")
        return "\n".join(lines)


# -------------------------------------------------------------------- mutations


def flip_bits(data: bytes, rng: np.random.Generator, lo: int = 0, hi: int | None = None) -> tuple[bytes, list[int]]:
    """1-4 random bit flips at positions in ``[lo, hi)``; the mutated bytes and the positions."""
    hi = len(data) if hi is None else hi
    out = bytearray(data)
    positions = sorted({int(p) for p in rng.integers(lo, max(lo + 1, hi), size=int(rng.integers(1, 5)))})
    for p in positions:
        out[p] ^= 1 << int(rng.integers(0, 8))
    return bytes(out), positions


def truncate(data: bytes, rng: np.random.Generator) -> tuple[bytes, int]:
    """``data`` cut at a random length (0 .. len - 1)."""
    cut = int(rng.integers(0, len(data)))
    return data[:cut], cut


def splice_bytes(data: bytes, offset: int, value: bytes) -> bytes:
    return data[:offset] + value + data[offset + len(value):]


def interesting_number(rng: np.random.Generator, original: float | None = None) -> float:
    """A value likely to break a reader: 0, +-1, extremes, NaN/Inf, or the original scaled."""
    choices = [0.0, 1.0, -1.0, 2.0, 65535.0, 65536.0, 2.0**31, -(2.0**31), 1e9, -1e9, 1e-9, float("nan"), float("inf"), -float("inf")]
    if original is not None:
        choices += [original * 2, original / 2, -original, original + 1, original * 1000]
    return float(choices[int(rng.integers(0, len(choices)))])


# ----------------------------------------------------------------------- runner


def _limit_memory(memory_bytes: int) -> None:
    try:
        with open("/proc/self/status") as f:
            size_kb = next(int(line.split()[1]) for line in f if line.startswith("VmSize:"))
    except (OSError, StopIteration):
        size_kb = 0
    limit = size_kb * 1024 + memory_bytes
    resource.setrlimit(resource.RLIMIT_AS, (limit, resource.getrlimit(resource.RLIMIT_AS)[1]))


@contextlib.contextmanager
def unlimited_memory():
    """Lift the worker's (soft) memory limit for code that checks a result, not the code under test."""
    soft, hard = resource.getrlimit(resource.RLIMIT_AS)
    resource.setrlimit(resource.RLIMIT_AS, (hard, hard))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_AS, (soft, hard))


def _worker(conn, case: Callable[[int], tuple[str, str, str, str]], describe: Callable[[int], tuple[str, str]],
            memory_bytes: int) -> None:
    faulthandler.disable()  # a crash is reported by the parent, not dumped by the worker
    # No core file: writing one of a worker this size can outlast the timeout, and the crash would read as a hang.
    resource.setrlimit(resource.RLIMIT_CORE, (0, 0))
    _limit_memory(memory_bytes)
    while True:
        index = conn.recv()
        if index is None:
            return
        start = time.perf_counter()
        try:
            target, mutation, outcome, detail = case(index)
        except MemoryError:
            (target, mutation), outcome, detail = describe(index), "out of memory", "MemoryError"
        except BaseException as exc:  # the case function's own guard failed: an escaped exception
            (target, mutation), outcome = describe(index), "other exception"
            detail = "".join(traceback.format_exception_only(type(exc), exc)).strip()
        conn.send((target, mutation, outcome, detail[:2000], time.perf_counter() - start))


def run_cases(
    case: Callable[[int], tuple[str, str, str, str]],
    indices: Iterable[int],
    *,
    describe: Callable[[int], tuple[str, str]],
    workers: int = 2,
    timeout_s: float = 30.0,
    memory_bytes: int = 2 << 30,
    cases_per_worker: int = 250,
    progress: Callable[[int], None] | None = None,
) -> Report:
    """Run ``case(i)`` for every index in forked workers. ``case`` returns ``(target, mutation, outcome,
    detail)``; ``describe(i)`` names a case's target and mutation when its worker hangs or crashes. A worker
    is replaced after ``cases_per_worker`` cases, so what native code leaks does not add up to a memory error."""
    ctx = multiprocessing.get_context("fork")
    queue = list(indices)
    lock = threading.Lock()
    report = Report()

    def spawn():
        parent, child = ctx.Pipe()
        proc = ctx.Process(target=_worker, args=(child, case, describe, memory_bytes), daemon=True)
        proc.start()
        child.close()
        return proc, parent

    def stop(proc, conn) -> None:
        try:
            conn.send(None)
        except (BrokenPipeError, OSError):
            pass
        proc.join(timeout=10)
        if proc.is_alive():
            proc.kill()
            proc.join()
        conn.close()

    def lane() -> None:
        proc, conn = spawn()
        served = 0
        while True:
            with lock:
                if not queue:
                    break
                index = queue.pop(0)
            if served >= cases_per_worker:
                stop(proc, conn)
                proc, conn = spawn()
                served = 0
            served += 1
            start = time.perf_counter()
            conn.send(index)
            result, outcome = None, "hang"
            # Wait on the worker's exit as well as its pipe: a worker forked by another lane can hold a copy
            # of this pipe's write end, so a dead worker need not close the pipe.
            ready = mp_connection.wait([conn, proc.sentinel], timeout_s)
            if conn in ready or conn.poll(0):
                try:
                    target, mutation, outcome, detail, seconds = conn.recv()
                    result = CaseResult(index, target, mutation, outcome, detail, seconds)
                except (EOFError, OSError):  # the worker died
                    outcome = "crash"
            elif ready:
                outcome = "crash"
            if result is None:
                if outcome == "hang":
                    proc.kill()
                proc.join()
                if outcome == "hang" and proc.exitcode not in (-signal.SIGKILL, None):
                    outcome = "crash"  # it was already dying of its own signal when the timeout came
                target, mutation = describe(index)
                result = CaseResult(index, target, mutation, outcome, f"exit code {proc.exitcode}", time.perf_counter() - start)
                conn.close()
                proc, conn = spawn()
                served = 0
            with lock:
                report.results.append(result)
                if progress:
                    progress(len(report.results))
        stop(proc, conn)

    threads = [threading.Thread(target=lane) for _ in range(max(1, workers))]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    report.results.sort(key=lambda r: r.index)
    return report


def pid_scratch(root: str) -> str:
    """A scratch folder of this (worker) process under ``root``."""
    path = os.path.join(root, f"worker-{os.getpid()}")
    os.makedirs(path, exist_ok=True)
    return path
