"""ament_python packaging for jointfit (also a plain setuptools package for pip users)."""

from glob import glob

from setuptools import find_packages, setup

package_name = "jointfit"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test", "test.*", "bench", "bench.*"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/config", glob("config/*.yaml")),
        ("share/" + package_name + "/config/two_subjects", glob("config/two_subjects/*.yaml")),
    ],
    # ROS packages (rclpy, *_msgs) are not pip dependencies: colcon users get
    # them from their ROS install, pip users who want them install the
    # ros-jazzy-* wheels listed in requirements.txt.
    install_requires=["numpy", "scipy", "pyyaml"],
    extras_require={
        "c3d": ["ezc3d"],
        "bag": ["rosbags"],
        "plot": ["matplotlib"],
    },
    python_requires=">=3.10",
    zip_safe=True,
    maintainer="jointfit developers",
    maintainer_email="dev@jointfit.invalid",
    description="Joint centre and axis estimation from motion-capture markers, with a ROS 2 adapter.",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "jointfit_node = jointfit_ros.node:main",
            "jointfit_fake_mocap = jointfit_ros.fake_mocap:main",
            "jointfit_replay = jointfit_ros.replay:main",
            "jointfit = jointfit_ros.cli:main",
        ],
    },
)
