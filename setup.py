"""ament_python package: `colcon build` on a ROS 2 Jazzy robot, or `pip install .` anywhere."""
from glob import glob

from setuptools import find_packages, setup

PACKAGE = "senfunet_ros"

setup(
    name=PACKAGE,
    version="0.1.0",
    description="Online learned two-sensor depth fusion (SenFuNet) as a ROS 2 node",
    packages=find_packages(include=["senfunet_core", "senfunet_core.*", "senfunet_ros", "senfunet_ros.*"]),
    package_data={"senfunet_core": ["weights/*.pt"], "senfunet_ros": ["fastdds_profile.xml"]},
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", glob("config/*.yaml")),
        (f"share/{PACKAGE}/launch", glob("launch/*.py")),
    ],
    install_requires=["numpy", "scipy", "numba", "scikit-image", "pyyaml", "tqdm"],
    python_requires=">=3.10",
    zip_safe=False,
    entry_points={
        "console_scripts": [
            "senfunet = senfunet_ros.cli:main",
            "fusion_node = senfunet_ros.node:main",
        ],
    },
)
