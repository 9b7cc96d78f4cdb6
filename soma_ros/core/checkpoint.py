"""Simulator checkpoints: one file that rebuilds the whole :class:`~.simulator.Simulator`.

A checkpoint is a ``torch.save`` of a plain dict (loadable with
``torch.load(weights_only=True)``: tensors, lists, dicts, strings, numbers):

=================  ===================================================================
key                content
=================  ===================================================================
format             "soma_ros.simulator/1"
soma_ros_version   package version that wrote it
model_config       :meth:`ModelConfig.to_dict` (hierarchy, graph, gnn, dynamics,
                   normalizer sections and the effect list with parameters, including
                   effects added after construction)
state_dict         all parameters and buffers (network, effects, per-splat attributes,
                   normaliser statistics)
hierarchy          :meth:`Hierarchy.to_dict` (parents, rest positions, masses,
                   thresholds) or None if the model was never bound
graphs             :meth:`LevelGraphs.to_dict` (static edges) or None
extra              caller's dict (training step, dataset name, metrics, ...)
checksum           "sha256:<hex>" of the content above (:func:`content_checksum`)
=================  ===================================================================

Every load verifies the checksum (:func:`read_checkpoint`): a file with flipped
bytes that torch still unpickles is refused with a one-line error naming it.
A file without a checksum (an older format) loads with a warning that it was not
verified. Training states (``train_state.pt``) carry the same checksum;
:func:`save_train_state` keeps the previous state beside the new one and
:func:`load_train_state` falls back to it, saying so, when the newest is
unreadable.

:func:`save_checkpoint` is atomic: it writes a temporary file in the target
folder, fsyncs it and ``os.replace`` s it over the target, so a reader never
sees a partial file and a crash leaves the previous checkpoint intact.
"""

from __future__ import annotations

import hashlib
import os
import tempfile
import warnings
from pathlib import Path
from typing import Any, Optional, Union

import torch

from soma_ros import __version__

from .config import ModelConfig
from .graph import LevelGraphs
from .hierarchy import Hierarchy
from .simulator import Simulator

__all__ = ["CHECKPOINT_FORMAT", "save_checkpoint", "load_checkpoint", "read_checkpoint", "check_checkpoint_payload",
           "simulator_from_payload", "content_checksum", "verify_checksum",
           "save_train_state", "load_train_state", "previous_state_path"]

CHECKPOINT_FORMAT = "soma_ros.simulator/1"
_SAFE_SCALARS = (str, int, float, bool, type(None))


def _check_safe(value: Any, where: str) -> None:
    """Raise TypeError unless ``value`` loads with ``torch.load(weights_only=True)``."""
    if isinstance(value, _SAFE_SCALARS) or isinstance(value, torch.Tensor):
        return
    if isinstance(value, (list, tuple)):
        for i, v in enumerate(value):
            _check_safe(v, f"{where}[{i}]")
        return
    if isinstance(value, dict):
        for k, v in value.items():
            if not isinstance(k, (str, int)):
                raise TypeError(f"{where}: dict keys must be str or int, got {type(k).__name__}")
            _check_safe(v, f"{where}.{k}")
        return
    raise TypeError(
        f"{where}: {type(value).__name__} cannot go into a checkpoint (use tensors, lists, dicts, str, numbers)"
    )


def _hash_into(h, value: Any) -> None:
    if isinstance(value, torch.Tensor):
        t = value.detach().cpu().contiguous().reshape(-1)
        h.update(f"t{t.dtype}{tuple(value.shape)}".encode())
        if t.numel():
            h.update(t.view(torch.uint8).numpy())
    elif isinstance(value, dict):
        h.update(f"d{len(value)}".encode())
        for k in sorted(value, key=lambda k: (type(k).__name__, str(k))):
            h.update(f"k{type(k).__name__}:{k}".encode())
            _hash_into(h, value[k])
    elif isinstance(value, (list, tuple)):
        h.update(f"l{len(value)}".encode())
        for v in value:
            _hash_into(h, v)
    else:
        h.update(f"s{type(value).__name__}:{value!r}".encode())


