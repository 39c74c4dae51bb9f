"""The PNG encoder against matplotlib's reader (libpng through Pillow)."""

from __future__ import annotations

import io

import matplotlib.image as mpimg
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from protocols.png import encode_png


@settings(max_examples=60, deadline=None)
@given(st.integers(1, 40), st.integers(1, 40), st.sampled_from([3, 4]), st.data())
def test_png_round_trips(h: int, w: int, c: int, data: st.DataObject) -> None:
    img = data.draw(arrays(np.uint8, (h, w, c)))
    back = mpimg.imread(io.BytesIO(encode_png(img)), format="png")
    assert back.shape == img.shape
    assert np.array_equal(np.round(back * 255).astype(np.uint8), img)


@pytest.mark.parametrize("bad", [np.zeros((4, 4), np.uint8), np.zeros((4, 4, 2), np.uint8),
                                 np.zeros((4, 4, 3), np.float32), np.zeros((0, 4, 3), np.uint8)])
def test_png_refuses_what_it_cannot_encode(bad: np.ndarray) -> None:
    with pytest.raises(ValueError):
        encode_png(bad)
