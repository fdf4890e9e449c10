from glob import glob

from setuptools import find_packages, setup

package_name = "body_scheme_sim"

setup(
    name=package_name,
    version="0.1.0",
    description="pybullet arm simulator seen by a fixed camera, with fault injection and ground truth.",
    license="Apache-2.0",
    packages=find_packages(exclude=["test"]),
    # The robot files live in the Python package (found next to robots/__init__.py) and in share/ for ROS tools.
    package_data={package_name: ["robots/*.urdf", "robots/*.yaml"]},
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/robots", glob(package_name + "/robots/*.urdf")
         + glob(package_name + "/robots/*.yaml")),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
)
