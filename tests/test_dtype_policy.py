"""float64 policy: a path that needs float64 and is handed float32 says so."""

import subprocess
import sys
import textwrap

import jax.numpy as jnp
import pytest

from gcrsky.base import check_float64


def test_check_float64_rejects_float32_and_complex64():
    check_float64(jnp.zeros(3, jnp.float64), jnp.zeros(3, jnp.complex128))
    with pytest.raises(TypeError, match="float64"):
        check_float64(jnp.zeros(3, jnp.float32))
    with pytest.raises(TypeError, match="complex128"):
        check_float64(jnp.zeros(3, jnp.complex64))


@pytest.mark.slow
def test_building_a_problem_without_x64_is_a_clear_error():
    # a fresh interpreter: the test session itself runs with x64 on
    code = textwrap.dedent(
        """
        import gcrsky
        try:
            gcrsky.standard_case(lmax=4, nside=8)
        except RuntimeError as e:
            print("ERR:", e)
        """
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert "ERR:" in out.stdout and "jax_enable_x64" in out.stdout, out.stdout + out.stderr
