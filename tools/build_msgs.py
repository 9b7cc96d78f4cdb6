#!/usr/bin/env python3
"""Build the soma_msgs interface package (msg_schemas/) into a Python venv
(and the vendored tf2_msgs TFMessage when the venv lacks tf2_msgs).

Runs with the venv's interpreter: `.venv/bin/python tools/build_msgs.py`.
Idempotent: it rewrites the ROS wheels' stale build-container include paths
(once), configures with plain CMake against the venv prefix, builds and
installs into the venv (libraries to <venv>/lib, the Python package to its
site-packages, the share/ files to <venv>/share). A stamp records the hash of
the interface files so a rebuild happens only when they change.
"""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
import sysconfig
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / "msg_schemas"
PREFIX = Path(sys.prefix)
STALE_PY_INCLUDE = "/opt/python/cp311-cp311/include/python3.11"
STALE_NUMPY_INCLUDE = "/opt/python/cp311-cp311/lib/python3.11/site-packages/numpy/_core/include"


def fix_stale_include_paths() -> int:
    """Point the message wheels' exported CMake targets at this venv's headers."""
    import numpy

    py_include = sysconfig.get_paths()["include"]
    np_include = numpy.get_include()
    changed = 0
    for f in (PREFIX / "share").glob("**/cmake/*.cmake"):
        text = f.read_text(errors="surrogateescape")
        if STALE_PY_INCLUDE in text or STALE_NUMPY_INCLUDE in text:
            text = text.replace(STALE_NUMPY_INCLUDE, np_include).replace(STALE_PY_INCLUDE, py_include)
            f.write_text(text, errors="surrogateescape")
            changed += 1
    return changed


def source_hash(src: Path) -> str:
    h = hashlib.sha256()
    for f in sorted(src.rglob("*")):
        if f.is_file() and "vendor" not in f.relative_to(src).parts[:1]:
            h.update(f.relative_to(src).as_posix().encode())
            h.update(f.read_bytes())
    h.update(str(PREFIX).encode())
    return h.hexdigest()


def have_module(name: str) -> bool:
    r = subprocess.run([sys.executable, "-c", f"import {name}"], capture_output=True)
    return r.returncode == 0


def main() -> int:
    n = fix_stale_include_paths()
    if n:
        print(f"interfaces: rewrote stale include paths in {n} CMake files of the venv")
    packages = []
    if not have_module("tf2_msgs"):
        packages.append(("tf2_msgs", SRC / "vendor" / "tf2_msgs"))
    packages.append(("soma_msgs", SRC))
    for name, src in packages:
        rc = build_package(name, src)
        if rc:
            return rc
    return 0


def build_package(name: str, src: Path) -> int:
    stamp = PREFIX / "share" / name / ".soma_build_stamp"
    digest = source_hash(src)
    if stamp.is_file() and stamp.read_text().strip() == digest:
        print(f"{name}: up to date")
        return 0
    build = ROOT / "build" / name
    env = dict(os.environ)
    env["AMENT_PREFIX_PATH"] = str(PREFIX)
    env["CMAKE_PREFIX_PATH"] = str(PREFIX)
    env["PATH"] = f"{PREFIX / 'bin'}{os.pathsep}{env.get('PATH', '')}"
    build.mkdir(parents=True, exist_ok=True)
    cfg = [
        "cmake", "-S", str(src), "-B", str(build),
        f"-DCMAKE_INSTALL_PREFIX={PREFIX}",
        f"-DCMAKE_PREFIX_PATH={PREFIX}",
        f"-DPython3_EXECUTABLE={sys.executable}",
        "-DBUILD_TESTING=OFF",
        "-DCMAKE_BUILD_TYPE=Release",
    ]
    for cmd in (cfg, ["cmake", "--build", str(build), "-j", str(os.cpu_count() or 2)], ["cmake", "--install", str(build)]):
        print("+", " ".join(cmd), flush=True)
        r = subprocess.run(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        if r.returncode != 0:
            print(r.stdout[-8000:])
            print(f"{name}: command failed ({r.returncode}): {' '.join(cmd)}", file=sys.stderr)
            return r.returncode
    stamp.write_text(digest + "\n")
    print(f"{name}: built and installed into {PREFIX}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
