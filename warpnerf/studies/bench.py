"""Benchmarks that print measured numbers (``warpnerf bench ...``).

Each benchmark times the Warp op and its pure-torch twin in the same process, both the same
way: median of ``repeats`` timed runs after ``warmup`` untimed ones (compilation, allocator and
cache warm-up), with inputs and cotangents allocated once outside the timed runs.

Next to the op timings they print a roofline measured on the same machine in the same process:
the random-gather rate (``kernels/roofline.py``) for the grid encodings, the float32 GEMM rate
for the field's MLPs, and the fraction of each that the op reaches.
"""

from __future__ import annotations

import functools
import statistics
import time
from typing import Callable

import torch

from warpnerf import device as devmod
from warpnerf import openmp
from warpnerf.kernels import roofline as roofline_kernels
from warpnerf.kernels.roofline import GATHERS_PER_THREAD
from warpnerf.model.encoders import HashGridEncoder
from warpnerf.ops.cpgrid import CPGridSpec, cpgrid_encode, init_cp_lines
from warpnerf.ops.hashgrid import HashGridSpec, hashgrid_encode
from warpnerf.ops.launch import as_warp, launch, load_here
from warpnerf.ops.reference import cpgrid as twin_cpgrid
from warpnerf.ops.reference import hashgrid as twin_hashgrid
from warpnerf.ops.registry import use_backend
from warpnerf.runs.folder import load_run, load_scene_for
from warpnerf.train.config import build_config
from warpnerf.train.metrics import psnr
from warpnerf.train.tasks import make_task
from warpnerf.train.trainer import Trainer


