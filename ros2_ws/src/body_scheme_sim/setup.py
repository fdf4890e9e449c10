from setuptools import find_packages, setup

package_name = "body_scheme_sim"

setup(
    name=package_name,
    version="0.1.0",
    description="pybullet arm simulator seen by a fixed camera, with fault injection and ground truth.",
    license="Apache-2.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    entry_points={"console_scripts": []},
)
