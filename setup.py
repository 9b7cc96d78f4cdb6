"""ament_python setup for soma_ros (also a plain pip-installable package)."""

import os
from glob import glob

from setuptools import find_packages, setup

PACKAGE = "soma_ros"


def tree(src: str, dest_root: str):
    """data_files entries that mirror folder `src` under `dest_root`."""
    out = {}
    for path in glob(os.path.join(src, "**", "*"), recursive=True):
        if os.path.isfile(path):
            rel_dir = os.path.relpath(os.path.dirname(path), src)
            out.setdefault(os.path.normpath(os.path.join(dest_root, rel_dir)), []).append(path)
    return sorted(out.items())


setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(include=["soma_ros", "soma_ros.*"]),
    package_data={PACKAGE: ["resources/robots/**/*", "core/kernels/*.cpp"]},
    include_package_data=True,
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        *tree("config", f"share/{PACKAGE}/config"),
    ],
    install_requires=["setuptools"],
    zip_safe=False,
    maintainer="soma_ros maintainers",
    maintainer_email="soma-ros@example.com",
    description="ROS 2 node suite for a learned real-to-sim soft-body manipulation simulator (SoMA).",
    license="Apache-2.0",
    python_requires=">=3.10",
    entry_points={
        "console_scripts": [
            "soma = soma_ros.cli:main",
            "soma_sim_node = soma_ros.nodes.sim_node:main",
            "soma_bag_player = soma_ros.nodes.bag_player:main",
            "soma_recorder = soma_ros.nodes.recorder:main",
        ],
    },
)
