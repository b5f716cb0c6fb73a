"""Run a computation on a worker thread while the calling thread stays responsive.

A front end whose own thread must keep working (a GUI's event loop: the Slicer module passes
``slicer.app.processEvents``) hands the computation to :func:`run_in_background`; the computation
must touch neither the GUI nor the scene (``register_case`` touches neither), its progress reports
and the results it hands over before it ends reach the caller on the calling thread. Standard library only.
"""

from __future__ import annotations

import logging
import threading
from typing import Any, Callable, Optional

__all__ = ["run_in_background"]


def run_in_background(work: Callable[..., Any], poll: Callable[[], None], interval_s: float,
                      progress: Optional[Callable[..., None]] = None, name: str = "GeoPose worker",
                      deliver: Optional[Callable[[Any], None]] = None) -> Any:
    """``work(report)`` on a worker thread while this thread calls ``poll()`` every ``interval_s`` (and once
    after the worker ends) and passes the latest ``report(*args)`` of the worker on to ``progress(*args)``
    (each new report once; reports in between are skipped). With ``deliver``, ``work(report, hand_over)`` is
    called instead and every ``hand_over(item)`` reaches ``deliver(item)`` on this thread, in order, none skipped,
    before the next ``poll()`` (an error in ``deliver`` is logged, the work goes on). Returns what ``work`` returns,
    or raises what it raised, on this thread."""
    lock = threading.Lock()
    latest: dict = {}
    outcome: dict = {}
    handed: list = []

    def report(*args) -> None:
        with lock:
            latest["progress"] = args

    def hand_over(item: Any) -> None:
        with lock:
            handed.append(item)

    def target() -> None:
        try:
            outcome["result"] = work(report) if deliver is None else work(report, hand_over)
        except BaseException as exc:  # re-raised on the calling thread below
            outcome["error"] = exc

    worker = threading.Thread(target=target, name=name, daemon=True)
    worker.start()
    shown = None
    while True:
        worker.join(interval_s)
        with lock:
            now = latest.get("progress")
            items, handed[:] = list(handed), []
        if progress is not None and now is not None and now != shown:
            progress(*now)
            shown = now
        for item in items:
            try:
                deliver(item)
            except Exception:  # showing an early result must not stop the work or lose its result
                logging.getLogger(__name__).exception("could not show a result handed over by %s", name)
        poll()
        if not worker.is_alive():
            break
    if "error" in outcome:
        raise outcome["error"]
    return outcome["result"]
