"""NHFD_REQUIRE_CUDA=1 (`make gpu-check`): a test skipped for want of CUDA fails instead, so a GPU
run cannot pass by skipping its CUDA tests; other skips stay skips. Checked on a small test file
run by pytester with this suite's hook (tests/conftest.py)."""

from __future__ import annotations

import pytest

pytest_plugins = ("pytester",)

SAMPLE = '''
import pytest

@pytest.mark.skipif(True, reason="needs CUDA")
def test_marked():
    pass

def test_skips_inside():
    pytest.skip("needs CUDA (and gsplat)")

@pytest.mark.skipif(True, reason="needs a browser")
def test_other_reason():
    pass

def test_runs():
    pass
'''


@pytest.fixture
def sample(pytester: pytest.Pytester) -> pytest.Pytester:
    pytester.makeconftest("from tests.conftest import pytest_runtest_makereport  # noqa: F401\n")
    pytester.makepyfile(test_sample=SAMPLE)
    return pytester


@pytest.mark.parametrize("value", [None, "0"])
def test_without_the_variable_cuda_skips_stay_skips(sample, monkeypatch, value):
    if value is None:
        monkeypatch.delenv("NHFD_REQUIRE_CUDA", raising=False)
    else:
        monkeypatch.setenv("NHFD_REQUIRE_CUDA", value)
    result = sample.runpytest("-rs")
    result.assert_outcomes(passed=1, skipped=3)
    assert result.ret == 0


def test_with_the_variable_a_cuda_skip_fails_naming_it(sample, monkeypatch):
    monkeypatch.setenv("NHFD_REQUIRE_CUDA", "1")
    result = sample.runpytest("-rfs")
    # the skipif mark (skipped in setup) and pytest.skip() in the test fail alike; the skip for
    # another reason stays a skip
    result.assert_outcomes(passed=1, failed=2, skipped=1)
    assert result.ret == 1
    result.stdout.fnmatch_lines([
        "*_ test_marked _*",
        "NHFD_REQUIRE_CUDA=1: this test must run on CUDA here, but it skipped: needs CUDA",
        "*_ test_skips_inside _*",
        "NHFD_REQUIRE_CUDA=1: this test must run on CUDA here, but it skipped: needs CUDA (and "
        "gsplat)",
        "FAILED test_sample.py::test_marked - NHFD_REQUIRE_CUDA=1*",
        "FAILED test_sample.py::test_skips_inside - NHFD_REQUIRE_CUDA=1*",
        "SKIPPED [[]1[]] test_sample.py:*: needs a browser",
    ])
