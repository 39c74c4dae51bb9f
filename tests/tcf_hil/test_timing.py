"""What decides a sender's wake-ups: the kernel's preemption read from what the kernel says
(other kernels than this machine's are given by replacing what they would say)."""

from __future__ import annotations

import pytest

from tcf_hil.devices import timing


def _kernel(monkeypatch: pytest.MonkeyPatch, version: str, files: dict[str, str]) -> None:
    monkeypatch.setattr(timing.platform, "version", lambda: version)
    monkeypatch.setattr(timing, "_read", lambda path: files.get(path))


@pytest.mark.parametrize(("version", "files", "want"), [
    ("#1 SMP PREEMPT_RT Tue Jan 1", {}, ("PREEMPT_RT", None)),
    ("#1 SMP PREEMPT Tue Jan 1", {}, ("PREEMPT", None)),
    ("#1 SMP Tue Jan 1", {}, ("none", None)),
    ("#1 SMP PREEMPT_DYNAMIC @0",
     {"/sys/kernel/debug/sched/preempt": "none voluntary (full) lazy"},
     ("PREEMPT_DYNAMIC", "full")),
    ("#1 SMP PREEMPT_DYNAMIC @0", {"/proc/cmdline": "quiet preempt=voluntary ro"},
     ("PREEMPT_DYNAMIC", "voluntary")),
])
def test_the_preemption_model_comes_from_what_the_kernel_says(
        monkeypatch: pytest.MonkeyPatch, version: str, files: dict[str, str],
        want: tuple[str, str | None]) -> None:
    _kernel(monkeypatch, version, files)
    assert timing._preemption() == want


def test_the_facts_are_those_of_this_machine() -> None:
    facts = timing.machine_facts()
    assert facts["cpus"] >= 1 and facts["kernel"]
    assert facts["preemption"] in ("PREEMPT_RT", "PREEMPT_DYNAMIC", "PREEMPT", "none")
    assert isinstance(facts["hypervisor"], bool)
