"""How torch's idle OpenMP workers wait: set before torch loads (the runtime reads it once).

By default libgomp (torch's Linux wheels) busy-waits for ~ms after each parallel region, on the
very cores Warp's launch threads need next. Fully passive waiting (``OMP_WAIT_POLICY=PASSIVE``,
warpnerf's earlier choice) instead pays a futex wake-up per parallel region, which made each small
torch op (the 4096-row MLP blocks, Adam, indexing) 2-3x slower. A short spin (``GOMP_SPINCOUNT``)
keeps back-to-back ops fast and frees the core soon after: measured, a chair few-shot step is
~20 % faster than with passive waiting (docs/studies/2026-12-07-speed.md). Other OpenMP runtimes (LLVM's, Intel's)
get their passive equivalent, ``KMP_BLOCKTIME=0``. Results are unchanged: only how idle threads wait.

This module imports nothing heavy: the command line and the test suite call
:func:`set_wait_defaults` before anything imports torch; a script can do the same.
"""

from __future__ import annotations

import os

# GOMP_SPINCOUNT counts pause-loop iterations (libgomp's default: 300000). Chair few-shot, 300 warm
# steps: 1000 measured no better than passive (58-62 s vs 64-77 s), 3000 and 10000 alike (48-56 s)
WAIT_DEFAULTS = {"GOMP_SPINCOUNT": "10000", "KMP_BLOCKTIME": "0"}
WAIT_SETTINGS = ("OMP_WAIT_POLICY", *WAIT_DEFAULTS)


def set_wait_defaults() -> bool:
    """Set :data:`WAIT_DEFAULTS` unless the user set any OpenMP wait setting (then nothing changes).
    Returns whether it set them. Has no effect on a torch that is already loaded."""
    if any(k in os.environ for k in WAIT_SETTINGS):
        return False
    os.environ.update(WAIT_DEFAULTS)
    return True


def describe() -> str:
    """The OpenMP wait settings in this process's environment, e.g. ``"GOMP_SPINCOUNT=10000
    KMP_BLOCKTIME=0"`` (``"default"`` when none is set): benchmarks record it beside their figures,
    which move by ~25 % with it."""
    return " ".join(f"{k}={os.environ[k]}" for k in WAIT_SETTINGS if k in os.environ) or "default"
