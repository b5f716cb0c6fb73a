"""The input fuzz suite (Testing/fuzz): a few hundred seeded mutations of every input kind must give
no traceback, hang, crash or wrongly accepted input; the harness itself classifies crashes and hangs;
runs are reproducible. ``make fuzz`` runs 10,000 cases and writes docs/fuzz.md."""

from __future__ import annotations

import os
import signal
import sys
import time
from pathlib import Path

import pytest

FUZZ = Path(__file__).resolve().parents[1] / "fuzz"
sys.path.insert(0, str(FUZZ))

import harness  # noqa: E402
import run as fuzz_run  # noqa: E402
import targets  # noqa: E402
import cli_targets  # noqa: E402

#: Cases of the default run (about 15 s on 2 cores).
DEFAULT_CASES = 600


@pytest.fixture(scope="module")
def report() -> harness.Report:
    return fuzz_run.fuzz(DEFAULT_CASES, seed=2026, workers=2, timeout_s=30.0, memory_bytes=2 << 30)


def test_no_failures(report: harness.Report):
    failures = report.failures()
    assert not failures, "\n".join(f"case {r.index} {r.target} {r.mutation}: {r.outcome}: {r.detail[-600:]}" for r in failures[:10])
    assert len(report.results) == DEFAULT_CASES


def test_every_target_is_exercised_and_refuses_damage(report: harness.Report):
    counts = report.counts()
    assert set(counts) == set(targets.TARGETS)
    for target, c in counts.items():
        assert c["clean error"] >= 0.3 * sum(c.values()), (target, c)  # most damage is refused with a clear line


def test_clean_errors_are_one_line(report: harness.Report):
    for r in report.results:
        if r.outcome == "clean error":
            assert "\n" not in r.detail and "Traceback" not in r.detail, r.detail


#: CLI-level cases of the default run (``geopose register`` situations; about 20 s on 2 cores).
DEFAULT_CLI_CASES = 40


def test_cli_level_cases_are_refused_cleanly_or_read_faithfully():
    """Out-folder collisions, special files, cross-input mismatches, misdeclared CT: exit 2, one line, inputs
    byte-identical; signed CT encodings read as pydicom and GDCM read them."""
    report = fuzz_run.fuzz(DEFAULT_CLI_CASES, seed=2026, workers=2, timeout_s=60.0, memory_bytes=2 << 30, suite="cli")
    failures = report.failures()
    assert not failures, "\n".join(f"case {r.index} {r.target} {r.mutation}: {r.outcome}: {r.detail[-600:]}" for r in failures[:10])
    counts = report.counts()
    assert set(counts) == set(cli_targets.CLI_TARGETS)
    for target in ("out_collision", "special_file", "mismatch"):
        assert counts[target]["clean error"] == sum(counts[target].values()), (target, counts[target])
    assert counts["ct_encoding"]["accepted, faithful"] == sum(counts["ct_encoding"].values())


def test_runs_are_reproducible():
    a = fuzz_run.fuzz(24, seed=7, workers=2, timeout_s=30.0, memory_bytes=2 << 30)
    b = fuzz_run.fuzz(24, seed=7, workers=1, timeout_s=30.0, memory_bytes=2 << 30)
    assert [(r.target, r.mutation, r.outcome) for r in a.results] == [(r.target, r.mutation, r.outcome) for r in b.results]


def _misbehaving(index: int):
    if index == 0:
        os.kill(os.getpid(), signal.SIGSEGV)
    if index == 1:
        time.sleep(30)
    if index == 2:
        bytearray(8 << 30)  # beyond the worker's memory limit
    if index == 3:
        raise KeyError("escaped")
    return "t", "m", "clean error", "fine"


def test_harness_classifies_crash_hang_memory_and_escapes():
    report = harness.run_cases(_misbehaving, range(5), describe=lambda i: ("t", "m"), workers=2, timeout_s=2.0,
                               memory_bytes=1 << 30)
    assert [r.outcome for r in report.results] == ["crash", "hang", "out of memory", "other exception", "clean error"]
    assert "KeyError" in report.results[3].detail
    table = report.table()
    assert "| t | 5 | 1 |" in table and "**5**" in table
