"""benchmarks/fuzz_atheris.py cannot rot: it imports without atheris, every target takes its
seed corpus and junk without raising, and an undocumented exception is not swallowed."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]


def _harness() -> ModuleType:
    spec = importlib.util.spec_from_file_location("fuzz_atheris",
                                                  ROOT / "benchmarks" / "fuzz_atheris.py")
    assert spec and spec.loader
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # dataclasses look their module up
    spec.loader.exec_module(mod)
    return mod


H = _harness()


def test_there_is_a_target_per_packet_decoder() -> None:
    names = set(H.TARGETS)
    assert {"lidar", "imu", "pcap", "canopen", "metadata"} <= names
    assert {f"lidar-{p}" for p in H.PROFILE_NAMES} <= names


@pytest.mark.parametrize("name", sorted(H.TARGETS))
def test_each_target_takes_its_seeds_and_junk(name: str) -> None:
    assert H.check(name) >= 2
    rng = np.random.default_rng(0)
    target = H.TARGETS[name]
    for seed in target.seeds()[:2]:
        for n in (0, 1, 7, 48, len(seed) - 1):
            target.one_input(seed[:n])
        damaged = bytearray(seed)
        for at in rng.integers(0, len(seed), 8):
            damaged[at] ^= 0xFF
        target.one_input(bytes(damaged))


def test_an_undocumented_exception_is_a_crash(monkeypatch: pytest.MonkeyPatch) -> None:
    def broken(_: bytes) -> None:
        raise KeyError("not a ProtocolError")

    monkeypatch.setattr(H.o, "decode_imu_packet", broken)
    with pytest.raises(KeyError):
        H.TARGETS["imu"].one_input(b"\x00" * 48)


def test_the_command_line_lists_and_refuses_unknown_targets(
        capsys: pytest.CaptureFixture[str]) -> None:
    assert H.main(["fuzz_atheris.py", "list"]) == 0
    assert "metadata" in capsys.readouterr().out
    assert H.main(["fuzz_atheris.py", "nope"]) == 2
    assert H.main(["fuzz_atheris.py", "pcap", "--check"]) == 0
