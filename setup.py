"""Package discovery for the one `nhfd` distribution.

The repository keeps `drivers/`, `models/` and `calib/` at its top level, beside `nhfd/`, and
installs them as `nhfd.drivers`, `nhfd.models` and `nhfd.calib`: one distribution, so nothing
generic like `models` lands at the top of site-packages (docs/design.md, "Layout"). Subpackages are
found, not listed, so a new subfolder cannot drop out of the wheel (tests/test_packaging.py builds
the wheel to prove it).
"""

from setuptools import find_packages, setup

ROOTS = {"nhfd": "nhfd", "nhfd.drivers": "drivers", "nhfd.models": "models", "nhfd.calib": "calib"}

packages: list[str] = []
for name, folder in ROOTS.items():
    packages.append(name)
    packages += [f"{name}.{sub}" for sub in find_packages(folder)]

setup(packages=packages, package_dir=ROOTS)
