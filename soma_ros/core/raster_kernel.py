"""Compiled CPU rasterizer: build, load and call the C++ kernels of ``kernels/raster.cpp``.

The kernels implement the same per-pixel rule as the pure-torch reference of
:mod:`soma_ros.core.render_raster` (which stays the reference and the
fallback): EWA projection, tile binning and front-to-back compositing,
with analytic backward kernels for the projection and the compositing.
:func:`soma_ros.core.render.render` uses them on CPU float32/float64 tensors
when ``RenderConfig.raster`` is ``"auto"`` (the default) or ``"compiled"``.

Build
-----
The source is one C++17 file with a plain C ABI (no torch headers); it is
compiled with ``g++`` (or ``$CXX``) into a shared library in a cache folder,
``$SOMA_KERNEL_DIR`` or ``$XDG_CACHE_HOME/soma_ros/kernels`` (default
``~/.cache/soma_ros/kernels``), named by a hash of the source, the compiler
flags, the compiler and the CPU, so a changed source or another machine gets
its own build. ``python -m soma_ros.core.raster_kernel --build`` builds it
(``make setup`` does); otherwise the first render builds it (about 5 s). When
no compiler is found or the build fails, one warning line says so and the
renderer uses the torch reference.

Calls go through :mod:`ctypes`, which releases the GIL for the duration of
each kernel call: a render in one thread does not block Python in another.
The kernels are single-threaded (one compute thread per process).

Set ``SOMA_RASTER=torch`` to never build or load the library.
"""

from __future__ import annotations

import argparse
import ctypes
import functools
import hashlib
import logging
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import threading
from pathlib import Path
from typing import Optional

import torch

__all__ = ["available", "load", "build", "kernel_path", "unavailable_reason", "project", "bin_splats",
           "composite", "KernelPlan"]

_LOG = logging.getLogger(__name__)
_SRC = Path(__file__).with_name("kernels") / "raster.cpp"
# -fno-trapping-math and -fopenmp-simd let g++ vectorise the per-tile pixel loops
# (branch-free selects and reductions); -march=native is dropped when unsupported.
_FLAGS = ["-O3", "-std=c++17", "-fPIC", "-shared", "-fno-math-errno", "-fno-trapping-math", "-fopenmp-simd"]
_ARCH = ["-march=native"]
_ABI = 2

_c_i64 = ctypes.c_int64
_c_ptr = ctypes.c_void_p


def _cxx() -> Optional[str]:
    return shutil.which(os.environ.get("CXX", "g++"))


def _cpu_id() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith(("model name", "flags")):
                    return line.strip()
    except OSError:
        pass
    return platform.processor()


def _cache_dir() -> Path:
    env = os.environ.get("SOMA_KERNEL_DIR")
    if env:
        return Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "soma_ros" / "kernels"


def _compiler_env() -> dict:
    """The environment for the compiler: this one without LD_PRELOAD (meant for Python, not g++)."""
    return {k: v for k, v in os.environ.items() if k != "LD_PRELOAD"}


def _compiler_version(cxx: str) -> str:
    try:
        return subprocess.run([cxx, "--version"], capture_output=True, text=True, timeout=30,
                              env=_compiler_env()).stdout
    except (OSError, subprocess.SubprocessError):
        return ""


@functools.lru_cache(maxsize=1)
def kernel_path() -> Path:
    """Where the shared library for this source, compiler and CPU lives (may not exist yet)."""
    cxx = _cxx() or ""
    h = hashlib.sha256()
    for part in (_SRC.read_bytes(), " ".join(_FLAGS + _ARCH).encode(), _compiler_version(cxx).encode(),
                 platform.machine().encode(), _cpu_id().encode()):
        h.update(part)
        h.update(b"\0")
    return _cache_dir() / f"soma_raster-{h.hexdigest()[:16]}.so"