def content_checksum(payload: dict) -> str:
    """"sha256:<hex>" over everything in ``payload`` except its "checksum" key: keys, tensor
    dtypes, shapes and bytes, and the other values (the loaded content, not the file bytes, so it
    does not depend on how torch laid out the archive)."""
    h = hashlib.sha256()
    _hash_into(h, {k: v for k, v in payload.items() if k != "checksum"})
    return "sha256:" + h.hexdigest()


def verify_checksum(payload: dict, path: Union[str, Path], what: str) -> None:
    """Check ``payload`` (as loaded from ``path``) against its stored "checksum": a ValueError naming
    the file when they differ; a warning (not an error) for a file written without one."""
    stored = payload.get("checksum")
    if stored is None:
        warnings.warn(f"{path}: {what} written without a content checksum; its content is not verified",
                      stacklevel=3)
        return
    if content_checksum(payload) != stored:
        raise ValueError(f"{path}: {what} is corrupt (its content does not match its SHA-256 checksum)")


def _torch_load(path: Path, map_location, what: str) -> Any:
    try:
        return torch.load(path, map_location=map_location, weights_only=True)
    except Exception as exc:  # corrupted / truncated / not a torch file / unsafe content
        msg = str(exc).strip().splitlines()[0][:160] if str(exc).strip() else ""
        raise ValueError(f"{path}: not a readable {what} ({type(exc).__name__}{': ' + msg if msg else ''})") from None


def atomic_torch_save(obj: Any, path: Union[str, Path]) -> None:
    """torch.save to a temp file in the same folder, fsync, then os.replace: readers see the
    old file or the new one, never a partial one (also after a kill)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            torch.save(obj, f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise


def save_checkpoint(path: Union[str, Path], simulator: Simulator, extra: Optional[dict] = None) -> Path:
    """Write ``simulator`` (config, weights, normalisers, hierarchy, effects) to ``path`` atomically."""
    path = Path(path)
    extra = dict(extra or {})
    _check_safe(extra, "extra")
    cfg = simulator.config
    cfg.effects = simulator.effects.specs
    payload = {
        "format": CHECKPOINT_FORMAT,
        "soma_ros_version": __version__,
        "model_config": cfg.to_dict(),
        "state_dict": {k: v.detach().cpu().clone() for k, v in simulator.state_dict().items()},
        "hierarchy": simulator.hierarchy.to_dict() if simulator.hierarchy is not None else None,
        "graphs": simulator.graphs.to_dict() if simulator.graphs is not None else None,
        "extra": extra,
    }
    payload["checksum"] = content_checksum(payload)
    atomic_torch_save(payload, path)
    try:  # make the rename durable
        dfd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)
    except OSError:  # pragma: no cover - e.g. file systems without directory fsync
        pass
    return path


def read_checkpoint(path: Union[str, Path], map_location: Union[str, torch.device] = "cpu") -> dict:
    """The raw checkpoint dict (validated format), loaded with ``weights_only=True``."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint not found: {path}")
    payload = _torch_load(path, map_location, "soma_ros checkpoint")
    check_checkpoint_payload(payload, path)
    return payload


def check_checkpoint_payload(payload: Any, path: Union[str, Path]) -> None:
    """Validate a dict loaded from ``path`` as a simulator checkpoint: its format, its keys and its
    content checksum (a ValueError naming the file)."""
    if not isinstance(payload, dict) or payload.get("format") != CHECKPOINT_FORMAT:
        fmt = payload.get("format") if isinstance(payload, dict) else type(payload).__name__
        raise ValueError(f"{path}: not a soma_ros simulator checkpoint (format {fmt!r}, expected {CHECKPOINT_FORMAT!r})")
    for key in ("model_config", "state_dict", "hierarchy", "graphs", "extra"):
        if key not in payload:
            raise ValueError(f"{path}: checkpoint misses {key!r}")
    verify_checksum(payload, path, "checkpoint")


