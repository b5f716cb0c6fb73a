"""Atomic result folders (geopose.outputs): checked before the work, locked, cleared, written by
temporary name and rename, the record last; a run killed at any point never leaves a result.json
that does not belong to the files beside it."""

from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from geopose.errors import InputError
from geopose.outputs import LOCK_NAME, RECORD_NAME, TEMP_PREFIX, OutputFolder, atomic_write

REPO = Path(__file__).resolve().parents[2]
NAMES = ("overlay_pa.png", "overlay_lat.png")


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_refuses_a_file_and_a_path_under_a_file(tmp_path: Path):
    (tmp_path / "f").write_text("x")
    with pytest.raises(InputError, match="exists and is not a folder"):
        OutputFolder(tmp_path / "f", NAMES).open()
    with pytest.raises(InputError, match="cannot create the output folder"):
        OutputFolder(tmp_path / "f" / "sub", NAMES).open()
    assert (tmp_path / "f").read_text() == "x"


@pytest.mark.skipif(os.name != "posix" or os.geteuid() == 0, reason="root writes into read-only folders")
def test_refuses_a_read_only_folder(tmp_path: Path):
    folder = tmp_path / "ro"
    folder.mkdir()
    folder.chmod(0o500)
    try:
        with pytest.raises(InputError, match="cannot write into"):
            OutputFolder(folder, NAMES).open()
    finally:
        folder.chmod(0o700)


def test_second_run_into_the_same_folder_is_refused(tmp_path: Path):
    with OutputFolder(tmp_path / "out", NAMES):
        with pytest.raises(InputError, match=rf"another geopose run \(pid {os.getpid()}\) is writing into"):
            OutputFolder(tmp_path / "out", NAMES).open()
    with OutputFolder(tmp_path / "out", NAMES) as again:  # released when the first run ends
        again.commit({"ok": True})


def test_stale_results_are_cleared_first_and_the_record_lists_the_outputs(tmp_path: Path):
    out = tmp_path / "out"
    out.mkdir()
    for name in (RECORD_NAME, *NAMES, f"{TEMP_PREFIX}old.png", "notes.txt"):
        (out / name).write_text("old")
    with OutputFolder(out, NAMES) as folder:
        assert sorted(p.name for p in out.iterdir()) == [LOCK_NAME, "notes.txt"]  # only other files stay
        folder.write_bytes("overlay_pa.png", b"pa")
        folder.write_file("overlay_lat.png", lambda p: p.write_bytes(b"lat"))
        assert not (out / RECORD_NAME).exists()
        record = folder.commit({"views": 2})
    data = json.loads(record.read_text())
    assert data["views"] == 2 and data["outputs"] == {n: _sha(out / n) for n in NAMES}
    assert oct((out / "overlay_pa.png").stat().st_mode & 0o777) == oct(0o666 & ~_umask())
    with pytest.raises(RuntimeError, match="not one of the outputs"):
        with OutputFolder(out, NAMES) as folder:
            folder.write_bytes("other.png", b"")


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def test_a_failed_write_leaves_neither_the_file_nor_a_temporary(tmp_path: Path):
    def fails(path: Path) -> None:
        path.write_bytes(b"half")
        raise OSError(28, "No space left on device")

    with pytest.raises(OSError):
        atomic_write(tmp_path / "a.png", fails)
    assert list(tmp_path.iterdir()) == []


WRITER = r"""
import sys, time
from pathlib import Path
from geopose.outputs import OutputFolder
out, run = Path(sys.argv[1]), int(sys.argv[2])
def slow(data):
    def write(path):
        with open(path, "wb") as f:
            for k in range(0, len(data), 4096):
                f.write(data[k:k + 4096]); f.flush(); time.sleep(0.005)
    return write
with OutputFolder(out, ("overlay_pa.png", "overlay_lat.png")) as folder:
    print("open", flush=True)
    for name in ("overlay_pa.png", "overlay_lat.png"):
        folder.write_file(name, slow(bytes([run % 256]) * 200_000))
    folder.commit({"run": run})
print("done", flush=True)
"""


def _check_consistent(out: Path, run: int) -> str:
    record = out / RECORD_NAME
    if not record.exists():
        return "none"
    data = json.loads(record.read_text())
    assert data["run"] == run, "a result.json of an earlier run survived a new run"
    for name, digest in data["outputs"].items():
        assert _sha(out / name) == digest, f"{name} does not belong to result.json"
        assert (out / name).read_bytes()[:1] == bytes([run % 256])
    return "complete"


def test_killing_a_run_at_any_point_leaves_no_foreign_record(tmp_path: Path):
    out = tmp_path / "out"
    env = {**os.environ, "PYTHONPATH": str(REPO / "Logic")}
    states = []
    for run, delay in enumerate([0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 99.0]):  # s after the folder was opened
        proc = subprocess.Popen([sys.executable, "-c", WRITER, str(out), str(run)], env=env, stdout=subprocess.PIPE, text=True)
        assert proc.stdout.readline().strip() == "open"
        try:
            proc.wait(timeout=delay)
        except subprocess.TimeoutExpired:
            os.kill(proc.pid, signal.SIGKILL)
            proc.wait()
        states.append(_check_consistent(out, run))
    assert states.count("none") >= 4 and states[-1] == "complete", states  # most runs were killed before their record
    assert not list(out.glob(f"{TEMP_PREFIX}*"))  # the last run cleared what the killed ones left


@pytest.mark.slow
def test_killed_registration_leaves_no_foreign_record(tmp_path: Path):
    """A real ``geopose register`` on a 4 mm phantom, killed at several points, then run to the end."""
    case = tmp_path / "case"
    env = {**os.environ, "PYTHONPATH": str(REPO / "Logic")}
    subprocess.run([sys.executable, "-m", "geopose.cli", "phantom", "--seed", "3", "--out", str(case), "--spacing-mm", "4",
                    "--max-matrix-px", "128"], env=env, check=True, capture_output=True)
    out = tmp_path / "out"
    argv = [sys.executable, "-m", "geopose.cli", "register", "--cta", str(case / "cta.nii.gz"), "--dsa-pa", str(case / "dsa_pa.dcm"),
            "--dsa-lat", str(case / "dsa_lat.dcm"), "--out", str(out), "--iterations", "0", "--refine-steps", "1",
            "--tto-px", "32", "--device", "cpu"]
    done = subprocess.run(argv, env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    total = json.loads((out / RECORD_NAME).read_text())["runtimes_s"]["total"]
    for fraction in (0.2, 0.8, 1.0, 1.2):
        proc = subprocess.Popen(argv, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        time.sleep(8 + fraction * total)  # start-up, then into the registration / the writing
        proc.kill()
        proc.wait()
        record = out / RECORD_NAME
        if record.exists():
            data = json.loads(record.read_text())
            assert all(_sha(out / n) == d for n, d in data["outputs"].items())
