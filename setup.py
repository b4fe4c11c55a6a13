"""The package list under its installed names (everything else is in pyproject.toml).

``pyproject.toml`` maps the import package ``isac_twin`` to ``engine/``, its
``contract`` subpackage to ``addon/contract/`` and ``scenes`` to ``blend_scenes/``;
``find_packages`` cannot rename, so the subpackages are listed here from the folders.
"""

from setuptools import find_packages, setup


def under(name: str, folder: str) -> list[str]:
    return [name] + [f"{name}.{p}" for p in find_packages(folder)]


setup(packages=under("isac_twin", "engine") + under("isac_twin.contract", "addon/contract")
      + ["isac_twin.scenes"])
