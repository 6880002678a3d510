"""ament_python setup of the octolgp ROS 2 node (``colcon build`` runs it)."""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = "octolgp_ros"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml", "README.md"]),
        (f"share/{PACKAGE}/launch", glob("launch/*.launch.py")),
        (f"share/{PACKAGE}/config", glob("config/*.yaml")),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="octolgp developers",
    maintainer_email="octolgp@example.org",
    description="Continuous occupancy mapping with octolgp for ROS 2 and nav2",
    license="BSD-3-Clause",
    entry_points={"console_scripts": ["octolgp_mapper = octolgp_ros.mapper:main"]},
)
