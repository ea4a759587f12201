"""ament_python package `train_estimation`: pure estimator core + ROS 2 nodes and tools."""

from glob import glob

from setuptools import find_packages, setup

PKG = "train_estimation"

setup(
    name=PKG,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    package_data={PKG: ["tools/templates/*.j2"]},  # report.html's Jinja2 templates
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PKG}"]),
        (f"share/{PKG}", ["package.xml"]),
        (f"share/{PKG}/config", glob("config/*.yaml")),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="Train estimation team",
    maintainer_email="dev@example.com",
    description="Train state and braking-rate estimators, recorder and offline bag tools.",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "recorder = train_estimation.nodes.recorder:main",
            "robust_filter = train_estimation.nodes.robust_filter:main",
            "gsma_estimator = train_estimation.nodes.gsma_estimator:main",
            "check_bag = train_estimation.tools.check_bag:main",
            "identify = train_estimation.tools.identify:main",
            "diagnose = train_estimation.tools.diagnose:main",
            "fleet = train_estimation.tools.fleet:main",
            "csv2bag = train_estimation.tools.csv2bag:main",
        ],
    },
)
