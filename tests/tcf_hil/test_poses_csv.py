"""sensor_poses.csv's rows from arrays are the very text of Python's formatting."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from tcf_hil.recording.poses_csv import pose_rows

DECIMALS = (6, 6, 6, 9, 9, 9, 9)


def _python(t: list[int], rows: list[list[float]]) -> str:
    return "".join(",".join([str(ti), *(f"{v:.{d}f}" for v, d in zip(r, DECIMALS,
                                                                     strict=True))]) + "\n"
                   for ti, r in zip(t, rows, strict=True))


# near-halves in decimals: k / 10**d + 5 / 10**(d + 1), nudged by a few ulps, and exact
# dyadic halves (2**-7 = 0.0078125 at six decimals rounds to even)
_halves = st.builds(lambda k, d, ulps: float(np.nextafter(
    k / 10.0**d + 5 / 10.0**(d + 1), np.inf if ulps > 0 else -np.inf)) if ulps else
    k / 10.0**d + 5 / 10.0**(d + 1), st.integers(-10**7, 10**7), st.sampled_from([6, 9]),
    st.integers(-1, 1))
_values = st.one_of(st.floats(allow_nan=False, allow_infinity=False, width=64),
                    st.floats(-1e7, 1e7), st.floats(-1.0, 1.0), _halves,
                    st.sampled_from([0.0, -0.0, 2.0**-7, -(2.0**-7), 3 * 2.0**-21, 2.0**-30,
                                     1e-7, -1e-10, 4.5e9, 2.0**51 / 1e6]))


@settings(max_examples=150, deadline=None)
@given(st.lists(st.tuples(st.integers(-2**63 + 1, 2**63 - 1),
                          st.lists(_values, min_size=7, max_size=7)), min_size=1,
                max_size=20))
@example([(60_000_000_000, [500013.6961695, 6699976.9786715, 54.0973525, 2.0**-7, 0.5,
                            -0.0, 1 / 3])])
def test_rows_from_arrays_are_pythons_formatting(rows: list[tuple[int, list[float]]]) -> None:
    t = [r[0] for r in rows]
    v = [r[1] for r in rows]
    got = pose_rows(np.array(t, np.int64), np.array(v, np.float64), DECIMALS)
    assert got == _python(t, v)


def test_a_value_it_does_not_cover_falls_back_to_python() -> None:
    v = np.array([[np.nan, np.inf, -np.inf, 1e300, 0.1, 0.2, 0.3]])
    assert pose_rows(np.array([5]), v, DECIMALS) == _python([5], v.tolist())
    assert pose_rows(np.zeros(0, np.int64), np.zeros((0, 7)), DECIMALS) == ""


def test_times_and_values_of_other_lengths_are_refused() -> None:
    with pytest.raises(ValueError):
        pose_rows(np.arange(2, dtype=np.int64), np.zeros((3, 7)), DECIMALS)
