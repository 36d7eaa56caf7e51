"""Every Warp kernel module the package can create, in one list; every public op and the backend switch.

Used by the ahead-of-time GPU compile test (``tests/test_cuda_compile.py``) and by
``warpnerf doctor --compile``, so neither keeps a hand-written list that could drift:

* the grid encodings generate a forward/backward kernel pair per variant; each op lists one
  spec per variant it accepts (``kernel_variant_specs``: ``SUPPORTED_DIMS`` x
  ``SUPPORTED_FEATURES`` for the hash grid, ``SUPPORTED_RANKS`` for the CP grid), and the
  kernels come from the op launcher's own ``make_kernels``, in both float dtypes (float64
  serves gradcheck);
* the other ops use one fixed Warp module each (one file in ``kernels/``), listed in
  :data:`STATIC_KERNEL_MODULES`; a test checks that no kernel file is missing from it.

Building the list imports Warp and defines the kernels (cheap: no compilation happens).

:data:`OPS` lists every public op (each wrapped by :func:`warpnerf.ops.launch.twin_dispatch`) and
:func:`use_backend` switches all of them at once to their pure-torch twins in
:mod:`warpnerf.ops.reference` (``warpnerf bench step``'s torch arm, the twin tests).
"""

from __future__ import annotations

import contextlib
import importlib
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

from warpnerf.device import init_warp
from warpnerf.ops import composite, cpgrid, hashgrid, launch, occupancy, raymarch
from warpnerf.ops.reference import composite as twin_composite
from warpnerf.ops.reference import cpgrid as twin_cpgrid
from warpnerf.ops.reference import hashgrid as twin_hashgrid
from warpnerf.ops.reference import occupancy as twin_occupancy
from warpnerf.ops.reference import raymarch as twin_raymarch

__all__ = ["KernelModule", "STATIC_KERNEL_MODULES", "GRID_DTYPE_NAMES", "kernel_modules", "OPS", "BACKENDS",
           "use_backend", "current_backend"]

# every public op: (its module, its name); each has a twin of the same name in TWIN_MODULES
OPS = tuple((module, name) for module in (hashgrid, cpgrid, raymarch, composite, occupancy)
            for name in {hashgrid: ["hashgrid_encode"], cpgrid: ["cpgrid_encode"],
                         raymarch: ["march_rays", "march_rays_within_budget", "march_rays_window"],
                         composite: ["composite_rays", "active_sample_counts"],
                         occupancy: list(occupancy.__all__)}[module])

# twin module name -> module, what launch.twin_dispatch looks the twins up in
TWIN_MODULES = {m.__name__: m for m in (twin_hashgrid, twin_cpgrid, twin_raymarch, twin_composite, twin_occupancy)}

BACKENDS = ("warp", "torch")


def current_backend() -> str:
    """``"warp"`` or ``"torch"``: what the public ops run right now."""
    return "torch" if launch.twins_on() else "warp"


@contextlib.contextmanager
def use_backend(name: str):
    """Run every public op (:data:`OPS`) on ``name``: ``"warp"`` (the kernels) or ``"torch"`` (the
    same-name twins in :mod:`warpnerf.ops.reference`) inside the ``with`` block; the previous setting
    comes back afterwards. Process-wide (all threads), not re-entrant across threads.

    Example:
        >>> import torch
        >>> from warpnerf.ops import composite_rays
        >>> with use_backend("torch"):
        ...     rgb = composite_rays(torch.tensor([1e9]), torch.ones(1, 3), torch.zeros(1), torch.ones(1),
        ...                          torch.zeros(1, dtype=torch.int32), torch.ones(1, dtype=torch.int32))[0]
        >>> rgb.tolist(), current_backend()
        ([[1.0, 1.0, 1.0]], 'warp')
    """
    if name not in BACKENDS:
        raise ValueError(f"use_backend: unknown backend {name!r}, expected one of {BACKENDS}")
    previous = launch.set_twin_modules(None if name == "warp" else dict(TWIN_MODULES))
    try:
        yield
    finally:
        launch.set_twin_modules(previous)

# op name -> the kernels/ file (one Warp module) it launches
STATIC_KERNEL_MODULES = {
    "raymarch": "warpnerf.kernels.raymarch",
    "composite": "warpnerf.kernels.composite",
    "occupancy": "warpnerf.kernels.occupancy",
    "raytrace": "warpnerf.kernels.raytrace",
    "roofline": "warpnerf.kernels.roofline",  # bench's random-gather probe, not a training op
}

