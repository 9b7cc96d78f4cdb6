"""Rendering in a child process, fed through shared memory, for the live node.

Why: the physics step is hundreds of small torch ops, and torch hands the GIL back
at every op; a render thread in the same process competes for it. A render in its own
process has its own interpreter and shares nothing but memory with the step. Measured
on a quiet 2-core AMD EPYC (13,000 splats, three 320x240 cameras,
``python -m benchmarks.bench_live --only rates --cameras 3``), it did not change the
node's sustained rates (24.9 steps/s and 10.0 image sets/s either way): the step's
wait inside the node is mostly not the render thread's. It is therefore off by default
(``render_process`` parameter of the node).

:class:`RenderProcess` owns one child process (nothing of the parent's threads, ROS
context or locks is inherited) and a set of shared tensors:

========== ================ ======================================
buffer     shape            written by
========== ================ ======================================
means      [N, 3]           parent, before each render
covs       [N, 3, 3]        parent, before each render
colors     [N, 3]           parent, when the scene changes
opacities  [N]              parent, when the scene changes
K          [C, 3, 3]        parent, before each render
w2c        [C, 4, 4]        parent, before each render
rgb        [C, H, W, 3] u8  child
depth      [C, H, W] f32    child
========== ================ ======================================

The child is ``python -m soma_ros.live_render``: a fresh interpreter that imports
only the renderer (not the parent's main module, whatever started the parent), with
the parent's environment. The buffers are files mapped by both processes
(``torch.from_file(..., shared=True)``) in ``/dev/shm`` where it exists; the parent
removes the files as soon as the child has mapped them, so nothing is left behind even
if both processes are killed.

One render is one request and one reply, JSON lines on the child's stdin and stdout:
the parent fills the inputs, sends ``{"op": "render"}`` and blocks on the reply (the
GIL is free meanwhile); the child renders with :func:`soma_ros.core.render.render` (the
same call the in-process path makes, so the images are the same to the last bit) and
answers ``{"ok": true, "cpu_ms": .., "wall_ms": ..}`` or ``{"ok": false, "error": ..}``.
Requests are strictly sequential, so no buffer is read while it is written. A new scene
(another splat count) maps new buffers.

The child ends at ``{"op": "stop"}``, or when its stdin closes (the parent died). A
child that dies or stops answering makes :meth:`RenderProcess.render` raise
:class:`RenderProcessError`; the node then renders in its own process.
"""

from __future__ import annotations

import json
import os
import select
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from .core.cameras import Cameras

__all__ = ["RenderProcess", "RenderProcessError", "RenderResult"]


class RenderProcessError(RuntimeError):
    """The render process failed, died or did not answer in time."""


@dataclass
class RenderResult:
    """One render of C cameras: views of the shared output buffers (valid until the next render)."""

    rgb: np.ndarray  # uint8 [C, H, W, 3]
    depth: np.ndarray  # float32 [C, H, W] metres, 0 where nothing was drawn (the renderer's rule)
    cpu_ms: float  # the child's CPU time for the render
    wall_ms: float  # the child's wall time for the render


_DTYPES = {"float32": torch.float32, "float64": torch.float64, "uint8": torch.uint8}


def _buffer_specs(n: int, cams: int, height: int, width: int, dtype: torch.dtype) -> dict:
    """name -> (shape, dtype) of the shared buffers (module docstring)."""
    return {"means": ((n, 3), dtype), "covs": ((n, 3, 3), dtype), "colors": ((n, 3), dtype),
            "opacities": ((n,), dtype), "K": ((cams, 3, 3), torch.float32), "w2c": ((cams, 4, 4), torch.float32),
            "rgb": ((cams, height, width, 3), torch.uint8), "depth": ((cams, height, width), torch.float32)}


def _map(path: str, shape: tuple, dtype: torch.dtype) -> torch.Tensor:
    numel = int(np.prod(shape)) if shape else 1
    return torch.from_file(path, shared=True, size=numel, dtype=dtype).view(*shape)


