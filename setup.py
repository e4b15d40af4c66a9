"""What pyproject.toml cannot say alone: the repository's ``configs/`` ship inside the package as
``locretrieval.configs`` (a wheel's ``locretrieval/configs/``; an editable install maps it to the
repository's folder), so that the installed ``locretrieval`` command finds them from any folder."""

from setuptools import find_namespace_packages, setup

setup(
    packages=[*find_namespace_packages(include=["locretrieval*", "hydra_plugins*"]), "locretrieval.configs"],
    package_dir={"locretrieval.configs": "configs"},
)