def build(force: bool = False) -> Path:
    """Compile the kernels into :func:`kernel_path` (atomic; safe with concurrent builders).

    Raises RuntimeError with a one-line reason when no compiler is found or g++ fails.
    """
    out = kernel_path()
    if out.exists() and not force:
        return out
    cxx = _cxx()
    if cxx is None:
        raise RuntimeError(f"no C++ compiler ({os.environ.get('CXX', 'g++')}) on PATH")
    out.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=out.stem + ".", suffix=".tmp", dir=out.parent)
    os.close(fd)
    try:
        env = _compiler_env()
        res = subprocess.run([cxx, *_FLAGS, *_ARCH, "-o", tmp, str(_SRC)], capture_output=True, text=True,
                             timeout=600, env=env)
        if res.returncode != 0:  # e.g. a compiler without -march=native
            res = subprocess.run([cxx, *_FLAGS, "-o", tmp, str(_SRC)], capture_output=True, text=True, timeout=600,
                                 env=env)
        if res.returncode != 0:
            first = (res.stderr.strip().splitlines() or ["(no output)"])[0]
            raise RuntimeError(f"{cxx} failed on {_SRC.name}: {first}")
        os.replace(tmp, out)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return out


def _declare(lib: ctypes.CDLL) -> None:
    for suf, real in (("f32", ctypes.c_float), ("f64", ctypes.c_double)):
        f = getattr(lib, f"soma_project_{suf}")
        f.restype = _c_i64
        f.argtypes = [_c_i64, _c_i64] + [_c_ptr] * 5 + [_c_i64, _c_i64] + [real] * 5 + [ctypes.c_int] \
            + [_c_ptr] * 9
        f = getattr(lib, f"soma_project_bwd_{suf}")
        f.restype = None
        f.argtypes = [_c_i64] + [_c_ptr] * 6 + [_c_i64, _c_i64, ctypes.c_int] + [_c_ptr] * 8
        f = getattr(lib, f"soma_bin_count_{suf}")
        f.restype = _c_i64
        f.argtypes = [_c_i64] + [_c_ptr] * 6 + [_c_i64] * 4 + [_c_ptr] * 3
        f = getattr(lib, f"soma_bin_fill_{suf}")
        f.restype = None
        f.argtypes = [_c_i64] + [_c_ptr] * 4 + [_c_i64] * 4 + [_c_ptr] * 5
        f = getattr(lib, f"soma_composite_fwd_{suf}")
        f.restype = None
        f.argtypes = [_c_i64, _c_i64] + [_c_ptr] * 5 + [_c_i64] * 4 + [_c_ptr] * 2 + [real] * 2 + [_c_ptr] * 3
        f = getattr(lib, f"soma_composite_bwd_{suf}")
        f.restype = None
        f.argtypes = [_c_i64, _c_i64] + [_c_ptr] * 5 + [_c_i64] * 4 + [_c_ptr] * 2 + [real] + [_c_ptr] * 4
    lib.soma_raster_abi_version.restype = ctypes.c_int
    if lib.soma_raster_abi_version() != _ABI:
        raise RuntimeError(f"kernel ABI {lib.soma_raster_abi_version()} != {_ABI}")


_state: dict = {}
_load_lock = threading.Lock()


def load() -> Optional[ctypes.CDLL]:
    """The loaded kernel library, building it when missing; None (and one warning) when unavailable."""
    if "lib" in _state:
        return _state["lib"]
    with _load_lock:
        if "lib" not in _state:
            _load()
    return _state["lib"]


def _load() -> None:
    lib, reason = None, None
    if os.environ.get("SOMA_RASTER", "").lower() == "torch":
        reason = "SOMA_RASTER=torch"
    else:
        try:
            lib = ctypes.CDLL(str(build()))
            _declare(lib)
        except (OSError, RuntimeError, AttributeError, subprocess.SubprocessError) as e:
            lib, reason = None, str(e).splitlines()[0] if str(e) else type(e).__name__
    _state["reason"] = reason
    _state["lib"] = lib
    if lib is None and reason != "SOMA_RASTER=torch":
        _LOG.warning("compiled CPU rasterizer unavailable (%s); rendering with the pure-torch reference", reason)


def available() -> bool:
    """True when the compiled kernels load (builds them on first call)."""
    return load() is not None


def unavailable_reason() -> Optional[str]:
    load()
    return _state.get("reason")


def _lib() -> ctypes.CDLL:
    lib = load()
    if lib is None:
        raise ImportError(f"compiled CPU rasterizer unavailable: {_state.get('reason')}")
    return lib


