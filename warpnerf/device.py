"""One place for device choice, Warp initialisation and the CPU thread split.

Warp on CPU runs every launch serially on one thread, but ``wp.launch`` releases the GIL, so
we split work into chunks and run them on a small thread pool. The split rules are:

* gathers (each output element written by exactly one thread) are split by points;
* scatters (``+=`` into a shared buffer) are split so that chunks write disjoint memory,
  e.g. by hash-grid level. CPU ``atomic_add`` is a plain ``+=``: two threads must never
  scatter into the same buffer.

The chunking never depends on the number of threads, so results are bit-identical whether
the chunks run on one thread or on several (docs/design.md §3).
"""

from __future__ import annotations

import logging
import os
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor
from typing import Callable, Sequence

_WARP_READY = False
_POOL: ThreadPoolExecutor | None = None
_NUM_THREADS: int | None = None

# Warp's native library prints this line to the process's stderr at init on every machine without an NVIDIA
# driver, although nothing was asked of CUDA; init_warp holds it back, and resolve_device names it when CUDA is asked for
CUDA_DRIVER_MISSING = "Could not find or load the NVIDIA CUDA driver"
_HELD_BACK: list[str] = []


def _init_without_driver_line(wp) -> None:
    """``wp.init()`` with file descriptor 2 sent to a temporary file (the line comes from C, below
    ``sys.stderr``); everything it printed except the CUDA-driver line is written to stderr afterwards,
    so real warnings and errors stay visible."""
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError, AttributeError):  # no usable fd 2 (a closed or replaced stderr)
        wp.init()
        return
    with tempfile.TemporaryFile() as tmp:
        os.dup2(tmp.fileno(), 2)
        try:
            wp.init()
        finally:
            try:
                sys.stderr.flush()  # Python-level warnings written meanwhile belong to the captured text
            except (OSError, ValueError):
                pass
            os.dup2(saved, 2)
            os.close(saved)
            tmp.seek(0)
            text = tmp.read().decode("utf-8", errors="replace")
            kept = []
            for line in text.splitlines(keepends=True):
                (_HELD_BACK if CUDA_DRIVER_MISSING in line else kept).append(line)
            if kept:
                sys.stderr.write("".join(kept))
                sys.stderr.flush()


def init_warp():
    """Import and initialise Warp once (quietly); returns the ``warp`` module.

    Warp's "Could not find or load the NVIDIA CUDA driver" line is held back: on a machine without a
    GPU it is noise for ``--device auto`` and ``cpu``; :func:`resolve_device` repeats it when CUDA is
    asked for and missing."""
    global _WARP_READY
    import warp as wp  # lazy: Warp loads with the first op that needs it, never with 'import warpnerf'

    if not _WARP_READY:
        # the init banner and per-module compile lines are INFO; keep the CLI output clean
        wp.config.log_level = logging.WARNING
        cache = os.environ.get("WARP_CACHE_PATH")
        if cache:
            wp.config.kernel_cache_dir = cache
        _init_without_driver_line(wp)
        _WARP_READY = True
    return wp


def held_back_warp_lines() -> list[str]:
    """What :func:`init_warp` kept from stderr (Warp's CUDA-driver line on a machine without one)."""
    return [line.strip() for line in _HELD_BACK]


def resolve_device(name: str = "auto") -> str:
    """Map ``auto|cpu|cuda|cuda:N`` to a Warp device string.

    ``auto`` picks ``cuda:0`` when Warp sees a CUDA device, else ``cpu``.
    Raises ``ValueError`` for an unknown name or a CUDA request on a machine without CUDA.
    """
    wp = init_warp()
    name = (name or "auto").lower()
    if name == "auto":
        return "cuda:0" if wp.is_cuda_available() else "cpu"
    if name == "cpu":
        return "cpu"
    if name == "cuda" or name.startswith("cuda:"):
        if not wp.is_cuda_available():
            why = "".join(f" ({line})" for line in held_back_warp_lines())
            raise ValueError(f"device '{name}' requested but Warp sees no CUDA device{why}; use --device cpu or auto")
        return "cuda:0" if name == "cuda" else name
    raise ValueError(f"unknown device '{name}': expected auto, cpu, cuda or cuda:N")


def torch_device(device: str):
    """The ``torch.device`` that matches a Warp device string."""
    import torch  # lazy: the command line imports this module before torch (OpenMP settings: openmp.py)

    return torch.device("cpu" if device == "cpu" else device)


def num_threads() -> int:
    """Threads used to run CPU chunks: ``WARPNERF_THREADS`` or min(2, cores)."""
    global _NUM_THREADS
    if _NUM_THREADS is None:
        env = os.environ.get("WARPNERF_THREADS")
        _NUM_THREADS = max(1, int(env)) if env else max(1, min(2, os.cpu_count() or 1))
    return _NUM_THREADS


def set_num_threads(n: int) -> None:
    """Change the CPU thread count (results do not depend on it)."""
    global _NUM_THREADS, _POOL
    if n < 1:
        raise ValueError(f"thread count must be >= 1, got {n}")
    _NUM_THREADS = int(n)
    if _POOL is not None:
        _POOL.shutdown(wait=True)
        _POOL = None


def limit_cpu_threads(n: int) -> None:
    """``--threads N``: N threads for Warp chunks *and* for torch's intra-op pool (the MLPs, Adam).

    Without the second, two runs started side by side with ``--threads 1`` each still ran torch on
    every core: four busy threads on two cores made each run ~3x slower than half speed.
    """
    import torch  # lazy: see torch_device

    set_num_threads(n)
    torch.set_num_threads(int(n))


def run_chunks(tasks: Sequence[Callable[[], object]]) -> list:
    """Run independent callables, in parallel on CPU when more than one thread is allowed."""
    global _POOL
    threads = num_threads()
    if threads == 1 or len(tasks) <= 1:
        return [t() for t in tasks]
    if _POOL is None:
        _POOL = ThreadPoolExecutor(max_workers=threads, thread_name_prefix="warpnerf")
    return [f.result() for f in [_POOL.submit(t) for t in tasks]]


def split_range(n: int, k: int) -> list[tuple[int, int]]:
    """Split ``range(n)`` into ``k`` contiguous (start, end) pieces of near-equal size."""
    k = max(1, min(k, n)) if n > 0 else 1
    bounds = [n * i // k for i in range(k + 1)]
    return [(bounds[i], bounds[i + 1]) for i in range(k)]
