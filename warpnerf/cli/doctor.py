"""``warpnerf doctor``: one screen on what this machine offers warpnerf, and the usual mistakes.

Prints Warp and torch versions and builds (CPU or CUDA torch), the CUDA devices Warp and torch
see with their architectures, whether the package's Warp kernels are compiled for them (the kernel
cache warm or cold), the CPU thread count, which optional extras are installed, the data root and
whether LPIPS's weights are on disk. Warnings Warp or Python raise while it probes are reported as
problems, so "none found" never stands beside a warning. ``--compile`` compiles the kernels: on every CUDA device (into Warp's kernel
cache, what training loads), or, without a GPU, ahead of time to PTX for ``--arch`` (default
sm_70/80/90, mapped onto what the installed NVRTC can target) into the AOT cache.

Nothing here runs at ``import warpnerf``: all probing happens when the command runs.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import platform
import re
import warnings
from importlib.metadata import PackageNotFoundError, metadata, version

from warpnerf import openmp
from warpnerf.cli.errors import UserError
from warpnerf.device import init_warp, num_threads


def add_parser(sub) -> None:
    """Register ``doctor`` on the ``warpnerf`` sub-parser set ``sub``."""
    p = sub.add_parser("doctor", help="what this machine offers (Warp, torch, CUDA devices, kernel cache) and common mistakes")
    p.add_argument("--compile", action="store_true",
                   help="compile every kernel: on each CUDA device, or ahead of time to PTX when there is no GPU")
    p.add_argument("--arch", default=None,
                   help="comma-separated SM architectures for the ahead-of-time check, e.g. 80,90 (default 70,80,90)")
    p.set_defaults(func=run)


def _parse_archs(text: str | None) -> tuple[int, ...]:
    from warpnerf.ops.registry import WANTED_ARCHS  # lazy: keeps --help fast (warpnerf.ops loads torch)

    if not text:
        return WANTED_ARCHS
    try:
        archs = tuple(int(a.strip().lower().removeprefix("sm_")) for a in text.split(",") if a.strip())
    except ValueError:
        archs = ()
    if not archs or any(a < 50 for a in archs):
        raise UserError(f"--arch must be comma-separated SM numbers such as 80,90, got '{text}'")
    return archs


_EXTRA_REQ = re.compile(r"""\s*([A-Za-z0-9][A-Za-z0-9._-]*)[^;]*;.*\bextra\s*==\s*['"]([^'"]+)['"]""")


def extras_status(requires: list[str] | None = None) -> dict[str, list[str]] | None:
    """Each optional extra of warpnerf (pyproject's optional-dependencies, read from the installed
    metadata) -> the distributions of it that are not installed ([] = the extra is installed); None
    when warpnerf's metadata is not there (a source tree that was never pip-installed)."""
    if requires is None:
        try:
            requires = metadata("warpnerf").get_all("Requires-Dist") or []
        except PackageNotFoundError:
            return None
    out: dict[str, list[str]] = {}
    for req in requires:
        m = _EXTRA_REQ.match(req)
        if not m:
            continue
        dist, extra = m.groups()
        missing = out.setdefault(extra, [])
        try:
            version(dist)
        except PackageNotFoundError:
            missing.append(dist)
    return out


def data_root_status() -> dict:
    """``$WARPNERF_DATA``: its value, whether it is a folder, and the dataset scenes found under it."""
    from warpnerf.data.errors import DatasetError  # lazy: warpnerf.data loads torch
    from warpnerf.data.resolve import DATA_ENV, data_root_from, dataset_scenes  # lazy: as above

    raw = os.environ.get(DATA_ENV) or None
    out = {"env": DATA_ENV, "value": raw, "root": None, "scenes": [], "error": None}
    try:
        out["root"] = data_root_from(None)
    except DatasetError as e:
        out["error"] = str(e)
    if out["root"]:
        out["scenes"] = sorted(dataset_scenes(out["root"]))
    return out


def lpips_status() -> dict:
    """Where LPIPS(alex)'s two weight files are looked for without --lpips-weights, and which are there."""
    from warpnerf.train.metrics import lpips_default_locations  # lazy: loads torch

    trunk, lin = lpips_default_locations()
    return {"trunk": trunk, "trunk_found": os.path.isfile(trunk), "lin": lin, "lin_found": lin is not None}


