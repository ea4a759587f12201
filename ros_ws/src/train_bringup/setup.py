"""ament_python package `train_bringup`: starts the whole system (the main job)."""

from setuptools import find_packages, setup

PKG = "train_bringup"

setup(
    name=PKG,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PKG}"]),
        (f"share/{PKG}", ["package.xml"]),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="Train estimation team",
    maintainer_email="dev@example.com",
    description="The main job: simulator, estimators, zone controller and recorder, then a report.",
    license="Apache-2.0",
    entry_points={"console_scripts": ["main_job = train_bringup.main_job:main"]},
)
