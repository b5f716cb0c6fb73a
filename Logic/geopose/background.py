"""Run a computation on a worker thread while the calling thread stays responsive.

A front end whose own thread must keep working (a GUI's event loop: the Slicer module passes
``slicer.app.processEvents``) hands the computation to :func:`run_in_background`; the computation
must touch neither the GUI nor the scene (``register_case`` touches neither), its progress reports
reach the caller on the calling thread. Standard library only.
"""

from __future__ import annotations

import threading
from typing import Any, Callable, Optional

__all__ = ["run_in_background"]


def run_in_background(work: Callable[[Callable[..., None]], Any], poll: Callable[[], None], interval_s: float,
                      progress: Optional[Callable[..., None]] = None, name: str = "GeoPose worker") -> Any:
    """``work(report)`` on a worker thread while this thread calls ``poll()`` every ``interval_s`` (and once
    after the worker ends) and passes the latest ``report(*args)`` of the worker on to ``progress(*args)``
    (each new report once; reports in between are skipped). Returns what ``work`` returns, or raises what it
    raised, on this thread."""
    lock = threading.Lock()
    latest: dict = {}
    outcome: dict = {}

    def report(*args) -> None:
        with lock:
            latest["progress"] = args

    def target() -> None:
        try:
            outcome["result"] = work(report)
        except BaseException as exc:  # re-raised on the calling thread below
            outcome["error"] = exc

    worker = threading.Thread(target=target, name=name, daemon=True)
    worker.start()
    shown = None
    while True:
        worker.join(interval_s)
        with lock:
            now = latest.get("progress")
        if progress is not None and now is not None and now != shown:
            progress(*now)
            shown = now
        poll()
        if not worker.is_alive():
            break
    if "error" in outcome:
        raise outcome["error"]
    return outcome["result"]