@contextlib.contextmanager
def _recording_warnings():
    """Collect, instead of printing, what Warp's logger and Python's warnings would print meanwhile
    (e.g. Warp's stale-kernel-cache warning): doctor reports them among its problems."""
    import warp  # lazy: keeps --help fast

    caught: list[str] = []

    class _Recorder:  # Warp's Logger protocol (warp.set_logger)
        def debug(self, message: str) -> None:
            pass

        def info(self, message: str) -> None:
            pass

        def warning(self, message: str, category=None, stacklevel: int = 1) -> None:
            caught.append(f"Warp warns: {message}")

        def error(self, message: str) -> None:
            caught.append(f"Warp error: {message}")

    set_logger = getattr(warp, "set_logger", None)  # Warp >= 1.12; older ones warn through Python's warnings
    previous = warp.get_logger() if set_logger else None
    if set_logger:
        set_logger(_Recorder())
    try:
        with warnings.catch_warnings(record=True) as python_warnings:  # the filters stay: only what would print
            yield caught
    finally:
        if set_logger:
            set_logger(previous)
    caught += [f"{w.category.__name__}: {w.message}" for w in python_warnings]


def collect(compile_kernels: bool = False, archs: tuple[int, ...] | None = None) -> dict:
    """Everything ``doctor`` reports, as a dict (also used by the tests)."""
    with _recording_warnings() as caught:
        info = _collect(compile_kernels, archs)
    info["warnings"] = caught
    info["problems"] = problems(info)
    return info


def _collect(compile_kernels: bool, archs: tuple[int, ...] | None) -> dict:
    import torch  # lazy: keeps --help fast

    from warpnerf.ops import registry  # lazy: keeps --help fast (torch)

    wp = init_warp()
    from warp._src.context import runtime  # lazy (Warp); toolkit/driver versions have no public accessor in 1.19

    info: dict = {
        "warpnerf": _package_version(),
        "python": platform.python_version(),
        "platform": f"{platform.system()} {platform.machine()}",
        "warp": wp.__version__,
        "warp_toolkit": runtime.toolkit_version,  # CUDA toolkit Warp was built with, (major, minor) or None
        "warp_driver": runtime.driver_version,  # installed NVIDIA driver's CUDA version, or None
        "nvrtc_archs": registry.nvrtc_archs(),
        "torch": torch.__version__,
        "torch_cuda_build": torch.version.cuda,  # None for a CPU wheel
        "torch_cuda_available": bool(torch.cuda.is_available()),
        "torch_cuda_devices": torch.cuda.device_count() if torch.cuda.is_available() else 0,
        "cpu_cores": os.cpu_count() or 1,
        "threads": num_threads(),
        "threads_env": os.environ.get("WARPNERF_THREADS"),
        "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY"),  # the command line leaves it unset unless given
        "openmp_wait": openmp.describe(),  # the command line sets a short spin unless given
        "kernel_cache": wp.config.kernel_cache_dir,
        "aot_cache": registry.aot_cache_dir(),
    }
    devices = []
    for d in wp.get_cuda_devices() if wp.is_cuda_available() else []:
        devices.append({"name": d.alias, "gpu": d.name, "arch": d.arch,
                        "memory_gb": round(d.total_memory / 2**30, 1), "compile_arch": d.get_cuda_compile_arch()})
    info["cuda_devices"] = devices

    modules = registry.kernel_modules()
    info["kernel_modules"] = len(modules)
    info["kernels"] = sum(len(km.kernel_names) for km in modules)
    failures: list[str] = []
    if compile_kernels and devices:
        for d in devices:
            for km in modules:
                try:
                    wp.load_module(km.module, device=d["name"])
                except Exception as e:  # noqa: BLE001 - reported with the kernel's name
                    failures.append(f"{km.label} on {d['name']}: {str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__}")
    info["device_compiled"] = {d["name"]: sum(_in_kernel_cache(wp, km, d["compile_arch"]) for km in modules)
                               for d in devices}
    info["cpu_compiled"] = sum(_in_kernel_cache(wp, km, None) for km in modules)

    wanted = tuple(archs or registry.WANTED_ARCHS)
    aot_archs = registry.target_archs(wanted)
    info["aot_archs"] = aot_archs
    info["aot_unsupported"] = [a for a in wanted if a not in info["nvrtc_archs"]]
    if compile_kernels and not devices and aot_archs:
        failures += registry.compile_aot(modules, aot_archs)
    info["aot_compiled"] = {a: sum(registry.aot_compiled(km, a) for km in modules) for a in aot_archs}
    info["compile_failures"] = failures
    info["extras"] = extras_status()
    info["data"] = data_root_status()
    info["lpips"] = lpips_status()
    return info


