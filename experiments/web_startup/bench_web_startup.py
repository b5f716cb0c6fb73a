"""Time to interactive of ``geopose view``: from launching the command to an enabled Register button
in Chromium (Debian's, driven by Playwright), with the server's own CPU time at that moment.

On a shared machine the wall time grows with the other processes' load; the server's CPU seconds
are what an idle machine would wait for its part (the page itself loads in about a second).
Writes a table to ``experiments/web_startup/web_startup.md``::

    python experiments/web_startup/bench_web_startup.py --runs 5 --doc experiments/web_startup/web_startup.md
"""

from __future__ import annotations

import argparse
import os
import platform
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync"]


def cpu_seconds(pid: int) -> float:
    """User + system CPU seconds of process ``pid`` so far (Linux /proc)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def one_run(context) -> dict:
    port = free_port()
    load = os.getloadavg()[0]
    t0 = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-m", "geopose.cli", "view", "--port", str(port)], stdout=subprocess.PIPE,
                            text=True, env=dict(os.environ, PYTHONUNBUFFERED="1"))
    try:
        proc.stdout.readline()
        listening_s, listening_cpu_s = time.perf_counter() - t0, cpu_seconds(proc.pid)
        page = context.new_page()
        page.goto(f"http://127.0.0.1:{port}/")
        page.wait_for_selector("#btn-register:not([disabled])", timeout=120000)
        interactive_s, interactive_cpu_s = time.perf_counter() - t0, cpu_seconds(proc.pid)
        page.wait_for_selector("#views-loading", state="detached", timeout=120000)
        views_s = time.perf_counter() - t0
        page.close()
    finally:
        proc.terminate()
        proc.wait()
    return {"load": load, "listening_s": listening_s, "listening_cpu_s": listening_cpu_s,
            "interactive_s": interactive_s, "interactive_cpu_s": interactive_cpu_s, "views_s": views_s}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=5)
    parser.add_argument("--doc", help="markdown file the table is written to")
    args = parser.parse_args(argv)
    from playwright.sync_api import sync_playwright

    chromium = shutil.which("chromium")
    if chromium is None:
        raise SystemExit("no chromium on PATH: apt-get install chromium")
    with sync_playwright() as pw, tempfile.TemporaryDirectory() as profile:
        context = pw.chromium.launch_persistent_context(profile, executable_path=chromium, args=FLAGS, headless=True)
        runs = [one_run(context) for _ in range(args.runs)]
        context.close()
    lines = [
        "# `geopose view`: time to interactive",
        "",
        f"`python experiments/web_startup/bench_web_startup.py --runs {args.runs}` on {platform.node()} ({os.cpu_count()} CPUs), "
        f"{time.strftime('%Y-%m-%d')}: launch of `geopose view` to an enabled Register button in headless Chromium; "
        "CPU = the server process's user + system seconds at that moment; 3D view = until the 3D view is in the page "
        "(Slicer's MRML is imported after the server listens); load = the machine's 1-minute load average at launch "
        "(other processes).",
        "",
        "| run | load | listening (s) | server CPU (s) | interactive (s) | server CPU (s) | 3D view (s) |",
        "|---|---|---|---|---|---|---|",
    ]
    for n, r in enumerate(runs, 1):
        lines.append(f"| {n} | {r['load']:.1f} | {r['listening_s']:.2f} | {r['listening_cpu_s']:.2f} | "
                     f"{r['interactive_s']:.2f} | {r['interactive_cpu_s']:.2f} | {r['views_s']:.2f} |")
    text = "\n".join(lines) + "\n"
    print(text)
    if args.doc:
        Path(args.doc).write_text(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