def _suffix(dtype: torch.dtype) -> str:
    if dtype == torch.float32:
        return "f32"
    if dtype == torch.float64:
        return "f64"
    raise TypeError(f"compiled rasterizer supports float32/float64, got {dtype}")


def _ptr(t: torch.Tensor) -> int:
    return t.data_ptr()


def _c(t: torch.Tensor, dtype=None) -> torch.Tensor:
    """Detached, contiguous CPU tensor (optionally cast)."""
    t = t.detach()
    if dtype is not None and t.dtype != dtype:
        t = t.to(dtype)
    return t.contiguous()


# ----------------------------------------------------------------- projection
@torch.no_grad()
def _project_raw(means, covs, opacities, w2c, Km, width: int, height: int, cfg):
    """One call of the projection kernel on contiguous tensors -> the V rows of every output."""
    dt = means.dtype
    N, C = means.shape[0], w2c.shape[0]
    R = C * N
    cam = torch.empty(R, dtype=torch.long)
    sidx = torch.empty(R, dtype=torch.long)
    mean2d = torch.empty(R, 2, dtype=dt)
    conic = torch.empty(R, 3, dtype=dt)
    cov2d = torch.empty(R, 3, dtype=dt)
    depth, op, smin, pmax = (torch.empty(R, dtype=dt) for _ in range(4))
    V = getattr(_lib(), f"soma_project_{_suffix(dt)}")(
        N, C, _ptr(means), _ptr(covs), _ptr(opacities), _ptr(w2c), _ptr(Km), width, height,
        cfg.near_plane, cfg.far_plane, cfg.eps2d, cfg.sigma_cutoff, cfg.alpha_min, int(cfg.clamp_jacobian),
        _ptr(cam), _ptr(sidx), _ptr(mean2d), _ptr(conic), _ptr(cov2d), _ptr(depth), _ptr(op), _ptr(smin),
        _ptr(pmax))
    return tuple(t[:V] for t in (cam, sidx, mean2d, conic, cov2d, depth, op, smin, pmax))


class _ProjectKernelFn(torch.autograd.Function):
    """Differentiable in means, covs and opacities through mean2d, conic, depth and opacity."""

    @staticmethod
    def forward(ctx, means, covs, opacities, w2c, Km, width, height, cfg):
        means, covs = _c(means), _c(covs)
        out = _project_raw(means, covs, _c(opacities), w2c, Km, width, height, cfg)
        cam, sidx, mean2d, conic, cov2d, depth, op, smin, pmax = out
        ctx.mark_non_differentiable(cam, sidx, cov2d, smin, pmax)
        ctx.save_for_backward(means, covs, w2c, Km, cam, sidx, conic)
        ctx.dims = (opacities.shape[0], width, height, int(cfg.clamp_jacobian))
        return out

    @staticmethod
    def backward(ctx, _gc, _gs, g_mean2d, g_conic, _gcov, g_depth, g_op, _gsm, _gpm):
        means, covs, w2c, Km, cam, sidx, conic = ctx.saved_tensors
        N, W, H, clamp = ctx.dims
        dt = means.dtype
        g_means = torch.zeros(N, 3, dtype=dt)
        g_covs = torch.zeros(N, 3, 3, dtype=dt)
        g_opac = torch.zeros(N, dtype=dt)
        gm, gc, gd, go = (_c(t, dt) for t in (g_mean2d, g_conic, g_depth, g_op))
        getattr(_lib(), f"soma_project_bwd_{_suffix(dt)}")(
            cam.shape[0], _ptr(cam), _ptr(sidx), _ptr(means), _ptr(covs), _ptr(w2c), _ptr(Km), W, H, clamp,
            _ptr(conic), _ptr(gm), _ptr(gc), _ptr(gd), _ptr(go), _ptr(g_means), _ptr(g_covs), _ptr(g_opac))
        need = ctx.needs_input_grad
        return (g_means if need[0] else None, g_covs if need[1] else None, g_opac if need[2] else None,
                None, None, None, None, None)


