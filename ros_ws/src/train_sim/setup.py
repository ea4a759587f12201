"""ament_python package `train_sim`: pure simulator core + ROS 2 nodes."""

from glob import glob

from setuptools import find_packages, setup

PKG = "train_sim"

setup(
    name=PKG,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PKG}"]),
        (f"share/{PKG}", ["package.xml"]),
        (f"share/{PKG}/scenarios", glob("scenarios/*.yaml")),
        (f"share/{PKG}/config", glob("config/*.yaml")),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="Train estimation team",
    maintainer_email="dev@example.com",
    description="Train longitudinal-dynamics simulator, lossy radio link, zone-controller stub.",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "simulator = train_sim.nodes.simulator:main",
            "zone_controller = train_sim.nodes.zone_controller:main",
        ],
    },
)
