"""LPIPS from a user's local weight files: random stand-in weights written in torchvision's and the
lpips package's layouts load by their key names, the distance equals a float64 NumPy evaluation
of the paper's definition, bad files give one clear error, and the appearance loss and metrics
gain the term only when it is configured (the weights never enter a checkpoint)."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
import torch
from numpy.lib.stride_tricks import sliding_window_view

from scube_sim.errors import InputError
from scube_sim.model.appearance.losses import evaluate_item, view_losses
from scube_sim.model.appearance.net import AppearanceNet
from scube_sim.model.nn.lpips import LPIPS, LPIPSConfig, load_lpips
from scube_sim.model.stages import get_stage

from ..appearance.test_appearance import DATA, MODEL, data  # noqa: F401  (the tiny worlds fixture)

# torchvision's AlexNet `features`, written out here rather than read from the module under test:
# (index, in, out, kernel, stride, padding) of each convolution; 3 x 3 / 2 max pools after 1 and 4.
ALEX_CONVS = [(0, 3, 64, 11, 4, 2), (3, 64, 192, 5, 1, 2), (6, 192, 384, 3, 1, 1), (8, 384, 256, 3, 1, 1),
              (10, 256, 256, 3, 1, 1)]


def _standin_files(tmp_path, seed=0):
    """Random weights saved as torchvision's alexnet state dict (with a classifier to ignore) and
    as the lpips package's alex.pth -> (backbone path, linear path, the numpy arrays)."""
    g = torch.Generator().manual_seed(seed)
    bb, arrays = {}, {}
    for i, cin, cout, k, _, _ in ALEX_CONVS:
        bb[f"features.{i}.weight"] = torch.randn(cout, cin, k, k, generator=g) * (2 / (cin * k * k)) ** 0.5
        bb[f"features.{i}.bias"] = torch.randn(cout, generator=g) * 0.1
    bb["classifier.1.weight"] = torch.zeros(4, 9216)
    lin = {f"lin{k}.model.1.weight": torch.rand(1, c, 1, 1, generator=g)
           for k, c in enumerate([64, 192, 384, 256, 256])}
    torch.save(bb, tmp_path / "alexnet-owt.pth")
    torch.save(lin, tmp_path / "alex.pth")
    arrays.update({k: v.double().numpy() for k, v in {**bb, **lin}.items()})
    return tmp_path / "alexnet-owt.pth", tmp_path / "alex.pth", arrays


def _conv(x, w, b, stride, pad):
    xp = np.pad(x, ((0, 0), (pad, pad), (pad, pad)))
    win = sliding_window_view(xp, w.shape[2:], axis=(1, 2))[:, ::stride, ::stride]
    return np.einsum("chwij,ocij->ohw", win, w) + b[:, None, None]


def _pool(x):
    return sliding_window_view(x, (3, 3), axis=(1, 2))[:, ::2, ::2].max((3, 4))


def _area_weights(mask, h, w):
    """PyTorch's adaptive average pooling of (H, W) to (h, w): cell i spans floor(i H / h) to
    ceil((i + 1) H / h)."""
    H, W = mask.shape
    out = np.empty((h, w))
    for i in range(h):
        for j in range(w):
            r0, r1 = (i * H) // h, -((-(i + 1) * H) // h)
            c0, c1 = (j * W) // w, -((-(j + 1) * W) // w)
            out[i, j] = mask[r0:r1, c0:c1].mean()
    return out


def _lpips_numpy(a, b, arrays, mask=None):
    """The v0.1 LPIPS of two (3, H, W) images in [0, 1], in float64."""
    shift = np.array([-0.030, -0.088, -0.188])[:, None, None]
    scale = np.array([0.458, 0.448, 0.450])[:, None, None]
    feats = []
    for img in (a, b):
        x = ((img * 2 - 1) - shift) / scale
        taps = []
        for n, (i, _, _, _, s, p) in enumerate(ALEX_CONVS):
            x = np.maximum(_conv(x, arrays[f"features.{i}.weight"], arrays[f"features.{i}.bias"], s, p), 0)
            taps.append(x)
            if n in (0, 1):
                x = _pool(x)
        feats.append(taps)
    total = 0.0
    for k, (fa, fb) in enumerate(zip(*feats)):
        ua = fa / (np.sqrt((fa ** 2).sum(0, keepdims=True)) + 1e-10)
        ub = fb / (np.sqrt((fb ** 2).sum(0, keepdims=True)) + 1e-10)
        d = np.einsum("c,chw->hw", arrays[f"lin{k}.model.1.weight"][0, :, 0, 0], (ua - ub) ** 2)
        if mask is None:
            total += d.mean()
        else:
            wts = _area_weights(mask, *d.shape)
            total += (d * wts).sum() / wts.sum()
    return total


