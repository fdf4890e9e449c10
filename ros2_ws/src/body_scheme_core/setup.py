from setuptools import find_packages, setup

package_name = "body_scheme_core"

setup(
    name=package_name,
    version="0.1.0",
    description="Learning and maintaining a robot's body scheme from self-observation (Sturm et al., RSS 2008). "
    "Plain Python, no ROS.",
    license="Apache-2.0",
    python_requires=">=3.10",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
    ],
    install_requires=["numpy>=1.26", "scipy>=1.11", "networkx>=3.0", "PyYAML>=6", "tqdm>=4", "threadpoolctl>=3"],
    extras_require={"test": ["pytest>=7", "scikit-learn>=1.3"]},
    zip_safe=True,
)
