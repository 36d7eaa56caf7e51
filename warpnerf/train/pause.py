"""Pausing a training run from outside it: while ``RUN/PAUSE`` exists, training waits between steps.

``warpnerf view``'s Pause button creates the file and Resume removes it; ``touch RUN/PAUSE`` and
``rm RUN/PAUSE`` do the same from a shell. The training loop checks for the file after every step
(one ``stat``); on pausing it saves a checkpoint first, so a viewer shows the step it waits at. The
time spent paused is not training time (``train_seconds`` leaves it out), and Ctrl-C still stops
a paused run (checkpoint saved, as at any step).
"""

from __future__ import annotations

import os
import time
from typing import Callable, Optional

from tqdm.auto import tqdm

PAUSE_FILE = "PAUSE"


def pause_path(run_dir: str) -> str:
    return os.path.join(run_dir, PAUSE_FILE)


def wait_while_paused(run_dir: str, step: int, on_pause: Optional[Callable[[], None]] = None,
                      should_stop: Callable[[], bool] = lambda: False, poll: float = 0.5) -> float:
    """If ``run_dir/PAUSE`` exists: call ``on_pause()`` (e.g. save a checkpoint), say so, and sleep
    until the file is gone or ``should_stop()`` is true. Returns the seconds paused (0.0 at once
    when there is no such file)."""
    path = pause_path(run_dir)
    if not os.path.exists(path):
        return 0.0
    if on_pause is not None:
        on_pause()
    tqdm.write(f"paused after step {step}: {path} exists (warpnerf view's Pause); remove it to continue")
    t0 = time.monotonic()
    while os.path.exists(path) and not should_stop():
        time.sleep(poll)
    waited = time.monotonic() - t0
    tqdm.write(f"resumed after {waited:.0f} s paused")
    return waited
