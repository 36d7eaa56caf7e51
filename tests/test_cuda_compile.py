"""Every Warp kernel of the package compiles for real GPU architectures, without a GPU.

Warp's NVRTC compiles CUDA source to PTX with no driver present, so a CUDA-only code-generation
error (a construct the CPU backend accepts, a type the GPU lacks, a too-large local array) is
caught here. The modules come from :func:`warpnerf.ops.registry.kernel_modules`, the list the
launchers' factories and spec limits define, and the artefacts are kept in a cache folder
(``$WARPNERF_AOT_CACHE`` or ``<Warp kernel cache>/aot``): a warm run only re-hashes the modules.

The wanted architectures are sm_70 (Volta), sm_80 (Ampere) and sm_90 (Hopper). NVRTC from
CUDA 13 no longer targets sm_70/72; an architecture the installed NVRTC cannot target is
replaced by the oldest one it can (sm_75 with CUDA 13), and the substitution is printed.
"""

import json
import os
import pkgutil
import time
from collections import Counter

import pytest

from warpnerf.ops.registry import WANTED_ARCHS, aot_cache_dir, aot_compiled, compile_aot, target_archs


def _warp():
    from warpnerf.device import init_warp

    return init_warp()


def test_registry_lists_every_kernel_file():
    """Each kernels/ file that defines kernels at module level is in STATIC_KERNEL_MODULES; the
    two factory files (module-level funcs only) are covered by the grid variants."""
    wp = _warp()
    import importlib

    import warpnerf.kernels as K
    from warpnerf.ops.registry import STATIC_KERNEL_MODULES, kernel_modules

    listed = set(STATIC_KERNEL_MODULES.values())
    ops = {km.op for km in kernel_modules()}
    for info in pkgutil.iter_modules(K.__path__):
        name = f"warpnerf.kernels.{info.name}"
        module = wp.get_module(importlib.import_module(name).__name__)
        if module.kernels:
            assert name in listed, f"{name} defines kernels {sorted(module.kernels)} but is not in the registry"
        else:
            assert info.name in ops, f"{name} defines no module-level kernels and no registered variants"


def test_every_kernel_compiles_for_gpu_architectures():
    _warp()
    from warpnerf.ops.registry import kernel_modules

    archs = target_archs()
    if not archs:
        pytest.skip("this Warp build has no NVRTC: it cannot compile CUDA code")
    cache = aot_cache_dir()
    modules = kernel_modules()
    t0 = time.perf_counter()
    failures = compile_aot(modules, archs, cache)
    seconds = time.perf_counter() - t0
    per_op = Counter()
    for km in modules:
        per_op[km.op] += len(km.kernel_names)
    summary = dict(archs=[f"sm_{a}" for a in archs], wanted=[f"sm_{a}" for a in WANTED_ARCHS],
                   modules=len(modules), kernels_per_op=dict(per_op), seconds=round(seconds, 1))
    print("\nAOT compile:", json.dumps(summary))
    os.makedirs(cache, exist_ok=True)
    with open(os.path.join(cache, "summary.json"), "w") as f:
        json.dump(summary, f, indent=1)
    assert not failures, "kernels that do not compile for the GPU:\n" + "\n".join(failures)
    # every (module, arch) left a PTX file behind
    missing = [f"{km.label} sm_{a}" for km in modules for a in archs if not aot_compiled(km, a, cache)]
    assert not missing, f"no PTX in {cache} for: {missing}"


def test_a_cuda_only_error_is_reported_with_the_kernel_name(tmp_path):
    """The test above would catch a kernel the CPU accepts and CUDA rejects: shown on a kernel
    whose CUDA source does not compile (an inline-CUDA snippet with an undeclared name)."""
    wp = _warp()
    archs = target_archs()
    if not archs:
        pytest.skip("this Warp build has no NVRTC")
    from warpnerf.ops.registry import KernelModule

    @wp.func_native(snippet="out[tid] = undeclared_on_any_gpu;")
    def broken_snippet(out: wp.array(dtype=float), tid: int): ...

    @wp.kernel(module="unique")
    def cuda_only_broken(out: wp.array(dtype=float)):
        broken_snippet(out, wp.tid())

    km = KernelModule("test", "broken", cuda_only_broken.module)
    failures = compile_aot([km], archs[:1], str(tmp_path), threads=1)
    assert len(failures) == 1 and "cuda_only_broken" in failures[0]