def median_seconds(fn: Callable[[], object], repeats: int, warmup: int = 2) -> float:
    """Median wall time of ``repeats`` calls of ``fn`` after ``warmup`` untimed calls."""
    if repeats < 1:
        raise ValueError(f"repeats must be >= 1, got {repeats}")
    for _ in range(max(warmup, 0)):  # compilation, allocator, caches
        fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def ray_like_points(n: int, samples_per_ray: int = 128, generator: torch.Generator | None = None) -> torch.Tensor:
    """(n, 3) points in [0, 1]^3 laid out ray by ray, as a ray marcher emits them.

    Rays start on a sphere around the unit cube and point at random targets inside it;
    consecutive points of a ray are one step apart, so neighbours share cache lines.
    """
    n_rays = -(-n // samples_per_ray)
    g = generator
    target = torch.rand(n_rays, 3, generator=g) * 0.6 + 0.2
    origin = torch.nn.functional.normalize(torch.randn(n_rays, 3, generator=g), dim=-1) * 1.5 + 0.5
    direction = torch.nn.functional.normalize(target - origin, dim=-1)
    t = torch.linspace(0.75, 2.25, samples_per_ray)
    pts = origin[:, None, :] + t[None, :, None] * direction[:, None, :]
    return pts.reshape(-1, 3)[:n].clamp(0, 1).contiguous()


def _sync(device: torch.device) -> None:
    """Wait for queued CUDA work, so a timed run ends when its work does (no-op on CPU)."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


# --- roofline: what this machine can do, measured, next to what the ops reach -------------------

# gather-probe points at most: 2^20 x 8 int32 row ids are 32 MiB, ample to amortise the launches
_GATHER_POINTS_MAX = 1 << 20
# (samples, in, out) of the GEMM peak: a 64-wide layer of the field's MLPs on a 64k-sample batch
GEMM_SHAPE = (65536, 64, 64)


@functools.lru_cache(maxsize=None)
def _gather_kernel(wp_device: str):
    """The probe kernel, compiled/loaded on the calling thread (never by two chunk threads at once)."""
    kernel = roofline_kernels.gather_sum
    load_here(kernel, wp_device)
    return kernel


def gather_sum(table: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
    """(T, 2) float32 table and (N, 8) int32 row ids -> (N, 2): each point's 8 rows summed in order.

    Runs ``kernels/roofline.py`` with the grid forward's thread split: by points into
    ``num_threads()`` chunks on CPU (:func:`~warpnerf.device.run_chunks`), one launch on CUDA.
    Row ids must lie in [0, T) (not checked: a probe, not an op).
    """
    if table.dtype != torch.float32 or table.dim() != 2 or table.shape[1] != 2:
        raise ValueError(f"gather_sum: table must be (T, 2) float32, got {tuple(table.shape)} {table.dtype}")
    if rows.dtype != torch.int32 or rows.dim() != 2 or rows.shape[1] != GATHERS_PER_THREAD:
        raise ValueError(f"gather_sum: rows must be (N, {GATHERS_PER_THREAD}) int32, "
                         f"got {tuple(rows.shape)} {rows.dtype}")
    wp = devmod.init_warp()
    dev = table.device
    kernel = _gather_kernel("cpu" if dev.type == "cpu" else f"cuda:{dev.index or 0}")
    n = rows.shape[0]
    out = torch.empty(n, 2, dtype=table.dtype, device=dev)
    args = as_warp(table, wp.vec2f), as_warp(rows)
    out_wp = as_warp(out, wp.vec2f)
    chunks = devmod.split_range(n, devmod.num_threads()) if dev.type == "cpu" else [(0, n)]
    devmod.run_chunks([lambda lo=lo, hi=hi: launch(kernel, hi - lo, [*args, lo, out_wp], dev)
                       for lo, hi in chunks if hi > lo])
    return out


def gather_rate(table_rows: int, n: int = 262144, repeats: int = 5, device: torch.device | str = "cpu",
                seed: int = 0) -> float:
    """Random gathers per second of this machine: :func:`gather_sum` of ``n`` points, each reading
    8 uniformly random rows of a ``table_rows``-row float32 vec2 table; median of ``repeats`` runs.

    The rows are random over the whole table, so a grid encoding, whose coarse levels are dense
    and cache-resident and whose level-major launches stay in one level's slice, can exceed it.
    """
    dev = torch.device(device)
    gen = torch.Generator().manual_seed(seed)
    table = torch.rand(table_rows, 2, generator=gen).to(dev)
    rows = torch.randint(0, table_rows, (n, GATHERS_PER_THREAD), generator=gen, dtype=torch.int32).to(dev)

    def run():
        gather_sum(table, rows)
        _sync(dev)

    return n * GATHERS_PER_THREAD / median_seconds(run, repeats)


def gemm_flop_rate(repeats: int = 5, device: torch.device | str = "cpu", shape=GEMM_SHAPE, seed: int = 0) -> float:
    """float32 FLOP/s of ``torch.mm`` of (m, k) @ (k, n), ``shape = (m, k, n)``: 2 m k n FLOPs over
    the median of ``repeats`` runs, output allocated once (torch's own thread count)."""
    m, k, n = shape
    dev = torch.device(device)
    gen = torch.Generator().manual_seed(seed)
    a, b = torch.randn(m, k, generator=gen).to(dev), torch.randn(k, n, generator=gen).to(dev)
    out = torch.empty(m, n, device=dev)

    def run():
        torch.mm(a, b, out=out)
        _sync(dev)

    return 2.0 * m * k * n / median_seconds(run, repeats)


def mlp_flops_per_sample(*nets: torch.nn.Module) -> int:
    """Forward FLOPs per sample of every ``nn.Linear`` in ``nets``: 2 * sum(in * out) (multiply-adds;
    biases and activations are not counted). Backward (input and weight gradients) is ~2x this."""
    return sum(2 * m.in_features * m.out_features for net in nets for m in net.modules()
               if isinstance(m, torch.nn.Linear))


def mlp_seconds(nets, n: int, repeats: int = 5, seed: int = 0) -> float:
    """Median seconds of forward + backward of each net in ``nets`` on ``n`` random samples.

    Gradients go to the inputs and the weights, as in training (the density MLP's input gradient
    feeds the grid, the color MLP's the density MLP); returned, not accumulated into ``.grad``.
    """
    gen = torch.Generator().manual_seed(seed)
    dev = next(nets[0].parameters()).device
    cases = []
    for net in nets:
        linears = [m for m in net.modules() if isinstance(m, torch.nn.Linear)]
        x = torch.randn(n, linears[0].in_features, generator=gen).to(dev).requires_grad_()
        cotangent = torch.ones(n, linears[-1].out_features, device=dev)  # allocated once, as in bench_encoding
        cases.append((net, x, cotangent, [x, *net.parameters()]))

    def run():
        for net, x, cotangent, wrt in cases:
            torch.autograd.grad(net(x), wrt, cotangent)
        _sync(dev)

    return median_seconds(run, repeats)


def bench_encoding(n: int = 262144, levels: int = 16, features: int = 2, log2_table_size: int = 19,
                   repeats: int = 5, torch_repeats: int | None = None, device: str = "cpu", seed: int = 0,
                   model: str = "ngp", cp_rank: int = 8, roofline: bool = True) -> dict:
    """Grid-encoding throughput (points/s) of the Warp op and its torch twin.

    ``model`` picks the encoding: ``ngp`` (hash grid: ``features``, ``log2_table_size``) or
    ``mtrf`` (multi-resolution CP lines: ``cp_rank`` components, lines of 16..512 entries).
    Cases: uniform random points (the headline numbers), ray-like coherent points, and the
    G²fR mask early in training (first 4 levels active). ``fwdbwd`` differentiates the grid
    only, as in NeRF training with fixed cameras; ``warp_fwdbwd_xgrad_pts_s`` adds the
    gradient with respect to the points (pose task). ``torch_repeats`` defaults to ``repeats``.

    ``warp_bwd_alloc_s`` is the median time of allocating and zeroing one parameter gradient
    (``torch.zeros_like(table)``), which the Warp backward does on every call: the part of
    ``warp_fwdbwd_s`` that is not kernel work. ``roofline`` (hash grid only; ``None`` for
    ``mtrf`` or ``roofline=False``): the machine's random-gather rate on a table of
    ``levels * 2^log2_table_size`` vec2 rows (:func:`gather_rate` with ``n * levels`` points,
    at most 2^20) and the rate the uniform-point forward reaches, ``n * L * 8`` corner gathers
    per ``warp_fwd_s``.
    """
    torch_repeats = repeats if torch_repeats is None else torch_repeats
    wp_device = devmod.resolve_device(device)
    tdev = devmod.torch_device(wp_device)
    gen = torch.Generator().manual_seed(seed)
    if model == "ngp":
        encode_op, twin_op = hashgrid_encode, twin_hashgrid.hashgrid_encode
        spec = HashGridSpec.create(dim=3, n_levels=levels, n_features=features, log2_table_size=log2_table_size)
        table = HashGridEncoder(spec, generator=gen).table.data.to(tdev).requires_grad_()
    elif model == "mtrf":
        encode_op, twin_op = cpgrid_encode, twin_cpgrid.cpgrid_encode
        spec = CPGridSpec.create(n_levels=levels, rank=cp_rank)
        table = init_cp_lines(spec, generator=gen).to(tdev).requires_grad_()
    else:
        raise ValueError(f"unknown model '{model}': expected ngp or mtrf")
    early = torch.zeros(levels)
    early[: min(4, levels)] = 1.0
    cases = {
        "uniform": (torch.rand(n, 3, generator=gen), None),
        "rays": (ray_like_points(n, generator=gen), None),
        "g2fr_first4": (torch.rand(n, 3, generator=gen), early),
    }

    # the cotangent is allocated once: the timed runs hold only the op's own allocations
    cotangent = torch.ones(n, spec.out_dim, device=tdev)

    def timed(encode, x, w, backward: bool, xgrad: bool = False, reps: int = repeats) -> float:
        def run():
            xi = x.requires_grad_(xgrad) if xgrad else x
            if backward:
                table.grad = None  # autograd then keeps the op's gradient tensor as .grad, no extra copy
                if xgrad:
                    xi.grad = None
                out = encode(xi, table, spec, w)
                out.backward(cotangent)
            else:
                with torch.no_grad():
                    encode(xi, table, spec, w)
            _sync(tdev)
        return median_seconds(run, reps)

    results = {}
    for name, (x, w) in cases.items():
        x = x.to(tdev)
        w = None if w is None else w.to(tdev)
        r = {
            "warp_fwd_s": timed(encode_op, x, w, False),
            "warp_fwdbwd_s": timed(encode_op, x, w, True),
            "torch_fwd_s": timed(twin_op, x, w, False, reps=torch_repeats),
            "torch_fwdbwd_s": timed(twin_op, x, w, True, reps=torch_repeats),
        }
        if name == "uniform":
            r["warp_fwdbwd_xgrad_s"] = timed(encode_op, x.clone(), w, True, xgrad=True)
        for key in [k for k in r if k.endswith("_s")]:
            r[key[:-2] + "_pts_s"] = n / r[key]
        r["ratio_fwd"] = r["torch_fwd_s"] / r["warp_fwd_s"]
        r["ratio_fwdbwd"] = r["torch_fwdbwd_s"] / r["warp_fwdbwd_s"]
        results[name] = r

    head = results["uniform"]
    params = table.detach()

    def alloc():
        torch.zeros_like(params)  # what GridLauncher.backward allocates per call
        _sync(tdev)

    alloc_s = median_seconds(alloc, repeats)
    roof = None
    if roofline and model == "ngp":
        table_rows = levels << log2_table_size
        # as many threads as the forward's (point, level) pairs, so launch overheads weigh the same
        points = min(n * levels, _GATHER_POINTS_MAX)
        machine = gather_rate(table_rows, points, repeats, tdev, seed)
        reached = n * levels * GATHERS_PER_THREAD / head["warp_fwd_s"]
        roof = {"gather_table_rows": table_rows, "gather_points": points, "gathers_per_point": GATHERS_PER_THREAD,
                "machine_gathers_s": machine,
                "encoding_fwd_gathers_s": reached, "encoding_fwd_fraction": reached / machine}
    return {
        "benchmark": "encoding",
        "model": model,
        "n": n,
        "levels": levels,
        "features": features if model == "ngp" else cp_rank,
        "log2_table_size": log2_table_size if model == "ngp" else None,
        "device": wp_device,
        "threads": devmod.num_threads() if wp_device == "cpu" else None,
        "openmp_wait": openmp.describe(),
        "repeats": repeats,
        "torch_repeats": torch_repeats,
        "torch_threads": torch.get_num_threads(),
        **{k: head[k] for k in ("warp_fwd_pts_s", "warp_fwdbwd_pts_s", "warp_fwdbwd_xgrad_pts_s",
                                "torch_fwd_pts_s", "torch_fwdbwd_pts_s", "ratio_fwd", "ratio_fwdbwd")},
        "warp_bwd_alloc_s": alloc_s,
        "warp_bwd_alloc_fraction": alloc_s / head["warp_fwdbwd_s"],
        "roofline": roof,
        "cases": results,
    }


def format_encoding(res: dict) -> str:
    grid = (f"hash-grid encoding: N={res['n']}, L={res['levels']}, F={res['features']}, T=2^{res['log2_table_size']}"
            if res.get("model", "ngp") == "ngp" else f"Mtrf (CP lines) encoding: N={res['n']}, L={res['levels']}, R={res['features']}")
    lines = [
        f"{grid}, device={res['device']}, threads={res['threads']}, torch threads={res['torch_threads']}, "
        f"OpenMP wait {res.get('openmp_wait', '?')}",
        f"{'case':<13}{'warp fwd':>14}{'warp fwd+bwd':>15}{'torch fwd':>14}{'torch fwd+bwd':>15}{'ratio fwd':>11}{'ratio f+b':>11}",
    ]
    for name, r in res["cases"].items():
        lines.append(
            f"{name:<13}{r['warp_fwd_pts_s'] / 1e6:>10.2f} M/s{r['warp_fwdbwd_pts_s'] / 1e6:>11.2f} M/s"
            f"{r['torch_fwd_pts_s'] / 1e6:>10.2f} M/s{r['torch_fwdbwd_pts_s'] / 1e6:>11.2f} M/s"
            f"{r['ratio_fwd']:>10.1f}x{r['ratio_fwdbwd']:>10.1f}x"
        )
    lines.append(f"fwd+bwd incl. d/dx (uniform): {res['warp_fwdbwd_xgrad_pts_s'] / 1e6:.2f} M points/s")
    lines.append(f"warp fwd+bwd allocates a zeroed table gradient per call: {res['warp_bwd_alloc_s'] * 1e3:.2f} ms of "
                 f"{res['n'] / res['warp_fwdbwd_pts_s'] * 1e3:.2f} ms ({res['warp_bwd_alloc_fraction']:.0%})")
    roof = res.get("roofline")
    if roof:
        lines.append(f"roofline: machine {roof['machine_gathers_s'] / 1e9:.3f} G gathers/s "
                     f"({roof['gathers_per_point']} random rows of a {roof['gather_table_rows']:,}-row table), "
                     f"encoding fwd reaches {roof['encoding_fwd_gathers_s'] / 1e9:.3f} G/s "
                     f"({roof['encoding_fwd_fraction']:.0%})")
    return "\n".join(lines)


def _twin_ops():
    """Context manager that runs every op of a training step (every public op of
    :mod:`warpnerf.ops`) on its torch twin: :func:`warpnerf.ops.use_backend` ``("torch")``."""
    return use_backend("torch")


def bench_step(repeats: int = 10, warmup_steps: int = 200, device: str = "cpu", data_root: str | None = None,
               torch_repeats: int | None = None, roofline: bool = True) -> dict:
    """Training-step throughput on a standard batch.

    Trains the ``full`` preset for ``warmup_steps`` steps on lego (when ``data_root`` has it) or
    on the built-in chair, so the occupancy grid is realistic, then times ``repeats`` steps with
    the Warp ops and ``torch_repeats`` steps with every op replaced by its pure-torch twin (same
    state, same batch size; ``torch_repeats`` defaults to ``repeats``). Each backend gets one
    untimed step first; rates are from the median step time. Reports samples/s and
    iterations/s of both and their ratio.

    ``roofline`` (``None`` when ``roofline=False``): the float32 GEMM rate (:func:`gemm_flop_rate`)
    and what the field's two MLPs reach: forward + backward (3x the forward FLOPs,
    :func:`mlp_flops_per_sample`) of the density and color MLPs alone on the Warp arm's median
    samples per step (:func:`mlp_seconds`, ``repeats`` runs), timed after both arms, and the
    share of the Warp step that MLP time is.
    """
    if repeats < 1:
        raise ValueError(f"repeats must be >= 1, got {repeats}")
    torch_repeats = repeats if torch_repeats is None else torch_repeats
    scene_name = "lego" if data_root else "chair"
    cfg = build_config("full", overrides=dict(scene=scene_name, data_root=data_root, iters=warmup_steps + 1000,
                                              device=device))
    wp_device = devmod.resolve_device(device)
    scene = load_scene_for(cfg, progress=False)
    trainer = Trainer(cfg, scene, make_task(cfg), wp_device)
    for step in range(warmup_steps):
        trainer.train_step(step)

    rays = trainer.n_rays
    trainer.occupancy.update_every = 1 << 30  # no grid updates inside the timed steps

    def timed(n: int, start: int) -> tuple[float, float]:
        """(median seconds per step, median samples per step) of n steps after one untimed step."""
        times, samples = [], []
        for k in range(n + 1):
            # train_step adapts the ray count; reset it so both backends see the same batch size
            trainer.n_rays = rays
            t0 = time.perf_counter()
            stats = trainer.train_step(start + k)
            if k:
                times.append(time.perf_counter() - t0)
                samples.append(stats["samples_per_ray"] * rays)
        return statistics.median(times), statistics.median(samples)

    start = warmup_steps
    warp_step, warp_samples = timed(repeats, start)
    with _twin_ops():
        torch_step, torch_samples = timed(torch_repeats, start + repeats + 1)
    roof = None
    if roofline:
        nets = (trainer.field.density_net, trainer.field.color_net)
        samples = max(1, round(warp_samples))
        flops = 3 * mlp_flops_per_sample(*nets)  # forward + backward per sample
        mlp_s = mlp_seconds(nets, samples, repeats)
        reached = flops * samples / mlp_s
        peak = gemm_flop_rate(repeats, devmod.torch_device(wp_device))
        roof = {"gemm_shape": list(GEMM_SHAPE), "gemm_flops_s": peak, "mlp_samples": samples,
                "mlp_fwdbwd_flops_per_sample": flops, "mlp_s": mlp_s,
                "mlp_flops_s": reached, "mlp_fraction": reached / peak, "mlp_step_fraction": mlp_s / warp_step}
    return {
        "benchmark": "step",
        "scene": scene.name,
        "scene_source": scene.source,
        "device": wp_device,
        "threads": devmod.num_threads(),
        "openmp_wait": openmp.describe(),
        "rays_per_step": rays,
        "repeats": repeats,
        "torch_repeats": torch_repeats,
        "warp_iters_s": 1.0 / warp_step,
        "warp_samples_s": warp_samples / warp_step,
        "torch_iters_s": 1.0 / torch_step,
        "torch_samples_s": torch_samples / torch_step,
        "ratio": torch_step / warp_step,
        "samples_per_step": warp_samples,
        "occupied_fraction": trainer.occupancy.occupied_fraction(),
        "roofline": roof,
    }


def format_step(res: dict) -> str:
    text = (f"training step on {res['scene']} ({res['scene_source']}), {res['rays_per_step']} rays, "
            f"{res['samples_per_step']:.0f} samples/step, device={res['device']}, threads={res['threads']}, "
            f"OpenMP wait {res.get('openmp_wait', '?')}\n"
            f"warp : {res['warp_iters_s']:.2f} it/s, {res['warp_samples_s'] / 1e6:.2f} M samples/s\n"
            f"torch: {res['torch_iters_s']:.3f} it/s, {res['torch_samples_s'] / 1e6:.3f} M samples/s\n"
            f"ratio (torch time / warp time): {res['ratio']:.1f}x")
    roof = res.get("roofline")
    if roof:
        text += (f"\nroofline: GEMM {roof['gemm_flops_s'] / 1e9:.1f} GFLOP/s, MLPs fwd+bwd reach "
                 f"{roof['mlp_flops_s'] / 1e9:.1f} GFLOP/s ({roof['mlp_fraction']:.0%}), "
                 f"{roof['mlp_step_fraction']:.0%} of the warp step")
    return text


def bench_render(run_dir: str, views: int = 5, device: str = "auto", every_sample: bool = False,
                 progress: bool = False) -> dict:
    """Seconds per rendered test view of a finished run (``render_image``, as evaluation, videos
    and the viewer render), with the PSNR of those views.

    Renders ``views`` test views spread evenly over the test set (one untimed view first:
    compilation, caches); reports the median, min and max seconds and the samples evaluated per
    pixel. ``every_sample`` renders with early ray termination off (``stop_transmittance`` = 0:
    every marched sample evaluated), the reference the rounds are measured against."""
    if views < 1:
        raise ValueError(f"views must be >= 1, got {views}")
    trainer = load_run(run_dir, device=device, progress=progress)
    test = trainer.scene.test
    weights = trainer.level_weights(trainer.cfg.iters)
    renderer = trainer.renderer
    if every_sample:
        renderer.stop_transmittance = 0.0
    picks = sorted({round(i * (len(test) - 1) / max(views - 1, 1)) for i in range(views)})
    dev = trainer.device
    secs, psnrs, evaluated = [], [], []
    for k in [picks[0]] + picks:
        _sync(dev)
        t0 = time.perf_counter()
        img = renderer.render_image(test.c2w[k].to(dev), test.height, test.width, test.focal, test.cx, test.cy,
                                    weights)
        _sync(dev)
        secs.append(time.perf_counter() - t0)
        evaluated.append(img["samples"])
        psnrs.append(psnr(img["rgb"].clamp(0, 1).cpu(), test.images[k]))
    secs, psnrs, evaluated = secs[1:], psnrs[1:], evaluated[1:]
    return {
        "benchmark": "render",
        "run": run_dir,
        "scene": trainer.scene.name,
        "device": str(dev),
        "threads": devmod.num_threads(),
        "openmp_wait": openmp.describe(),
        "width": test.width,
        "height": test.height,
        "views": picks,
        "mode": "every sample" if every_sample else "rounds",
        "median_s": statistics.median(secs),
        "min_s": min(secs),
        "max_s": max(secs),
        "samples_per_pixel": statistics.mean(evaluated) / (test.width * test.height),
        "psnr": statistics.mean(psnrs),
    }


def format_render(res: dict) -> str:
    return (f"render {res['scene']} ({res['run']}), {len(res['views'])} test views {res['width']}x{res['height']}, "
            f"{res['mode']}, device={res['device']}, threads={res['threads']}\n"
            f"{res['median_s']:.3f} s per view (median; min {res['min_s']:.3f}, max {res['max_s']:.3f}), "
            f"{res['samples_per_pixel']:.1f} samples evaluated per pixel, PSNR {res['psnr']:.3f} dB")