def _in_kernel_cache(wp, km, arch: int | None) -> bool:
    """Whether Warp's kernel cache holds this module's binary for the CPU (arch None) or an SM arch.

    The cache folder is named by a hash that includes the block size: CPU launches use 1, CUDA
    the module default, so both identifiers are checked."""
    for block_dim in (None, 1):
        ident = km.module.get_module_identifier(block_dim)
        folder = os.path.join(wp.config.kernel_cache_dir, ident)
        if not os.path.isdir(folder):
            continue
        for f in os.listdir(folder):
            if arch is None and f.startswith(ident) and f.endswith(".o"):
                return True
            if arch is not None and f.startswith(f"{ident}.sm{arch}") and f.endswith((".ptx", ".cubin")):
                return True
    return False


def problems(info: dict) -> list[str]:
    """One line per known misconfiguration, most serious first."""
    out = []
    torch_cuda, warp_gpus = info["torch_cuda_build"], len(info["cuda_devices"])
    if torch_cuda and not info["torch_cuda_available"]:
        out.append(f"CUDA torch without a usable driver: torch was built for CUDA {torch_cuda} but sees no GPU; "
                   "everything runs on the CPU (install the NVIDIA driver, or the ~200 MB CPU wheel of torch)")
    if not torch_cuda and warp_gpus:
        out.append(f"CPU torch on a GPU machine: Warp sees {warp_gpus} CUDA device(s) but torch is a CPU build, so "
                   "'--device auto' fails; install a CUDA build of torch, or pass --device cpu")
    if info["warp_toolkit"] and info["warp_driver"] and info["warp_driver"] < (info["warp_toolkit"][0], 0):
        out.append(f"driver too old for Warp: the driver supports CUDA {_v(info['warp_driver'])}, Warp was built with "
                   f"CUDA {_v(info['warp_toolkit'])}; update the NVIDIA driver or install a Warp build for CUDA "
                   f"{info['warp_driver'][0]}")
    if torch_cuda and info["warp_driver"]:
        major = int(str(torch_cuda).split(".")[0])
        if info["warp_driver"][0] < major:
            out.append(f"driver too old for torch: the driver supports CUDA {_v(info['warp_driver'])}, torch was "
                       f"built for CUDA {torch_cuda}; install a torch wheel for CUDA {info['warp_driver'][0]}")
    if torch_cuda and info["warp_toolkit"] and warp_gpus and int(str(torch_cuda).split(".")[0]) != info["warp_toolkit"][0]:
        out.append(f"mismatched CUDA versions: torch is built for CUDA {torch_cuda}, Warp for CUDA "
                   f"{_v(info['warp_toolkit'])}; both work while the driver supports the newer one, but prefer "
                   "matching majors")
    policy = str(info.get("omp_wait_policy") or "").strip().lower()
    if policy == "active" and not warp_gpus:
        out.append("OMP_WAIT_POLICY=ACTIVE: torch's idle OpenMP workers spin on the cores Warp's launch threads "
                   "need (training steps ~20 % slower on 2 cores); unset it and the command line sets a short spin")
    elif policy == "passive" and not warp_gpus:
        out.append("OMP_WAIT_POLICY=PASSIVE: every small torch op pays a thread wake-up (training steps ~20 % "
                   "slower on 2 cores); unset it and the command line sets a short spin (GOMP_SPINCOUNT)")
    if info["torch_cuda_available"] and not warp_gpus:
        out.append("torch sees a GPU but Warp does not: the kernels would run on the CPU; check the Warp install")
    for name, n in info["device_compiled"].items():
        if n < info["kernel_modules"]:
            out.append(f"{name}: {info['kernel_modules'] - n} of {info['kernel_modules']} kernel modules not compiled yet "
                       "(the first training step compiles them; 'warpnerf doctor --compile' does it now)")
    out += [f"does not compile: {f}" for f in info["compile_failures"]]
    data = info.get("data") or {}
    if data.get("error"):
        out.append(f"{data['error']}: dataset scenes cannot be found; fix or unset ${data['env']}")
    out += info.get("warnings", [])  # whatever warned while probing: never "none found" beside a warning
    return out


def _package_version() -> str:
    try:
        return version("warpnerf")
    except PackageNotFoundError:
        return "source checkout"


def _v(pair) -> str:
    return f"{pair[0]}.{pair[1]}" if pair else "none"