def load_checkpoint(path: Union[str, Path], map_location: Union[str, torch.device] = "cpu") -> Simulator:
    """Rebuild the :class:`Simulator` saved by :func:`save_checkpoint` (only the file is needed).

    The extra dict is available as ``simulator.checkpoint_extra``.
    """
    return simulator_from_payload(read_checkpoint(path, map_location), path, map_location)


def simulator_from_payload(payload: dict, path: Union[str, Path],
                           map_location: Union[str, torch.device] = "cpu") -> Simulator:
    """The :class:`Simulator` of a checkpoint dict already read and checked
    (:func:`read_checkpoint` or :func:`check_checkpoint_payload`); ``path`` names it in errors."""
    cfg = ModelConfig.from_dict(payload["model_config"], f"{Path(path).name}: model_config.")
    sim = Simulator(cfg)
    state = payload["state_dict"]
    if payload["hierarchy"] is not None:
        hier = Hierarchy.from_dict(payload["hierarchy"])
        graphs = LevelGraphs.from_dict(payload["graphs"]) if payload["graphs"] is not None else None
        sim.bind_hierarchy(hier, graphs)
    missing, unexpected = sim.load_state_dict(state, strict=False)
    # an effect parameter added after the checkpoint was written (gripper_slip's weaken) keeps the
    # value its spec gives it (the term's default: no change); anything else missing is an error
    added = sorted(k for k in missing if k.startswith("effects.terms."))
    if added:
        warnings.warn(f"{path}: effect parameters not in the checkpoint keep their config values: {added}",
                      stacklevel=2)
        missing = [k for k in missing if k not in added]
    if missing or unexpected:
        raise ValueError(
            f"{path}: checkpoint does not match its model config (missing {sorted(missing)[:5]}, "
            f"unexpected {sorted(unexpected)[:5]})"
        )
    sim.to(map_location)
    sim.checkpoint_extra = payload["extra"]
    return sim


# ------------------------------------------------------------------ training state
def previous_state_path(path: Union[str, Path]) -> Path:
    """Where :func:`save_train_state` keeps the state it replaces (``train_state.prev.pt``)."""
    path = Path(path)
    return path.with_name(f"{path.stem}.prev{path.suffix}")


def save_train_state(payload: dict, path: Union[str, Path]) -> Path:
    """Write a training state with its content checksum; the state it replaces is kept at
    :func:`previous_state_path`. Each file is written whole or not at all, so after a crash
    at any point at least one complete state remains."""
    path = Path(path)
    payload = dict(payload)
    payload["checksum"] = content_checksum(payload)
    tmp = path.with_name(f".{path.name}.new")
    atomic_torch_save(payload, tmp)
    if path.is_file():
        os.replace(path, previous_state_path(path))
    os.replace(tmp, path)
    return path


def load_train_state(path: Union[str, Path], fmt: str, log=print) -> Optional[dict]:
    """The newest readable training state: ``path`` (checksum verified, ``format == fmt``), else
    the previous one (saying so through ``log``); None when neither file exists. A ValueError
    names both files when neither can be read."""
    path = Path(path)
    prev = previous_state_path(path)
    errors = []
    for p in (path, prev):
        if not p.is_file():
            if p == path and prev.is_file():
                errors.append(f"{path}: missing")
            continue
        try:
            payload = _torch_load(p, "cpu", "training state")
            if not isinstance(payload, dict) or payload.get("format") != fmt:
                raise ValueError(f"{p}: not a soma_ros training state (expected format {fmt!r})")
            verify_checksum(payload, p, "training state")
        except ValueError as exc:
            errors.append(str(exc))
            continue
        if p != path:
            log(f"{errors[0]}; resuming from the previous training state {p.name} "
                f"(iteration {payload.get('iteration')})")
        return payload
    if errors:
        raise ValueError(f"no readable training state to resume from: {'; '.join(errors)} "
                         "(remove them, or use another --out, to start afresh)")
    return None
