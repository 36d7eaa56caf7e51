"""Benchmarks that print measured numbers (``warpnerf bench ...``).

Each benchmark times the Warp op and its pure-torch twin in the same process: median of
several repeats after one warm-up run (which also absorbs Warp's kernel compilation).
"""

from __future__ import annotations

import statistics
import time
from typing import Callable

import torch

from . import device as devmod


def median_seconds(fn: Callable[[], object], repeats: int) -> float:
    fn()  # warm-up: compilation, allocator, caches
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


def bench_encoding(n: int = 262144, levels: int = 16, features: int = 2, log2_table_size: int = 19,
                   repeats: int = 5, torch_repeats: int = 3, device: str = "cpu", seed: int = 0) -> dict:
    """Hash-grid encoding throughput (points/s) of the Warp op and the torch twin.

    Cases: uniform random points (the headline numbers), ray-like coherent points, and the
    G²fR mask early in training (first 4 levels active). ``fwdbwd`` differentiates the table
    only, as in NeRF training with fixed cameras; ``warp_fwdbwd_xgrad_pts_s`` adds the
    gradient with respect to the points (pose task).
    """
    from .encoders import HashGridEncoder
    from .ops.hashgrid import HashGridSpec, hashgrid_encode
    from .ops.reference import hashgrid as twin

    wp_device = devmod.resolve_device(device)
    tdev = devmod.torch_device(wp_device)
    gen = torch.Generator().manual_seed(seed)
    spec = HashGridSpec.create(dim=3, n_levels=levels, n_features=features, log2_table_size=log2_table_size)
    table = HashGridEncoder(spec, generator=gen).table.data.to(tdev).requires_grad_()
    early = torch.zeros(levels)
    early[: min(4, levels)] = 1.0
    cases = {
        "uniform": (torch.rand(n, 3, generator=gen), None),
        "rays": (ray_like_points(n, generator=gen), None),
        "g2fr_first4": (torch.rand(n, 3, generator=gen), early),
    }

    def sync():
        if tdev.type == "cuda":
            torch.cuda.synchronize()

    def timed(encode, x, w, backward: bool, xgrad: bool = False, reps: int = repeats) -> float:
        def run():
            xi = x.requires_grad_(xgrad) if xgrad else x
            if backward:
                table.grad = None
                out = encode(xi, table, spec, w)
                out.backward(torch.ones_like(out))
            else:
                with torch.no_grad():
                    encode(xi, table, spec, w)
            sync()
        return median_seconds(run, reps)

    results = {}
    for name, (x, w) in cases.items():
        x = x.to(tdev)
        w = None if w is None else w.to(tdev)
        r = {
            "warp_fwd_s": timed(hashgrid_encode, x, w, False),
            "warp_fwdbwd_s": timed(hashgrid_encode, x, w, True),
            "torch_fwd_s": timed(twin.hashgrid_encode, x, w, False, reps=torch_repeats),
            "torch_fwdbwd_s": timed(twin.hashgrid_encode, x, w, True, reps=torch_repeats),
        }
        if name == "uniform":
            r["warp_fwdbwd_xgrad_s"] = timed(hashgrid_encode, x.clone(), w, True, xgrad=True)
        for key in [k for k in r if k.endswith("_s")]:
            r[key[:-2] + "_pts_s"] = n / r[key]
        r["ratio_fwd"] = r["torch_fwd_s"] / r["warp_fwd_s"]
        r["ratio_fwdbwd"] = r["torch_fwdbwd_s"] / r["warp_fwdbwd_s"]
        results[name] = r

    head = results["uniform"]
    return {
        "benchmark": "encoding",
        "n": n,
        "levels": levels,
        "features": features,
        "log2_table_size": log2_table_size,
        "device": wp_device,
        "threads": devmod.num_threads() if wp_device == "cpu" else None,
        "repeats": repeats,
        "torch_threads": torch.get_num_threads(),
        **{k: head[k] for k in ("warp_fwd_pts_s", "warp_fwdbwd_pts_s", "warp_fwdbwd_xgrad_pts_s",
                                "torch_fwd_pts_s", "torch_fwdbwd_pts_s", "ratio_fwd", "ratio_fwdbwd")},
        "cases": results,
    }


def format_encoding(res: dict) -> str:
    lines = [
        f"hash-grid encoding: N={res['n']}, L={res['levels']}, F={res['features']}, T=2^{res['log2_table_size']}, "
        f"device={res['device']}, threads={res['threads']}, torch threads={res['torch_threads']}",
        f"{'case':<13}{'warp fwd':>14}{'warp fwd+bwd':>15}{'torch fwd':>14}{'torch fwd+bwd':>15}{'ratio fwd':>11}{'ratio f+b':>11}",
    ]
    for name, r in res["cases"].items():
        lines.append(
            f"{name:<13}{r['warp_fwd_pts_s'] / 1e6:>10.2f} M/s{r['warp_fwdbwd_pts_s'] / 1e6:>11.2f} M/s"
            f"{r['torch_fwd_pts_s'] / 1e6:>10.2f} M/s{r['torch_fwdbwd_pts_s'] / 1e6:>11.2f} M/s"
            f"{r['ratio_fwd']:>10.1f}x{r['ratio_fwdbwd']:>10.1f}x"
        )
    lines.append(f"fwd+bwd incl. d/dx (uniform): {res['warp_fwdbwd_xgrad_pts_s'] / 1e6:.2f} M points/s")
    return "\n".join(lines)