def format_report(info: dict) -> str:
    torch_build = f"CUDA {info['torch_cuda_build']}" if info["torch_cuda_build"] else "CPU"
    gpu = "yes" if info["torch_cuda_available"] else "no"
    lines = [
        f"warpnerf  {info['warpnerf']}, python {info['python']} on {info['platform']}",
        f"torch     {info['torch']} ({torch_build} build; sees a GPU: {gpu}, devices: {info['torch_cuda_devices']})",
        f"warp      {info['warp']} (built with CUDA {_v(info['warp_toolkit'])}; driver: "
        f"{('CUDA ' + _v(info['warp_driver'])) if info['warp_driver'] else 'none'}; "
        f"NVRTC targets: {_arch_list(info['nvrtc_archs'])})",
    ]
    if info["cuda_devices"]:
        for d in info["cuda_devices"]:
            lines.append(f"device    {d['name']}: {d['gpu']}, sm_{d['arch']}, {d['memory_gb']} GB; kernels compiled "
                         f"{info['device_compiled'][d['name']]}/{info['kernel_modules']} modules")
    else:
        lines.append("device    no CUDA device: warpnerf runs on the CPU")
    threads_src = "WARPNERF_THREADS" if info["threads_env"] else "min(2, cores)"
    lines.append(f"cpu       {info['cpu_cores']} cores, {info['threads']} thread(s) for Warp launches ({threads_src}); "
                 f"OpenMP wait {info.get('openmp_wait', 'default')}")
    lines.append(f"kernels   {info['kernels']} kernels in {info['kernel_modules']} modules; cache {info['kernel_cache']}: "
                 + _cache_warmth(info['cpu_compiled'], info['kernel_modules']))
    if info["aot_archs"]:
        done = ", ".join(f"sm_{a} {n}/{info['kernel_modules']}" for a, n in info["aot_compiled"].items())
        lines.append(f"PTX       ahead-of-time (no GPU needed): {done}  [{info['aot_cache']}]")
        if info["aot_unsupported"]:
            lines.append(f"          (this NVRTC cannot target {', '.join(f'sm_{a}' for a in info['aot_unsupported'])}: "
                         "the next supported architecture stands in)")
    lines += _extras_lines(info.get("extras"))
    lines.append(_data_line(info.get("data")))
    lines.append(_lpips_line(info.get("lpips")))
    lines += [f"problem   {p}" for p in info["problems"]] or ["problems  none found"]
    return "\n".join(line for line in lines if line)


def _cache_warmth(compiled: int, total: int) -> str:
    """The CPU kernel cache in words: warm (every module compiled), cold (none) or partly warm."""
    if compiled >= total:
        return f"warm for the CPU ({compiled}/{total} modules compiled)"
    later = "a run compiles the ones it uses in its first steps, once"
    if compiled == 0:
        return f"cold for the CPU (0/{total} modules compiled; {later})"
    return f"partly warm for the CPU ({compiled}/{total} modules compiled; {later})"


def _extras_lines(extras: dict | None) -> list[str]:
    if extras is None:
        return ["extras    unknown: warpnerf's package metadata is missing (pip install -e . in the source tree)"]
    have = [e for e, missing in extras.items() if not missing]
    lack = [e for e, missing in extras.items() if missing]
    line = f"extras    installed: {', '.join(have) or 'none'}"
    if lack:
        line += f"; missing: {', '.join(lack)} (pip install 'warpnerf[NAME]')"
    return [line]


def _data_line(data: dict | None) -> str:
    if not data:
        return ""
    env = f"${data['env']}"
    if data["value"] is None:
        return f"data      {env} not set: scene names resolve to built-in scenes unless --data-root is given"
    if data["error"]:
        return f"data      {env} = {data['value']}: not a folder (see problems)"
    scenes = data["scenes"]
    shown = ", ".join(scenes[:8]) + (", ..." if len(scenes) > 8 else "")
    return f"data      {env} = {data['root']}: {len(scenes)} dataset scene(s)" + (f" ({shown})" if scenes else "")


def _lpips_line(lp: dict | None) -> str:
    if not lp:
        return ""
    if lp["trunk_found"] and lp["lin_found"]:
        return f"lpips     weights found: {lp['trunk']}, {lp['lin']}"
    missing = []
    if not lp["trunk_found"]:
        missing.append(f"AlexNet trunk {lp['trunk']}")
    if not lp["lin_found"]:
        missing.append("lpips' alex.pth (pip install 'warpnerf[metrics]')")
    return (f"lpips     weights not found: {'; '.join(missing)}; LPIPS is reported as null unless --lpips-weights "
            "names them (docs/outputs.md#lpips)")


def _arch_list(archs) -> str:
    if not archs:
        return "none"
    return f"sm_{archs[0]}..sm_{archs[-1]}" if len(archs) > 3 else ", ".join(f"sm_{a}" for a in archs)


def run(args: argparse.Namespace) -> int:
    info = collect(compile_kernels=args.compile, archs=_parse_archs(args.arch))
    print(format_report(info))
    # exit 1 only when asked to compile and something does not compile; a report is not an error
    return 1 if info["compile_failures"] else 0