def _serve(inp, out) -> None:
    """The child's loop (module docstring): JSON requests on ``inp``, replies on ``out``."""
    from .core.render import render

    bufs: dict = {}
    meta: dict = {}
    for line in inp:
        try:
            req = json.loads(line)
            op = req.get("op")
            if op == "stop":
                return
            if op == "scene":
                dtype = _DTYPES[req["dtype"]]
                specs = _buffer_specs(req["n"], req["cams"], req["height"], req["width"], dtype)
                bufs = {k: _map(req["files"][k], shape, dt) for k, (shape, dt) in specs.items()}
                meta = {"width": req["width"], "height": req["height"]}
                reply = {"ok": True, "cpu_ms": 0.0, "wall_ms": 0.0}
            elif op == "render":
                if not bufs:
                    raise RuntimeError("render before any scene")
                t0, c0 = time.perf_counter(), time.thread_time()
                cams = Cameras(K=bufs["K"], world_to_cam=bufs["w2c"], width=meta["width"], height=meta["height"])
                with torch.no_grad():
                    r = render(bufs["means"], bufs["covs"], bufs["colors"], bufs["opacities"], cams,
                               background=torch.zeros(3, dtype=bufs["means"].dtype))
                    bufs["rgb"].copy_(r.rgb_u8())
                    bufs["depth"].copy_(r.depth.to(torch.float32))
                reply = {"ok": True, "cpu_ms": (time.thread_time() - c0) * 1e3,
                         "wall_ms": (time.perf_counter() - t0) * 1e3}
            else:
                reply = {"ok": False, "error": f"unknown request {op!r}"}
        except Exception as exc:  # noqa: BLE001 - reported to the parent, which falls back
            reply = {"ok": False, "error": f"{type(exc).__name__}: {exc}"}
        out.write(json.dumps(reply) + "\n")
        out.flush()


def main() -> int:
    """Entry of the child process: ``python -m soma_ros.live_render [--threads N]``."""
    threads = int(sys.argv[sys.argv.index("--threads") + 1]) if "--threads" in sys.argv else 1
    torch.set_num_threads(max(1, threads))
    # the protocol owns the original stdout; anything else written to fd 1 goes to stderr
    proto = os.fdopen(os.dup(1), "w", buffering=1)
    os.dup2(2, 1)
    _serve(sys.stdin, proto)
    return 0


