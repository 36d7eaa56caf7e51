import os

# Helpers (tiny_scene, fake_scenes, chair_run, trainer_helpers) live in this folder; pyproject's pytest
# pythonpath puts it on sys.path, so the tests in the per-layer sub-folders import them by name.

# torch's OpenMP workers: the command line's short spin (warpnerf/openmp.py), before torch loads
from warpnerf.openmp import set_wait_defaults  # noqa: E402  (imports nothing heavy)

set_wait_defaults()

import pytest  # noqa: E402

# Keep compiled Warp kernels between test runs unless the caller chose a cache.
os.environ.setdefault("WARP_CACHE_PATH", os.path.join(os.path.dirname(__file__), "..", ".warp_cache"))


@pytest.fixture
def threads():
    """Set the CPU thread count for one test and restore it afterwards."""
    from warpnerf import device

    before = device.num_threads()
    yield device.set_num_threads
    device.set_num_threads(before)


@pytest.fixture(scope="session")
def chair_run(tmp_path_factory):
    """A run folder of the built-in chair, briefly trained (tests/chair_run.py); shared by several test files."""
    from chair_run import train_chair_run

    return train_chair_run(tmp_path_factory.mktemp("chair_run"))
