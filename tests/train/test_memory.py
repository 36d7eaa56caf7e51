"""Peak memory is per run, not per process: runs that share a process (table, sweep) must not
inherit an earlier run's high-water mark (a mic run was stopped at step 0 by memory_budget_mb)."""

import os

import numpy as np
import pytest

from warpnerf.train.trainer import peak_rss_mb, start_memory_window


@pytest.mark.skipif(not os.access("/proc/self/clear_refs", os.W_OK), reason="needs Linux /proc/self/clear_refs")
def test_memory_window_forgets_an_earlier_runs_peak():
    start_memory_window()
    base = peak_rss_mb()
    big = np.ones(400 * 2**20 // 8)  # 400 MB, touched
    assert peak_rss_mb() > base + 350
    del big
    start_memory_window()
    assert peak_rss_mb() < base + 100