# the dtypes every grid variant exists in (float64 for gradcheck), as Warp type names
GRID_DTYPE_NAMES = ("float32", "float64")


@dataclass(frozen=True)
class KernelModule:
    """One Warp module: the unit Warp compiles (one source file, one PTX per architecture)."""

    op: str  # op family: hashgrid, cpgrid, raymarch, composite, occupancy, raytrace, roofline
    variant: str  # e.g. "dim=3 F=2 float32 fwd"; "" for a fixed module
    module: object  # warp Module

    @property
    def kernel_names(self) -> list[str]:
        return sorted(self.module.kernels)

    @property
    def label(self) -> str:
        return f"{self.op}[{self.variant}]" if self.variant else self.op


def kernel_modules() -> list[KernelModule]:
    """All Warp modules of the package, grid variants first; see the module docstring."""
    wp = init_warp()
    out: list[KernelModule] = []
    for op, grid in (("hashgrid", hashgrid), ("cpgrid", cpgrid)):
        for dtype_name in GRID_DTYPE_NAMES:
            for label, spec in grid.kernel_variant_specs():
                # the very call the op's launcher makes for this spec and dtype
                fwd, bwd, _ = grid._Launcher.make_kernels(spec, getattr(wp, dtype_name))
                for kind, kernel in (("fwd", fwd), ("bwd", bwd)):
                    out.append(KernelModule(op, f"{label} {dtype_name} {kind}", kernel.module))
    for op, name in STATIC_KERNEL_MODULES.items():
        out.append(KernelModule(op, "", wp.get_module(importlib.import_module(name).__name__)))
    return out


# the GPU generations the ahead-of-time compile covers: Volta, Ampere, Hopper
WANTED_ARCHS = (70, 80, 90)


def nvrtc_archs() -> list[int]:
    """Architectures this Warp build's NVRTC can compile for (empty without NVRTC)."""
    init_warp()
    from warp._src.context import runtime  # lazy (Warp); no public accessor in Warp 1.19

    return sorted(getattr(runtime, "nvrtc_supported_archs", None) or [])


def target_archs(wanted=WANTED_ARCHS) -> list[int]:
    """``wanted`` mapped onto what NVRTC can target: an unsupported arch becomes the next supported
    one (CUDA 13's NVRTC dropped sm_70/72, so sm_70 becomes sm_75); duplicates removed."""
    supported = nvrtc_archs()
    out: list[int] = []
    for arch in wanted:
        pick = arch if arch in supported else next((a for a in supported if a >= arch), None)
        if pick is not None and pick not in out:
            out.append(pick)
    return out


def aot_cache_dir() -> str:
    """Folder of ahead-of-time PTX: ``$WARPNERF_AOT_CACHE`` or ``<Warp kernel cache>/aot``."""
    wp = init_warp()
    return os.environ.get("WARPNERF_AOT_CACHE") or os.path.join(wp.config.kernel_cache_dir, "aot")


def aot_compiled(km: KernelModule, arch: int, cache: str | None = None) -> bool:
    """Whether ``km`` has PTX for ``arch`` in the AOT cache (for its current source hash)."""
    folder = os.path.join(cache or aot_cache_dir(), km.module.name)
    ident = km.module.get_module_identifier()
    return os.path.isdir(folder) and any(f.startswith(ident) and f.endswith(f".sm{arch}.ptx") for f in os.listdir(folder))


def compile_aot(modules: list[KernelModule], archs: list[int], cache: str | None = None, threads: int = 2) -> list[str]:
    """Compile every module for every arch to PTX (skipped when the cache already has it).

    Returns one line per failure, naming the op variant, its kernels and the arch. No GPU needed."""
    wp = init_warp()
    cache = cache or aot_cache_dir()

    def one(job):
        km, arch = job
        try:
            wp.compile_aot_module(km.module, arch=arch, module_dir=os.path.join(cache, km.module.name), use_ptx=True)
            return None
        except Exception as e:  # noqa: BLE001 - any failure is reported with the kernel's name
            first = (str(e).strip().splitlines() or [type(e).__name__])[0]
            return f"{km.label} kernels {km.kernel_names} sm_{arch}: {first}"

    jobs = [(km, arch) for km in modules for arch in archs]
    # NVRTC runs outside the GIL (Warp serialises only its Python code generation)
    with ThreadPoolExecutor(max_workers=max(1, threads)) as pool:
        return [r for r in pool.map(one, jobs) if r]
