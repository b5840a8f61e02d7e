"""Maps the top-level folders onto the `aeroperception.*` import namespace.

pyproject.toml holds the metadata; this file only computes the package list, because
setuptools cannot express "every subpackage of schemas/, services/, tools/ under a prefix"
declaratively. `aeroperception` itself is an implicit namespace package.

The editable install maps the folders with an import hook, which static analysers do not run:
for them src/aeroperception/ holds relative symlinks to the same three folders (pyproject's
[tool.pyright] extraPaths, [tool.mypy] mypy_path). Python never looks there.
"""
from setuptools import find_packages, setup

TOP_LEVEL = ("schemas", "services", "tools")
packages, package_dir = [], {}
for top in TOP_LEVEL:
    package_dir[f"aeroperception.{top}"] = top
    packages += [f"aeroperception.{top}"] + [f"aeroperception.{top}.{p}" for p in find_packages(top)]
setup(packages=packages, package_dir=package_dir)
