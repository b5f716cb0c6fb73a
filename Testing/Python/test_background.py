"""geopose.background: a computation on a worker thread while the calling thread keeps polling (the
Slicer module's Apply: Testing/Python/test_slicer_module.py measures the GUI's event processing)."""

from __future__ import annotations

import threading
import time

import pytest

from geopose.background import run_in_background


def test_the_caller_polls_and_sees_the_latest_progress_on_its_own_thread():
    caller = threading.current_thread()
    polls, shown = [], []

    def work(report):
        assert threading.current_thread() is not caller
        for n in range(3):
            report("stage", n / 2, f"step {n}")
            time.sleep(0.05)
        return "done"

    result = run_in_background(work, lambda: polls.append(time.perf_counter()), 0.01,
                               lambda *args: shown.append((threading.current_thread() is caller, args)))
    assert result == "done" and len(polls) >= 10
    assert all(on_caller for on_caller, _ in shown) and shown[-1][1] == ("stage", 1.0, "step 2")
    assert [args for _, args in shown] == sorted({args for _, args in shown}, key=lambda a: a[1])  # each report once, in order


def test_the_workers_error_is_raised_on_the_caller():
    polls = []

    def work(report):
        raise KeyError("inside")

    with pytest.raises(KeyError, match="inside"):
        run_in_background(work, lambda: polls.append(1), 0.01)
    assert polls  # polled once after the worker ended, at least


def test_handed_over_results_reach_the_caller_in_order_none_skipped():
    """Results handed over in a burst (faster than the poll) all arrive, in order, on the calling thread, before the
    work ends; progress reports in between may be skipped, they may not."""
    caller = threading.current_thread()
    delivered, ended = [], threading.Event()

    def work(report, hand_over):
        for n in range(5):
            hand_over(n)
            report("stage", n / 4, "")
        time.sleep(0.1)  # the caller polls meanwhile: the items arrive while the work still runs
        ended.set()
        return "done"

    result = run_in_background(work, lambda: None, 0.01, None,
                               deliver=lambda item: delivered.append((item, threading.current_thread() is caller,
                                                                      ended.is_set())))
    assert result == "done"
    assert [item for item, _, _ in delivered] == [0, 1, 2, 3, 4]
    assert all(on_caller and not late for _, on_caller, late in delivered)


def test_an_error_in_showing_a_handed_over_result_does_not_stop_the_work(caplog):
    def work(report, hand_over):
        hand_over("early")
        time.sleep(0.05)
        return "done"

    def deliver(item):
        raise RuntimeError("no scene")

    assert run_in_background(work, lambda: None, 0.01, None, name="test worker", deliver=deliver) == "done"
    assert "could not show a result handed over by test worker" in caplog.text
