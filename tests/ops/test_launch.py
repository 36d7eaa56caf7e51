"""The launcher's CPU thread split: kernels are compiled on the calling thread before the pool runs them."""

import threading

import torch
import warp as wp

from warpnerf import device as devmod
from warpnerf.device import init_warp
from warpnerf.ops import launch as L

init_warp()


@wp.kernel
def _write_index(first_ray: int, out: wp.array(dtype=float)):
    i = first_ray + wp.tid()
    out[i] = float(i)


def test_launch_over_rays_loads_the_module_once_on_the_calling_thread(monkeypatch):
    """Warp's first compile on a thread pays a per-thread start-up, and two pool threads meeting a cold
    module both compile it: the module is loaded here, once, before the chunks go to the pool."""
    loads = []
    load_module = wp.load_module

    def spy(module, device=None, **kw):
        loads.append((module, threading.current_thread() is threading.main_thread()))
        return load_module(module, device=device, **kw)

    monkeypatch.setattr(wp, "load_module", spy)
    monkeypatch.setattr(L, "_LOADED", set())
    threads = devmod.num_threads()
    devmod.set_num_threads(2)
    try:
        for n in (37, 53):
            out = torch.full((n,), -1.0)
            L.launch_over_rays(_write_index, n, [L.as_warp(out)], torch.device("cpu"))
            assert torch.equal(out, torch.arange(n, dtype=torch.float32))
    finally:
        devmod.set_num_threads(threads)
    assert loads == [(_write_index.module, True)]
