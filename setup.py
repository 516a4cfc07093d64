"""Packaging glue that pyproject.toml cannot express: ship the repository's ``configs/`` folder inside the
installed package as ``harness.configs`` so a non-editable install finds the protocols and profiles, and the shipped
reference results (``references/``) as ``harness.shipped_references``."""

from setuptools import find_packages, setup

setup(
    packages=find_packages(include=["harness", "harness.*", "adapters", "adapters.*"])
    + ["harness.configs", "harness.shipped_references"],
    package_dir={"harness.configs": "configs", "harness.shipped_references": "references"},
    package_data={
        "harness.configs": ["*.yaml", "**/*.yaml"],
        "harness": ["py.typed"],
        "harness.shipped_references": ["**/*"],
    },
)
