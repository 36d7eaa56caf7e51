"""LPIPS(alex) in plain torch: the formula with a stand-in network, the lpips package's own forward
as a reference (its torchvision import replaced by our trunk), weight loading, and null without weights."""

import importlib.util
import sys
import types

import pytest
import torch

from warpnerf.train import metrics as M


@pytest.fixture(autouse=True)
def reset_lpips(tmp_path, monkeypatch):
    # no real AlexNet checkpoint may be found (and none is ever downloaded): an empty hub folder
    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(tmp_path / "hub"))
    M.configure_lpips("")
    yield
    monkeypatch.undo()
    M.configure_lpips("")


class Identity(torch.nn.Module):
    """Stand-in trunk: one 'feature map' = the scaled image itself (3 channels)."""

    channels = (3,)

    def forward(self, x):
        return [x]


def _images(n=2, size=64, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(n, size, size, 3, generator=g), torch.rand(n, size, size, 3, generator=g)


def test_lpips_formula_with_a_stand_in_network():
    net = LPIPS_with_ones = M.LPIPSNet(Identity())
    with torch.no_grad():
        LPIPS_with_ones.lins[0].weight.fill_(1.0)
    a, b = _images()
    assert M.configure_lpips(net=net)
    got = M.lpips_or_none(a, b)
    # by hand: scale like lpips, unit-normalise over channels, squared distance summed over channels, mean
    shift = torch.tensor([-0.030, -0.088, -0.188])
    scale = torch.tensor([0.458, 0.448, 0.450])
    fa, fb = ((a * 2 - 1) - shift) / scale, ((b * 2 - 1) - shift) / scale
    fa, fb = fa / (fa.norm(dim=-1, keepdim=True) + 1e-10), fb / (fb.norm(dim=-1, keepdim=True) + 1e-10)
    want = ((fa - fb) ** 2).sum(-1).mean((1, 2)).mean()
    assert got == pytest.approx(float(want), rel=1e-5)
    assert M.lpips_or_none(a, a) == pytest.approx(0.0, abs=1e-7)
    assert M.lpips_or_none(b, a) == pytest.approx(got, rel=1e-6)  # symmetric


def test_lpips_is_null_without_weights(tmp_path):
    assert M.configure_lpips("") is False or importlib.util.find_spec("lpips") is None
    a, b = _images(1)
    assert M.lpips_or_none(a, b) is None
    with pytest.raises(ValueError, match="no usable LPIPS"):
        M.configure_lpips(str(tmp_path / "missing.pth"))


def _fake_torchvision(monkeypatch, features):
    """A stand-in torchvision whose models.alexnet(...).features is ``features`` (no download)."""
    tv = types.ModuleType("torchvision")
    models = types.ModuleType("torchvision.models")
    models.alexnet = lambda pretrained=False, **kw: types.SimpleNamespace(features=features)
    tv.models = models
    monkeypatch.setitem(sys.modules, "torchvision", tv)
    monkeypatch.setitem(sys.modules, "torchvision.models", models)
    for name in [m for m in sys.modules if m == "lpips" or m.startswith("lpips.")]:
        monkeypatch.delitem(sys.modules, name)


def test_matches_the_lpips_package_and_loads_its_weights(monkeypatch, tmp_path):
    if importlib.util.find_spec("lpips") is None:
        pytest.skip("lpips package not installed (pip install --no-deps lpips)")
    pytest.importorskip("scipy")  # lpips.trainer imports scipy.ndimage
    torch.manual_seed(0)
    trunk = M.AlexNetTrunk()  # random trunk weights: the real ImageNet ones cannot be downloaded here
    _fake_torchvision(monkeypatch, trunk.features)
    import lpips

    ref = lpips.LPIPS(net="alex", version="0.1", pretrained=True, pnet_rand=True, verbose=False).eval()
    a, b = _images(2, 64)
    with torch.no_grad():
        want = ref(a.permute(0, 3, 1, 2) * 2 - 1, b.permute(0, 3, 1, 2) * 2 - 1).flatten()
    # 1) a full lpips state dict, from one file
    full = tmp_path / "lpips_alex_full.pth"
    torch.save(ref.state_dict(), full)
    assert M.configure_lpips(str(full))
    assert M.lpips_or_none(a, b) == pytest.approx(float(want.mean()), rel=1e-5)
    # 2) torchvision's checkpoint layout (features.N.*, plus the classifier we ignore) + lpips' shipped alex.pth
    folder = tmp_path / "weights"
    folder.mkdir()
    tv_state = {f"features.{k}": v for k, v in trunk.features.state_dict().items()}
    tv_state["classifier.1.weight"] = torch.zeros(4096, 9216)
    torch.save(tv_state, folder / M.ALEXNET_CHECKPOINT)
    assert M.configure_lpips(str(folder))
    per_image = [M.lpips_or_none(a[i], b[i]) for i in range(2)]
    assert per_image == pytest.approx(want.tolist(), rel=1e-5)
    # 3) the auto path: torch hub's checkpoint folder + the installed lpips package
    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(tmp_path / "hub2"))
    (tmp_path / "hub2" / "checkpoints").mkdir(parents=True)
    torch.save(tv_state, tmp_path / "hub2" / "checkpoints" / M.ALEXNET_CHECKPOINT)
    assert M.configure_lpips("")
    assert M.lpips_or_none(a, b) == pytest.approx(float(want.mean()), rel=1e-5)