class RenderProcess:
    """A render worker process for one camera rig (module docstring).

    Args:
        width, height: image size of every camera.
        num_cameras: C.
        dtype: the splats' float dtype (the state's): float32 or float64.
        torch_threads: the child's torch intra-op threads.
        timeout_s: how long one render may take before :class:`RenderProcessError`.
        startup_s: how long the child may take to start and map its first buffers.
    """

    def __init__(self, width: int, height: int, num_cameras: int, dtype: torch.dtype = torch.float32,
                 torch_threads: int = 1, timeout_s: float = 30.0, startup_s: float = 120.0) -> None:
        if width <= 0 or height <= 0 or num_cameras <= 0:
            raise ValueError(f"RenderProcess needs a positive size and camera count, got {width}x{height}, "
                             f"{num_cameras} cameras")
        names = {v: k for k, v in _DTYPES.items()}
        if dtype not in (torch.float32, torch.float64):
            raise ValueError(f"RenderProcess renders float32 or float64 splats, got {dtype}")
        self.width, self.height, self.num_cameras = int(width), int(height), int(num_cameras)
        self.dtype, self._dtype_name = dtype, names[dtype]
        self.timeout_s, self.startup_s = float(timeout_s), float(startup_s)
        self._n = -1
        self._bufs: dict = {}
        self._lock = threading.Lock()  # one request at a time, whichever thread asks
        self._shm = Path("/dev/shm") if Path("/dev/shm").is_dir() else None
        self._proc = subprocess.Popen([sys.executable, "-m", "soma_ros.live_render", "--threads", str(int(torch_threads))],
                                      stdin=subprocess.PIPE, stdout=subprocess.PIPE, bufsize=0)
        self._rbuf = b""
        self._closed = False

    @property
    def pid(self) -> int:
        return self._proc.pid

    def alive(self) -> bool:
        return not self._closed and self._proc.poll() is None

    def _ask(self, req: dict, timeout_s: float) -> dict:
        if not self.alive():
            raise RenderProcessError("the render process is not running")
        try:
            self._proc.stdin.write((json.dumps(req) + "\n").encode())
            fd = self._proc.stdout.fileno()
            deadline = time.monotonic() + timeout_s
            while b"\n" not in self._rbuf:
                left = deadline - time.monotonic()
                if left <= 0 or not select.select([fd], [], [], left)[0]:
                    raise RenderProcessError(f"the render process gave no answer in {timeout_s:g} s")
                chunk = os.read(fd, 65536)
                if not chunk:
                    raise RenderProcessError(f"the render process is gone (exit status {self._proc.wait(1.0)})")
                self._rbuf += chunk
        except (BrokenPipeError, OSError) as exc:
            raise RenderProcessError(f"the render process is gone ({type(exc).__name__})") from exc
        line, self._rbuf = self._rbuf.split(b"\n", 1)
        reply = json.loads(line)
        if not reply.get("ok"):
            raise RenderProcessError(f"render process: {reply.get('error')}")
        return reply

    def set_scene(self, colors: torch.Tensor, opacities: torch.Tensor) -> None:
        """The splats' colours [N, 3] and opacities [N]; new buffers when N changes."""
        if colors.ndim != 2 or colors.shape[1] != 3 or opacities.shape != (colors.shape[0],):
            raise ValueError(f"set_scene: colors must be [N, 3] and opacities [N], got {list(colors.shape)}, "
                             f"{list(opacities.shape)}")
        n = int(colors.shape[0])
        with self._lock:
            if n != self._n:
                specs = _buffer_specs(n, self.num_cameras, self.height, self.width, self.dtype)
                folder = Path(tempfile.mkdtemp(prefix="soma_render_", dir=self._shm))
                try:
                    files, bufs = {}, {}
                    for k, (shape, dt) in specs.items():
                        f = folder / k
                        nbytes = int(np.prod(shape)) * torch.empty((), dtype=dt).element_size()
                        with open(f, "wb") as fh:
                            fh.truncate(nbytes)
                        files[k], bufs[k] = str(f), _map(str(f), shape, dt)
                    self._ask({"op": "scene", "n": n, "cams": self.num_cameras, "height": self.height,
                               "width": self.width, "dtype": self._dtype_name, "files": files},
                              self.startup_s if self._n < 0 else self.timeout_s)
                finally:  # both processes hold their mappings; the files are not needed any more
                    for f in folder.iterdir():
                        f.unlink()
                    folder.rmdir()
                self._bufs, self._n = bufs, n
            self._bufs["colors"].copy_(colors.detach())
            self._bufs["opacities"].copy_(opacities.detach())

    def render(self, means: torch.Tensor, covs: torch.Tensor, cameras: Cameras) -> RenderResult:
        """Render the current splats [N, 3] / [N, 3, 3] into ``cameras`` (this rig's size)."""
        if cameras.width != self.width or cameras.height != self.height or len(cameras) != self.num_cameras:
            raise ValueError(f"render: cameras are {len(cameras)} x {cameras.width}x{cameras.height}, the process "
                             f"renders {self.num_cameras} x {self.width}x{self.height}")
        with self._lock:
            if means.shape != (self._n, 3) or covs.shape != (self._n, 3, 3):
                raise ValueError(f"render: expected means [{self._n}, 3] and covs [{self._n}, 3, 3] (set_scene), got "
                                 f"{list(means.shape)}, {list(covs.shape)}")
            b = self._bufs
            b["means"].copy_(means.detach())
            b["covs"].copy_(covs.detach())
            b["K"].copy_(cameras.K.detach())
            b["w2c"].copy_(cameras.world_to_cam.detach())
            r = self._ask({"op": "render"}, self.timeout_s)
            return RenderResult(rgb=b["rgb"].numpy(), depth=b["depth"].numpy(), cpu_ms=float(r["cpu_ms"]),
                                wall_ms=float(r["wall_ms"]))

    def close(self, timeout_s: float = 2.0) -> None:
        """Stop the child (politely, then by signal) and drop the buffers."""
        if self._closed:
            return
        self._closed = True
        try:
            self._proc.stdin.write(b'{"op": "stop"}\n')
            self._proc.stdin.close()
        except (BrokenPipeError, OSError):
            pass
        try:
            self._proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            self._proc.wait(timeout_s)
        self._proc.stdout.close()
        self._bufs = {}

    def __enter__(self) -> "RenderProcess":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


if __name__ == "__main__":
    sys.exit(main())
