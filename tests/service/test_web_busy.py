"""The web view counts its own work: the CPU seconds of the requests it answers, and for each decode or
render (the mapper's lock held) its wall time and the CPU that other threads spent meanwhile."""

from __future__ import annotations

import threading
import time

from ogserver.web.maps import Busy

BURN_SECONDS = 0.1


def burn(seconds: float) -> None:
    """Spend about ``seconds`` of this thread's CPU."""
    until = time.thread_time() + seconds
    while time.thread_time() < until:
        pass


def test_a_request_counts_its_threads_cpu_and_not_its_waits() -> None:
    busy = Busy()
    with busy.request():
        burn(BURN_SECONDS)
    assert BURN_SECONDS <= busy.cpu_seconds < 3 * BURN_SECONDS
    with busy.request():
        time.sleep(0.3)
    assert busy.cpu_seconds < 3 * BURN_SECONDS
    assert busy.count == 0


def test_holding_the_lock_counts_its_time_and_the_other_threads_cpu() -> None:
    busy, lock = Busy(), threading.RLock()
    acquired: list[bool] = []
    with busy.holding(lock):
        blocked = threading.Thread(target=lambda: acquired.append(lock.acquire(timeout=0.05)))
        blocked.start()
        blocked.join()
        helper = threading.Thread(target=burn, args=(BURN_SECONDS,))
        helper.start()
        helper.join()
        burn(BURN_SECONDS)  # the caller's own: its request counts it
    assert acquired == [False]
    assert busy.count == 1
    assert busy.seconds >= 2 * BURN_SECONDS
    assert BURN_SECONDS * 0.9 <= busy.cpu_seconds < 1.9 * BURN_SECONDS


def test_holding_waits_for_the_lock_without_counting_the_wait() -> None:
    busy, lock = Busy(), threading.RLock()
    taken = threading.Event()

    def hold_briefly() -> None:
        with lock:
            taken.set()
            time.sleep(0.3)

    holder = threading.Thread(target=hold_briefly)
    holder.start()
    taken.wait()
    with busy.holding(lock):
        pass
    holder.join()
    assert busy.count == 1 and busy.seconds < 0.1
