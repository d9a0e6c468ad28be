"""The optional test-time fit (`appearance.fit_steps`): the network's Gaussians and sky panorama
optimised on the input views with the training loss, Adam, one camera per step.
"""

from __future__ import annotations

import numpy as np
import torch

from ...errors import InputError
from ..nn.activations import OFFSET, OPACITY, QUAT, RGB, SCALE
from .losses import view_losses
from .net import AppearanceNet

# The test-time fit (`fit_input_views`): Adam rates per kind of raw value, in the raw layout's order, and
# for the panorama's features. Offsets are r * tanh(raw) with r one voxel, so 0.02 is about 3DGS's
# position rate for a 100 m scene (1.6e-4 x extent) at 0.4 m; colours are SH degree 0 (x 0.28).
FIT_RATES = {"offset": 0.02, "opacity": 0.05, "scale": 0.01, "quat": 0.005, "rgb": 0.02, "pano": 0.01}


_RAW_SLOTS = {"offset": OFFSET, "opacity": OPACITY, "scale": SCALE, "quat": QUAT, "rgb": RGB}


def fit_input_views(model: AppearanceNet, out: dict, item: dict, steps: int, on_step=None) -> dict:
    """Test-time fitting, after the network: its prediction `out` for `item` (made with the sky)
    optimised for `steps` Adam steps (`FIT_RATES`) on the item's own input views at T, one
    camera per step in order, with the training loss -> a prediction of the same form, without
    gradients. What moves is what the network outputs: every Gaussian's raw values and the
    panorama's features; the network (its sky decoder too) stays as it is. Not the paper's
    method (SCube is feed-forward): a speed/accuracy knob, off by default (0 steps).
    on_step(step, prediction) is called after each step (evaluation hooks)."""
    if isinstance(steps, bool) or not isinstance(steps, (int, np.integer)) or steps < 0:
        raise InputError(f"fit steps: expected an integer >= 0, got {steps!r}")
    if steps == 0:
        return out
    if out.get("pano") is None:
        raise InputError("fit_input_views: the prediction has no sky panorama (the loss composites the sky behind the "
                         "Gaussians); run the network with sky=True")
    parts = {k: out["raw"][..., s].detach().clone().requires_grad_(True) for k, s in _RAW_SLOTS.items()}
    pano = out["pano"].detach().clone().requires_grad_(True)
    leaves = [*parts.values(), pano]
    opt = torch.optim.Adam([{"params": [parts[k]], "lr": FIT_RATES[k]} for k in parts]
                           + [{"params": [pano], "lr": FIT_RATES["pano"]}])

    def current() -> dict:
        return {**model.splats(torch.cat(list(parts.values()), dim=-1), item), "pano": pano,
                "pano_weight": out.get("pano_weight")}

    n_views = item["images"].shape[0]
    for step in range(1, int(steps) + 1):
        with torch.enable_grad():
            loss, _ = view_losses(model, current(), item, views=[(0, (step - 1) % n_views)])
            # gradients for the prediction alone: the network's weights collect none
            for leaf, grad in zip(leaves, torch.autograd.grad(loss, leaves)):
                leaf.grad = grad
        opt.step()
        if on_step is not None:
            with torch.no_grad():
                on_step(step, current())
    with torch.no_grad():
        return {k: (v.detach() if torch.is_tensor(v) else v) for k, v in current().items()}


