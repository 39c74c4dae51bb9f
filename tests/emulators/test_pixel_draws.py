"""The physical sensor model's per-pixel draws (detection and range noise): a counter-based
generator, each pixel's draws its own, the same compiled and in numpy, and normal."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import special, stats

from emulators.jit import jit_enabled
from emulators.lidar._footprint import (
    mix64,
    ndtri,
    ndtri_np,
    pixel_normals_np,
    pixel_uniforms,
)

keys = st.integers(0, 2**64 - 1).map(np.uint64)


@settings(max_examples=60, deadline=None)
@given(p=st.floats(1e-300, 1.0, exclude_max=True, allow_subnormal=False))
def test_ndtri_is_the_normal_quantile(p: float) -> None:
    """Acklam's approximation: relative error under 1.15e-9 (his bound) against scipy's
    ndtri, and the array form gives the very same bits."""
    want = special.ndtri(p)
    got = ndtri(p)
    assert abs(got - want) <= 1.2e-9 * max(abs(want), 1e-300) + 1e-15
    assert ndtri_np(np.array([p]))[0] == got


@settings(max_examples=30, deadline=None)
@given(key=keys, n=st.integers(1, 300))
def test_a_pixels_draws_are_the_same_alone_and_at_once(key: np.uint64, n: int) -> None:
    """Pixel i's uniforms from the scalar generator (compiled where numba is: the kernels'
    own) are those the numpy path draws for all pixels at once, in (0, 1); so are their
    normals."""
    from emulators.lidar import _footprint

    v, z = pixel_normals_np(key, n)
    for i in range(0, n, max(1, n // 7)):
        u1, u2 = _footprint._pixel_uniforms(key, i)
        assert 0.0 < u1 < 1.0 and 0.0 < u2 < 1.0
        assert _footprint._ndtri(u1) == v[i] and _footprint._ndtri(u2) == z[i]
        with np.errstate(over="ignore"):  # (numpy's scalars warn where uint64 wraps)
            assert pixel_uniforms(key, i) == (u1, u2)


def test_mix64_wraps_as_uint64() -> None:
    """splitmix64's finaliser on arrays and scalars alike (its first outputs from seed 0 are
    the reference values of Vigna's splitmix64.c)."""
    state = np.arange(1, 4, dtype=np.uint64) * np.uint64(0x9E3779B97F4A7C15)
    got = mix64(state)
    assert [int(x) for x in got] == [0xE220A8397B1DCDAF, 0x6E789E6AA1B965F4,
                                     0x06C45D188009454F]
    with np.errstate(over="ignore"):
        assert int(mix64(np.uint64(state[0]))) == 0xE220A8397B1DCDAF


@pytest.mark.parametrize("key", [0, 1, 0x0501, 2**63 + 12345])
def test_the_draws_are_standard_normal_and_independent(key: int) -> None:
    """200,000 pixels of one key: each draw standard normal (Kolmogorov-Smirnov), the two
    of a pixel and neighbouring pixels' uncorrelated, and another key draws others."""
    v, z = pixel_normals_np(np.uint64(key), 200_000)
    for x in (v, z):
        assert stats.kstest(x, "norm").pvalue > 1e-4
        assert abs(x.mean()) < 0.01 and abs(x.std() - 1.0) < 0.01
    assert abs(np.corrcoef(v, z)[0, 1]) < 0.01
    assert abs(np.corrcoef(v[:-1], v[1:])[0, 1]) < 0.01
    other, _ = pixel_normals_np(np.uint64(key + 1), 1000)
    assert not np.array_equal(other, v[:1000])


def test_the_kernels_use_the_compiled_generator() -> None:
    """Where numba is, the generator the detection kernel calls is compiled (a Python
    function per pixel would cost a frame seconds)."""
    from emulators.lidar import _footprint

    if not jit_enabled():
        pytest.skip("compiled kernels are off (TCF_HIL_NO_JIT or no numba)")
    assert _footprint._pixel_uniforms is not _footprint.pixel_uniforms
    assert _footprint._ndtri is not _footprint.ndtri
