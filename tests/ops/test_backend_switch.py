"""warpnerf.ops.use_backend: one switch that routes every public op to its pure-torch twin.

Under ``use_backend("torch")`` each op of ``registry.OPS`` must call the function of the same name in
its twin module (a spy counts the calls) and return what the Warp op returns; afterwards the Warp ops
run again. Every function ``warpnerf.ops`` exports is either such an op or listed here as not one."""

import pytest
import torch

import warpnerf.ops as ops
from warpnerf.ops import registry
from warpnerf.ops.cpgrid import CPGridSpec, init_cp_lines
from warpnerf.ops.hashgrid_spec import HashGridSpec
from warpnerf.ops.raymarch import MarchState

# exported functions that are not ops (no kernel, no twin)
NOT_OPS = {"init_cp_lines", "use_backend", "current_backend"}
AABB = (-1.0, -1.0, -1.0, 1.0, 1.0, 1.0)


def test_every_exported_function_is_a_registered_op_with_a_twin():
    functions = {n for n in ops.__all__ if callable(getattr(ops, n)) and not isinstance(getattr(ops, n), type)}
    names = {name for _, name in registry.OPS}
    assert functions - NOT_OPS == names
    for module, name in registry.OPS:
        op = getattr(module, name)
        assert op is getattr(ops, name)
        twin_module, twin_name = op.__twin__
        assert twin_name == name and callable(getattr(registry.TWIN_MODULES[twin_module], name))


def _cases():
    """{op name: a function of the backend's ops returning the outputs to compare}; every input fixed."""
    g = torch.Generator().manual_seed(0)
    res = 8
    bitfield = (torch.rand(res**3, generator=g) < 0.4).to(torch.uint8)
    o = torch.randn(64, 3, generator=g) * 0.3 + torch.tensor([0.0, 0.0, -3.0])
    d = torch.nn.functional.normalize(torch.randn(64, 3, generator=g) * 0.2 + torch.tensor([0.0, 0.0, 1.0]), dim=-1)
    march = (AABB, bitfield, res, 0.0, 10.0, 0.05)
    hspec = HashGridSpec.create(dim=3, n_levels=3, n_features=2, log2_table_size=8, base_resolution=4,
                                max_resolution=32)
    table = torch.randn(hspec.n_rows, hspec.n_features, generator=g) * 0.1
    cspec = CPGridSpec.create(n_levels=2, rank=2, base_resolution=4, max_resolution=16)
    lines = init_cp_lines(cspec, generator=g)
    x = torch.rand(100, 3, generator=g)
    counts = torch.tensor([3, 0, 5, 1], dtype=torch.int32)
    offsets = (torch.cumsum(counts, 0) - counts).int()
    sig, rgb = torch.rand(9, generator=g) * 5.0, torch.rand(9, 3, generator=g)
    ts = torch.cumsum(torch.rand(9, generator=g) * 0.2, 0)
    te = ts + 0.1
    cells = torch.randint(0, res**3, (200,), generator=g, dtype=torch.int32)
    jitter = torch.rand(200, 3, generator=g)
    points = torch.rand(200, 3, generator=g) * 2.0 - 1.0
    sigmas = torch.rand(200, generator=g)
    dens = torch.rand(res**3, generator=g)
    fresh = torch.where(torch.rand(res**3, generator=g) < 0.5, dens * 2.0, torch.full_like(dens, -1.0))

    def window(op):
        state = MarchState.start(o.shape[0], 0.0, "cpu")
        t0, t1, n = op(o, d, state, 6, *march)
        keep = torch.arange(6) < n[:, None]
        return t0[keep], t1[keep], n, *state

    return {
        "hashgrid_encode": lambda op: op(x, table, hspec),
        "cpgrid_encode": lambda op: op(x, lines, cspec),
        "march_rays": lambda op: tuple(op(o, d, *march)),
        "march_rays_within_budget": lambda op: (*op(o, d, *march, max_total_samples=300)[0],
                                                op(o, d, *march, max_total_samples=300)[1]),
        "march_rays_window": window,
        "composite_rays": lambda op: op(sig, rgb, ts, te, offsets, counts, return_weights=True),
        "active_sample_counts": lambda op: op(sig * 20.0, ts, te, offsets, counts),
        "occupancy_sample_points": lambda op: op(cells, jitter, AABB[:3], [2.0 / res] * 3, res),
        "occupancy_scatter_max": lambda op: op(points, sigmas, AABB[:3], [res / 2.0] * 3, res,
                                               torch.full((res**3,), -1.0)),
        "occupancy_ema": lambda op: op(fresh, 0.9, dens.clone()),
        "occupancy_bitfield": lambda op: op(dens, 0.5, torch.zeros(res**3, dtype=torch.uint8)),
    }


CASES = _cases()


def test_the_cases_cover_every_op():
    assert set(CASES) == {name for _, name in registry.OPS}


@pytest.mark.parametrize("module,name", registry.OPS, ids=[name for _, name in registry.OPS])
def test_under_the_switch_each_op_runs_its_twin_and_agrees_with_warp(monkeypatch, module, name):
    twin_module = registry.TWIN_MODULES[getattr(module, name).__twin__[0]]
    calls = []
    real_twin = getattr(twin_module, name)

    def spy(*args, **kwargs):
        calls.append(name)
        return real_twin(*args, **kwargs)

    monkeypatch.setattr(twin_module, name, spy)
    op = getattr(ops, name)  # what callers hold: the decorated op, looked up once
    warp_out = CASES[name](op)
    assert calls == [] and ops.current_backend() == "warp"
    with ops.use_backend("torch"):
        assert ops.current_backend() == "torch"
        torch_out = CASES[name](op)
    assert calls and set(calls) == {name}
    assert ops.current_backend() == "warp"
    warp_out = warp_out if isinstance(warp_out, tuple) else (warp_out,)
    torch_out = torch_out if isinstance(torch_out, tuple) else (torch_out,)
    assert len(warp_out) == len(torch_out)
    for w, t in zip(warp_out, torch_out):
        if isinstance(w, torch.Tensor) and w.is_floating_point():
            torch.testing.assert_close(t.to(w.dtype), w, rtol=1e-5, atol=1e-5)
        elif isinstance(w, torch.Tensor):
            assert torch.equal(t.to(w.dtype), w)
        else:
            assert t == w
    # back on Warp: the twin is no longer called
    n = len(calls)
    CASES[name](op)
    assert len(calls) == n


def test_use_backend_nests_restores_after_errors_and_rejects_unknown_names():
    with ops.use_backend("torch"):
        with ops.use_backend("warp"):
            assert ops.current_backend() == "warp"
        assert ops.current_backend() == "torch"
    with pytest.raises(RuntimeError, match="boom"):
        with ops.use_backend("torch"):
            raise RuntimeError("boom")
    assert ops.current_backend() == "warp"
    with pytest.raises(ValueError, match="unknown backend"):
        with ops.use_backend("cuda"):
            pass
