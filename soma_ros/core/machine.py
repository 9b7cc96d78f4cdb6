"""The machine a figure was measured on, named the same way by every benchmark and report."""

from __future__ import annotations

import os
import platform
import sys

import torch

__all__ = ["cpu_model", "machine_description", "machine_info"]


def cpu_model() -> str:
    """The CPU's model name (Linux ``/proc/cpuinfo``), else what ``platform`` knows."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _gpu_name(device: str) -> str | None:
    if str(device).startswith("cuda") and torch.cuda.is_available():
        return torch.cuda.get_device_name(torch.device(device))
    return None


def machine_description(device: str = "cpu", torch_threads: int | None = None) -> str:
    """One line: CPU model | cores | torch version | torch threads | device (and its GPU's name).

    ``torch_threads`` names the threads of the process that was measured when that is not
    this one (a node the benchmark started); by default this process's own.
    """
    threads = torch.get_num_threads() if torch_threads is None else int(torch_threads)
    s = (f"{cpu_model()} | {os.cpu_count()} cores | torch {torch.__version__} | "
         f"torch threads {threads} | device {device}")
    gpu = _gpu_name(str(device))
    return s + (f" ({gpu})" if gpu else "")


def machine_info() -> dict:
    """The same as a JSON-able dict, with the platform and the Python version."""
    return {"cpu": cpu_model(), "platform": platform.platform(), "python": sys.version.split()[0],
            "torch": torch.__version__, "cpu_count": os.cpu_count(), "torch_threads": torch.get_num_threads(),
            "cuda": _gpu_name("cuda:0")}
