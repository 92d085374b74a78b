"""Packaging glue that pyproject.toml cannot express: ship the top-level conf/ as ``torchsde_lti.conf``
(and the shipped filters of ``torchsde_lti.pretrained``, package data).

Everything else (metadata, dependencies) lives in pyproject.toml. The Hydra configs stay at the
top of the repository (design card); in a wheel they are the data package ``torchsde_lti.conf``
(YAML only), which the entry point finds as ``pkg://torchsde_lti.conf`` when no checkout's
conf/ sits next to the package.
"""

from setuptools import find_packages, setup

setup(
    packages=[*find_packages(include=["torchsde_lti", "torchsde_lti.*"]), "torchsde_lti.conf"],
    package_dir={"torchsde_lti.conf": "conf"},
    package_data={
        "torchsde_lti": ["py.typed"],  # PEP 561 marker
        "torchsde_lti.conf": ["*.yaml", "**/*.yaml"],
        "torchsde_lti.pretrained": ["files/*.json", "files/*.pt", "files/*.npz"],  # shipped filters, cards, slices
    },
    include_package_data=False,
)
