from glob import glob

from setuptools import find_packages, setup

PACKAGE = "sma_stage"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test", "test.*"]),
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", sorted(glob("config/*.yaml") + glob("config/*_layout.*"))),
        (f"share/{PACKAGE}/launch", sorted(glob("launch/*.launch.py"))),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="sma_stage maintainers",
    maintainer_email="maintainers@example.com",
    description="SMA micro-positioning stage: simulator, GPI hysteresis compensation and identification.",
    license="Apache-2.0",
    python_requires=">=3.10",
    entry_points={
        "console_scripts": [
            "stage_node = sma_stage.nodes.stage_node:main",
            "compensator_node = sma_stage.nodes.compensator_node:main",
            "stage_and_compensator = sma_stage.nodes.stage_and_compensator:main",
            "identification_node = sma_stage.nodes.identification_node:main",
            "gpi_tool = sma_stage.cli:main",
        ],
    },
)
