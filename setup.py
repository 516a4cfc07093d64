"""Packaging glue that pyproject.toml cannot express: ship the repository's ``configs/`` folder inside the
installed package as ``harness.configs`` so a non-editable install finds the protocols and profiles."""

from setuptools import find_packages, setup

setup(
    packages=find_packages(include=["harness", "harness.*", "adapters", "adapters.*"]) + ["harness.configs"],
    package_dir={"harness.configs": "configs"},
    package_data={"harness.configs": ["*.yaml", "**/*.yaml"], "harness": ["py.typed"]},
)
