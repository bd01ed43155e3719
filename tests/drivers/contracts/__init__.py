"""Contract suites: what every backend of a device kind must do, written once per kind.

Each `test_<kind>.py` holds the facts and one parametrised fixture; a backend takes part by
adding its set-up (a param of that fixture) and nothing else. The shipped backends run on every
test run (real drivers on their twins, the simulated backends); a lab's real bench runs the same
suite when an environment variable names its port (`bench_target`), and is skipped with the
variable's name otherwise.

The templates in nhfd.drivers.templates are skeletons whose hooks raise NotImplementedError: a lab
that fills one in adds a param here (or points the variable at its device) to prove it.
"""

from __future__ import annotations

import os

import pytest


def bench_target(variable: str, backends: tuple[str, ...], example: str) -> tuple[str, list[str]]:
    """(backend, [target, ...]) from `variable` = "backend:target[:more]", or skip saying how."""
    value = os.environ.get(variable, "")
    if not value:
        pytest.skip(f"no real device: set {variable} (e.g. {variable}={example}) to run this "
                    "contract on the bench")
    backend, _, rest = value.partition(":")
    if backend not in backends or not rest:
        pytest.fail(f"{variable}={value!r}: expected one of {', '.join(backends)} followed by "
                    f"':' and the device (e.g. {example})")
    return backend, rest.split(":")
