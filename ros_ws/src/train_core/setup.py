"""ament_python package `train_core`: what the simulator and the estimators share (no ROS in the
core: model records, YAML loading and validation, effects, actuator and train physics, the radio
link model, bag I/O, process helpers; `train_core.ros` is the one module for ROS nodes)."""

from glob import glob

from setuptools import find_packages, setup

PKG = "train_core"

setup(
    name=PKG,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PKG}"]),
        (f"share/{PKG}", ["package.xml"]),
        (f"share/{PKG}/config/lines", glob("config/lines/*.yaml")),
        (f"share/{PKG}/config/trains", glob("config/trains/*.yaml")),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="Train estimation team",
    maintainer_email="dev@example.com",
    description="Shared model, physics, configuration, bag I/O and node helpers.",
    license="Apache-2.0",
)
