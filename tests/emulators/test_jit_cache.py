"""The compiled kernels' cache directory is named after every kernel source: emulators'
own, and those modules elsewhere register (tcf_hil.world.track), whenever they register."""

from __future__ import annotations

from pathlib import Path

import pytest

from emulators import jit as _jit


def test_kernel_sources_are_emulators_own_and_the_registered(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    import tcf_hil.world.track

    sources = _jit.kernel_sources()
    package = Path(_jit.__file__).resolve().parent
    assert {package / name for name in _jit.KERNEL_SOURCES} <= sources
    assert all(p.exists() for p in sources)
    assert Path(tcf_hil.world.track.__file__).resolve() in sources
    assert not any("tcf_hil" in name for name in _jit.KERNEL_SOURCES)  # no layer leak

    numba = _jit.numba_module()
    if numba is None:
        pytest.skip("numba is not installed here")
    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    monkeypatch.setattr(_jit, "_sources", set(_jit._sources))  # restored afterwards
    monkeypatch.setattr(numba.config, "CACHE_DIR", numba.config.CACHE_DIR)
    before = _jit.cache_dir()
    assert before.parent == tmp_path / "tcf-hil" and before.name.startswith("numba-")
    kernel = tmp_path / "kernels.py"
    kernel.write_text("x = 1\n")
    _jit.register_kernel_source(kernel)  # after numba was set up: kernels declared from now
    after = _jit.cache_dir()
    assert after != before and numba.config.CACHE_DIR == str(after)
    _jit.register_kernel_source(str(kernel))  # again: nothing changes
    assert _jit.cache_dir() == after
    kernel.write_text("x = 2\n")  # the content counts, not only the name
    assert _jit.cache_dir() not in (before, after)