def project(means: torch.Tensor, covs: torch.Tensor, opacities: torch.Tensor, cameras, cfg):
    """EWA projection, the same result as ``render.project_gaussians``, differentiable in
    means, covs and opacities (through mean2d, conic, depth and opacity; cov2d, smin and
    pmax only select and carry no gradient, as in the reference).

    means [N, 3], covs [N, 3, 3], opacities [N] (CPU, float32/64) -> ``Projected`` with V rows.
    The cameras are constants: a camera that needs gradients goes through the reference.
    """
    from .render_raster import Projected

    dt = means.dtype
    N, C = means.shape[0], len(cameras)
    if tuple(means.shape) != (N, 3) or tuple(covs.shape) != (N, 3, 3) or tuple(opacities.shape) != (N,):
        raise ValueError(f"project: expected means [N,3], covs [N,3,3], opacities [N]; got "
                         f"{list(means.shape)}, {list(covs.shape)}, {list(opacities.shape)}")
    w2c = _c(cameras.world_to_cam.detach(), dt)
    Km = _c(cameras.K.detach(), dt)
    if tuple(w2c.shape) != (C, 4, 4) or tuple(Km.shape) != (C, 3, 3):
        raise ValueError(f"project: cameras need world_to_cam [C,4,4] and K [C,3,3], got "
                         f"{list(w2c.shape)}, {list(Km.shape)}")
    ins = (means, covs, opacities)
    if torch.is_grad_enabled() and any(t.requires_grad for t in ins):
        out = _ProjectKernelFn.apply(*ins, w2c, Km, cameras.width, cameras.height, cfg)
    else:
        out = _project_raw(*(_c(t) for t in ins), w2c, Km, cameras.width, cameras.height, cfg)
    cam, sidx, mean2d, conic, cov2d, depth, op, smin, pmax = out
    return Projected(cam_idx=cam, splat_idx=sidx, mean2d=mean2d, conic=conic, cov2d=cov2d, depth=depth,
                     opacity=op, smin=smin, pmax=pmax)


# ----------------------------------------------------------------- binning
class KernelPlan:
    """Per-tile, front-to-back splat lists of one render (no gradients)."""

    def __init__(self, n_cams, width, height, tile, offsets, isect):
        self.n_cams, self.width, self.height, self.tile = n_cams, width, height, tile
        self.offsets = offsets  # [n_tiles + 1] int32
        self.isect = isect  # [M] int32 visible-splat indices
        self.n_isect = int(isect.numel())


