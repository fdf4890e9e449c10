from glob import glob

from setuptools import find_packages, setup

package_name = "body_scheme_nodes"

setup(
    name=package_name,
    version="0.1.0",
    description="Thin rclpy nodes around body_scheme_core.",
    license="Apache-2.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/config", glob("config/*.yaml") + glob("config/*.rviz") + glob("config/*.json")),
        ("share/" + package_name + "/launch", glob("launch/*.launch.py")),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    entry_points={
        "console_scripts": [
            "scheme_node = body_scheme_nodes.scheme_node:main",
            "tracker_node = body_scheme_nodes.tracker_node:main",
            "control_node = body_scheme_nodes.control_node:main",
            "bag_replay = body_scheme_nodes.bag_replay:main",
            "sim_node = body_scheme_nodes.sim_node:main",
            "babble_node = body_scheme_nodes.babble_node:main",
            "body-scheme = body_scheme_nodes.cli:main",
        ],
    },
)