def test_the_distance_is_the_papers_definition_on_stand_in_weights(tmp_path):
    """(rel 1e-7: the normalisation constants are float32 buffers.)"""
    bb, lin, arrays = _standin_files(tmp_path)
    net = load_lpips(LPIPSConfig(backbone=str(bb), linear=str(lin))).double()
    rng = np.random.default_rng(1)
    a, b = rng.random((3, 70, 83)), rng.random((3, 70, 83))
    mask = rng.random((70, 83)) > 0.3
    ta, tb = torch.from_numpy(a)[None], torch.from_numpy(b)[None]
    got = float(net(ta, tb)[0])
    want = _lpips_numpy(a, b, arrays)
    assert got == pytest.approx(want, rel=1e-7) and want > 0
    got_m = float(net(ta, tb, torch.from_numpy(mask)[None])[0])
    assert got_m == pytest.approx(_lpips_numpy(a, b, arrays, mask.astype(float)), rel=1e-7)
    assert float(net(ta, ta)[0]) == 0.0
    assert float(net(tb, ta)[0]) == pytest.approx(got, rel=1e-12)


def test_bad_weight_files_give_one_clear_error(tmp_path):
    bb, lin, _ = _standin_files(tmp_path)
    with pytest.raises(InputError, match="no such file"):
        load_lpips(LPIPSConfig(backbone=str(tmp_path / "missing.pth"), linear=str(lin)))
    with pytest.raises(InputError, match=r"alex\.pth.*no key 'features\.0\.weight'"):
        load_lpips(LPIPSConfig(backbone=str(lin), linear=str(lin)))  # the files swapped
    sd = torch.load(lin, weights_only=True)
    sd["lin2.model.1.weight"] = torch.zeros(1, 100, 1, 1)
    torch.save(sd, tmp_path / "bad.pth")
    with pytest.raises(InputError, match=r"'lin2\.model\.1\.weight' is \(1, 100, 1, 1\), expected \(1, 384, 1, 1\)"):
        load_lpips(LPIPSConfig(backbone=str(bb), linear=str(tmp_path / "bad.pth")))
    # a pickle of anything but tensors is refused, not executed
    (tmp_path / "evil.pth").write_bytes(pickle.dumps(InputError("an arbitrary object"), protocol=2))
    with pytest.raises(InputError, match="not a tensor state dict"):
        load_lpips(LPIPSConfig(backbone=str(tmp_path / "evil.pth"), linear=str(lin)))
    with pytest.raises(InputError, match="expected two"):
        LPIPS()(torch.rand(1, 3, 32, 32), torch.rand(1, 3, 32, 31))


def test_the_appearance_loss_gains_the_term_only_when_configured(data, tmp_path):  # noqa: F811
    bb, lin, _ = _standin_files(tmp_path)
    stage = get_stage("appearance")
    item = stage.dataset(data, stage.data_config(**DATA), "val", 0)[0]
    torch.manual_seed(0)
    plain = AppearanceNet(stage.model_config(**MODEL))
    cfg = stage.model_config(**MODEL, lpips={"backbone": str(bb), "linear": str(lin), "weight": 0.6})
    with_lp = AppearanceNet(cfg)
    with_lp.load_state_dict(plain.state_dict())
    assert set(with_lp.state_dict()) == set(plain.state_dict())  # the LPIPS weights stay out of checkpoints
    out = plain(item)
    base, logs = view_losses(plain, out, item, views=[(0, 0)])
    total, logs_lp = view_losses(with_lp, out, item, views=[(0, 0)])
    assert "lpips" not in logs and logs_lp["lpips"] > 0
    assert float((total - base).detach()) == pytest.approx(0.6 * logs_lp["lpips"], rel=1e-5)
    total.backward()
    assert plain.unet.parameters().__next__().grad is not None  # gradients reach the network
    assert all(p.grad is None for p in with_lp.lpips().parameters())  # and never the frozen LPIPS
    with torch.no_grad():
        metrics = evaluate_item(with_lp, item)
        assert "lpips_t0" in metrics and "lpips_t0" not in evaluate_item(plain, item)