@torch.no_grad()
def bin_splats(mean2d, conic, cov2d, pmax, depth, cam_idx, n_cams: int, width: int, height: int,
               tile: int) -> KernelPlan:
    """Tile lists of V visible splats: mean2d [V,2], conic [V,3], cov2d [V,3], pmax/depth/cam_idx [V]."""
    V = mean2d.shape[0]
    for name, t, shape in (("mean2d", mean2d, (V, 2)), ("conic", conic, (V, 3)), ("cov2d", cov2d, (V, 3)),
                           ("pmax", pmax, (V,)), ("depth", depth, (V,)), ("cam_idx", cam_idx, (V,))):
        if tuple(t.shape) != shape:
            raise ValueError(f"bin_splats: {name} must be {list(shape)}, got {list(t.shape)}")
    dt = mean2d.dtype
    lib = _lib()
    suf = _suffix(dt)
    n_tiles = n_cams * ((width + tile - 1) // tile) * ((height + tile - 1) // tile)
    m, cn, cv, pm, dp = (_c(t, dt) for t in (mean2d, conic, cov2d, pmax, depth))
    cam = _c(cam_idx, torch.long)
    order = torch.empty(V, dtype=torch.int32)
    box = torch.empty(V, 4, dtype=torch.int32)
    counts = torch.zeros(n_tiles, dtype=torch.int32)
    M = getattr(lib, f"soma_bin_count_{suf}")(V, _ptr(m), _ptr(cn), _ptr(cv), _ptr(pm), _ptr(dp), _ptr(cam),
                                             n_cams, width, height, tile, _ptr(order), _ptr(box), _ptr(counts))
    if M >= 2**31:
        raise RuntimeError(f"bin_splats: {M} tile/splat intersections exceed the int32 index range")
    offsets = torch.empty(n_tiles + 1, dtype=torch.int32)
    isect = torch.empty(M, dtype=torch.int32)
    getattr(lib, f"soma_bin_fill_{suf}")(V, _ptr(m), _ptr(cn), _ptr(pm), _ptr(cam), n_cams, width, height, tile,
                                         _ptr(order), _ptr(box), _ptr(counts), _ptr(offsets), _ptr(isect))
    return KernelPlan(n_cams, width, height, tile, offsets, isect)


# ----------------------------------------------------------------- compositing
class _CompositeKernelFn(torch.autograd.Function):
    @staticmethod
    def forward(ctx, mean2d, conic, opac, feat, smin, plan, alpha_max, t_min):
        dt = mean2d.dtype
        lib = _lib()
        V, K = feat.shape
        C, H, W = plan.n_cams, plan.height, plan.width
        ins = [_c(t, dt) for t in (mean2d, conic, opac, feat, smin)]
        img = torch.empty(C, H, W, K, dtype=dt)
        t_final = torch.empty(C * H * W, dtype=dt)
        n_last = torch.empty(C * H * W, dtype=torch.int32)
        getattr(lib, f"soma_composite_fwd_{_suffix(dt)}")(
            V, K, *(_ptr(t) for t in ins), C, W, H, plan.tile, _ptr(plan.offsets), _ptr(plan.isect),
            alpha_max, t_min, _ptr(img), _ptr(t_final), _ptr(n_last))
        ctx.save_for_backward(*ins, t_final, n_last)
        ctx.plan = plan
        ctx.alpha_max = alpha_max
        return img

    @staticmethod
    def backward(ctx, grad_img):
        m, cn, op, feat, smin, t_final, n_last = ctx.saved_tensors
        plan = ctx.plan
        dt = m.dtype
        V, K = feat.shape
        g_img = _c(grad_img, dt)
        grad = torch.zeros(V, 6 + K, dtype=dt)
        getattr(_lib(), f"soma_composite_bwd_{_suffix(dt)}")(
            V, K, _ptr(m), _ptr(cn), _ptr(op), _ptr(feat), _ptr(smin), plan.n_cams, plan.width, plan.height,
            plan.tile, _ptr(plan.offsets), _ptr(plan.isect), ctx.alpha_max, _ptr(g_img), _ptr(t_final),
            _ptr(n_last), _ptr(grad))
        need = ctx.needs_input_grad
        return (grad[:, 0:2] if need[0] else None, grad[:, 2:5] if need[1] else None,
                grad[:, 5] if need[2] else None, grad[:, 6:] if need[3] else None,
                None, None, None, None)


def composite(mean2d, conic, opacity, feat, smin, plan: KernelPlan, alpha_max: float,
              transmittance_min: float) -> torch.Tensor:
    """Compiled counterpart of :func:`render_raster.composite`: ``[C, H, W, K]`` feature images.

    mean2d [V,2], conic [V,3], opacity [V], feat [V,K] (differentiable), smin [V] (not differentiated).
    """
    V = mean2d.shape[0]
    if mean2d.shape != (V, 2) or conic.shape != (V, 3) or opacity.shape != (V,) or feat.ndim != 2 \
            or feat.shape[0] != V or smin.shape != (V,):
        raise ValueError(
            f"composite: expected mean2d [V,2], conic [V,3], opacity [V], feat [V,K], smin [V]; got "
            f"{list(mean2d.shape)}, {list(conic.shape)}, {list(opacity.shape)}, {list(feat.shape)}, "
            f"{list(smin.shape)}")
    return _CompositeKernelFn.apply(mean2d, conic, opacity, feat, smin.detach(), plan, float(alpha_max),
                                    float(transmittance_min))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description="Build the compiled CPU rasterizer (soma_ros/core/kernels/raster.cpp).")
    ap.add_argument("--build", action="store_true", help="compile now (no-op when the current build exists)")
    ap.add_argument("--force", action="store_true", help="recompile even when a build exists")
    args = ap.parse_args(argv)
    if not (args.build or args.force):
        print(kernel_path())
        return 0
    try:
        path = build(force=args.force)
    except RuntimeError as e:
        print(f"compiled CPU rasterizer not built ({e}); the renderer will use the pure-torch reference",
              file=sys.stderr)
        return 0  # not fatal: the torch path is the fallback
    print(f"compiled CPU rasterizer: {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
