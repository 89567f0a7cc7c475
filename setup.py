"""ament_python package: `colcon build` on a ROS 2 Jazzy robot, or `pip install .` anywhere."""
from glob import glob

from setuptools import find_packages, setup

PACKAGE = "senfunet_ros"

setup(
    name=PACKAGE,
    version="0.1.0",
    description="Online learned two-sensor depth fusion (SenFuNet) as a ROS 2 node",
    packages=find_packages(include=["senfunet_core", "senfunet_core.*", "senfunet_ros", "senfunet_ros.*"]),
    package_data={"senfunet_core": ["weights/*.pt", "weights/*.int8.json"], "senfunet_ros": ["fastdds_profile.xml"]},
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", glob("config/*.yaml") + glob("config/*.rviz")),
        (f"share/{PACKAGE}/launch", glob("launch/*.py")),
    ],
    # everything the code imports but ROS 2 (pinned versions: requirements.txt; the ROS 2 packages come from
    # the ROS install or the ros-jazzy-* wheels); test/ros/test_packaging.py checks the list
    install_requires=["numpy", "scipy", "numba", "llvmlite", "scikit-image", "pyyaml", "ruamel.yaml", "tqdm", "torch",
                      "rosbags", "mcap", "zstandard", "opencv-python-headless", "matplotlib", "pillow"],
    python_requires=">=3.11",  # the pinned numpy, scipy and scikit-image need it
    zip_safe=False,
    entry_points={
        "console_scripts": [
            "senfunet = senfunet_ros.cli:main",
            "fusion_node = senfunet_ros.node:main",
        ],
    },
)
