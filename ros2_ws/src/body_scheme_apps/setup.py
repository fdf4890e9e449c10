from glob import glob

from setuptools import find_packages, setup

package_name = "body_scheme_apps"

setup(
    name=package_name,
    version="0.1.0",
    description="Applications of the body scheme suite: the paper's experiments, demos, benchmarks, offline replay "
    "reports and session recording.",
    license="Apache-2.0",
    packages=find_packages(exclude=["test"]),
    package_data={"body_scheme_apps.experiments": ["data/*.urdf"]},
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/launch", glob("launch/*.launch.py")),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    entry_points={
        "console_scripts": [
            "experiments = body_scheme_apps.experiments.__main__:main",
            "live_demo = body_scheme_apps.live_demo:main",
            "core_demo = body_scheme_apps.core_demo:main",
            "record_session = body_scheme_apps.record:main",
            "replay_offline = body_scheme_apps.replay_offline:main",
            "learning_bench = body_scheme_apps.learning_bench:main",
            "perception_bench = body_scheme_apps.perception_bench:main",
            "load_bench = body_scheme_apps.load_bench:main",
            "calibrate = body_scheme_apps.calibrate:main",
            "fuzz = body_scheme_apps.fuzz:main",
            "other_stacks = body_scheme_apps.other_stacks:main",
        ],
    },
)
