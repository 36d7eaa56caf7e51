"""Atomic checkpoint files and the RNG state they carry.

A checkpoint is a plain dict of tensors, numbers, strings, lists and dicts, so it loads with
``torch.load(..., weights_only=True)``: a foreign file cannot run code. It is written to a temp
file in the run folder, flushed and fsynced, then ``os.replace``d over the old one, so a crash
at any moment leaves either the previous checkpoint or the new one, never half a file.
"""

from __future__ import annotations

import os
import signal
import tempfile

import numpy as np
import torch

FORMAT = "warpnerf-checkpoint-1"


class CheckpointError(ValueError):
    """A checkpoint file is missing, truncated or not ours (one line, names the file)."""


class WriteError(OSError):
    """A file could not be written (disk full, read-only file system, quota): one line naming it. The
    atomic writer leaves the file it would have replaced as it was."""

    def __str__(self) -> str:
        name = os.path.basename(self.filename or "")
        return f"cannot write {self.filename}: {self.strerror}; the previous {name} (if any) is unchanged"


def _fault(point: str) -> None:
    # fault injection for the crash tests: WARPNERF_FAULT=<point> sends this process
    # $WARPNERF_FAULT_SIGNAL (default KILL) there, so a test can crash it at an exact place
    if os.environ.get("WARPNERF_FAULT") == point:
        os.kill(os.getpid(), getattr(signal, "SIG" + os.environ.get("WARPNERF_FAULT_SIGNAL", "KILL")))


def atomic_write_bytes(path: str, write) -> None:
    """Call ``write(fh)`` on a temp file next to ``path``, fsync it, then rename it over ``path``.

    An OSError on the way (a full disk: ENOSPC) removes the temp file, leaves ``path`` as it was and is
    raised as :class:`WriteError`."""
    folder = os.path.dirname(os.path.abspath(path))
    try:
        fd, tmp = tempfile.mkstemp(prefix=".tmp-" + os.path.basename(path) + "-", dir=folder)
    except OSError as e:
        raise WriteError(e.errno, e.strerror or str(e), path) from e
    try:
        with os.fdopen(fd, "wb") as fh:
            write(fh)
            fh.flush()
            os.fsync(fh.fileno())
        _fault("before_replace:" + os.path.basename(path))
        os.replace(tmp, path)
    except BaseException as e:
        if os.path.exists(tmp):
            os.unlink(tmp)
        if isinstance(e, OSError) and not isinstance(e, WriteError):
            raise WriteError(e.errno, e.strerror or str(e), path) from e
        raise
    try:  # make the rename itself durable
        dfd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)
    except OSError:  # pragma: no cover - some file systems refuse fsync on folders
        pass


def atomic_write_text(path: str, text: str) -> None:
    atomic_write_bytes(path, lambda fh: fh.write(text.encode("utf-8")))


def save_checkpoint(path: str, state: dict) -> None:
    """Write ``state`` (plus a format tag) atomically to ``path``."""
    atomic_write_bytes(path, lambda fh: torch.save({"format": FORMAT, **state}, fh))


def load_checkpoint(path: str, map_location=None) -> dict:
    """Read a checkpoint written by :func:`save_checkpoint`; CheckpointError on anything else."""
    if not os.path.isfile(path):
        raise CheckpointError(f"checkpoint not found: {path}")
    try:
        state = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as exc:  # truncated zip, pickle refused by weights_only, not a torch file...
        msg = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise CheckpointError(f"{path} is not a readable warpnerf checkpoint (truncated or foreign file: {msg[:120]})") from None
    if not isinstance(state, dict) or state.get("format") != FORMAT:
        raise CheckpointError(f"{path} is not a warpnerf checkpoint (no '{FORMAT}' tag)")
    return state


def rng_state(gen: torch.Generator) -> dict:
    """Every random stream a training step may draw from: torch's global one, the trainer's
    generator and numpy's global one (as tensors and ints, so weights_only can load them)."""
    kind, keys, pos, has_gauss, cached = np.random.get_state()
    return {"torch": torch.get_rng_state(), "gen": gen.get_state(),
            "numpy": {"keys": torch.from_numpy(keys.astype(np.int64)), "pos": int(pos),
                      "has_gauss": int(has_gauss), "cached": float(cached)}}


def set_rng_state(state: dict, gen: torch.Generator) -> None:
    torch.set_rng_state(state["torch"].cpu())
    gen.set_state(state["gen"].cpu())
    n = state["numpy"]
    np.random.set_state(("MT19937", n["keys"].numpy().astype(np.uint32), n["pos"], n["has_gauss"], n["cached"]))
