"""The numerical tests hold on another CPU's BLAS kernels, not only on this machine's.

A fresh clone once failed on a machine whose OpenBLAS picked other kernels than the machine the
suite was written on: an "exact" test met 2e-8 where it asserted 1e-12 (the arccos of a trace
amplifies one rounding step to sqrt(eps)). OpenBLAS chooses its kernels by CPU at run time, and
``OPENBLAS_CORETYPE`` forces a choice, so this test reruns the numerics-heavy tests under the
generic x86-64 kernels (``Prescott``: SSE3, present on every x86-64 CPU), whose round-off
differs from the AVX2/AVX-512 ones a developer's machine usually uses.
"""

from __future__ import annotations

import os
import platform
import subprocess
import sys

import pytest

from tests.conftest import REPO

NUMERIC_TESTS = ("tests/tracker/test_tracker.py", "tests/tracker/test_body.py",
                 "tests/tracker/test_ransac.py", "tests/common/test_kabsch.py",
                 "tests/common/test_se3.py", "tests/kinematics/test_filters.py")


@pytest.mark.skipif(platform.machine() not in ("x86_64", "AMD64"),
                    reason="OPENBLAS_CORETYPE names x86-64 kernels")
@pytest.mark.skipif(os.environ.get("OPENBLAS_CORETYPE") is not None,
                    reason="already running under a forced BLAS kernel")
def test_numerical_tests_pass_on_generic_blas_kernels() -> None:
    env = {**os.environ, "OPENBLAS_CORETYPE": "Prescott"}
    result = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
                             *NUMERIC_TESTS], cwd=REPO, env=env, capture_output=True, text=True,
                            check=False, timeout=1200)
    assert result.returncode == 0, result.stdout[-4000:] + result.stderr[-2000:]
