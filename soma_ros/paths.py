"""Where the package's shipped data lives (robots, configs), installed or in a checkout."""

from __future__ import annotations

from pathlib import Path

PACKAGE_DIR = Path(__file__).resolve().parent
RESOURCES_DIR = PACKAGE_DIR / "resources"
ROBOTS_DIR = RESOURCES_DIR / "robots"


def config_dir() -> Path:
    """The `config/` folder: the checkout's, else the installed share/soma_ros/config."""
    here = PACKAGE_DIR.parent / "config"
    if here.is_dir():
        return here
    try:
        from ament_index_python.packages import get_package_share_directory  # type: ignore

        return Path(get_package_share_directory("soma_ros")) / "config"
    except Exception:  # pragma: no cover - only without a checkout and without ament
        pass
    import sys

    return Path(sys.prefix) / "share" / "soma_ros" / "config"


def resolve_config(path: str | Path) -> Path:
    """A config path as given, or relative to `config/` (with or without .yaml)."""
    p = Path(path)
    if p.is_file():
        return p
    for cand in (config_dir() / p, config_dir() / f"{p}.yaml"):
        if cand.is_file():
            return cand
    raise FileNotFoundError(f"config file not found: {path} (looked in . and {config_dir()})")
