"""The README's two set-up commands exist and CI runs the second one verbatim."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _setup_commands() -> list[str]:
    text = (ROOT / "README.md").read_text()
    block = re.search(r"## Set up.*?```bash\n(.*?)```", text, re.S)
    assert block, "README lacks the set-up code block"
    return [line for line in block.group(1).splitlines() if line.strip()]


def test_readme_has_exactly_two_setup_commands() -> None:
    cmds = _setup_commands()
    assert len(cmds) == 2
    assert cmds[0].endswith("tcf-hil demo")
    assert "pytest" in cmds[1]


def test_ci_runs_the_readme_test_command() -> None:
    ci = (ROOT / ".ci" / "run").read_text().splitlines()
    assert _setup_commands()[1] in [line.strip() for line in ci]


def test_every_variable_of_the_sic_contract_is_documented() -> None:
    """What a SIC finds in its environment (and in {placeholders}) is in the README's table,
    and nothing the table promises is missing from the environment (TCF_PUBLISH was set
    but not documented)."""
    import inspect

    from tcf_hil.run import ENV_DOC, sic_environment

    text = (ROOT / "README.md").read_text()
    table = text[text.index("### The SIC contract"):text.index("### The run directory")]
    documented = set(re.findall(r"`(TCF_[A-Z_]+)`", table))
    names = {k for k, _ in ENV_DOC}
    assert names == documented, (names - documented, documented - names)
    # what sic_environment sets is what ENV_DOC lists
    assert set(re.findall(r'"(TCF_[A-Z_]+)"', inspect.getsource(sic_environment))) == names
    for name in names:  # each with its placeholder
        assert "{" + name[4:].lower() + "}" in table, name


def test_the_readme_says_which_ouster_frame_the_mount_places() -> None:
    text = (ROOT / "README.md").read_text()
    can = text[text.index("## The harvester on the CAN bus"):text.index("## Layout")]
    assert re.search(r"0x2002 holds the lidar mount.{0,80}Ouster's\s+sensor frame", can, re.S)


def test_the_command_tables_run_rows_list_every_option_of_run() -> None:
    """`run --help`'s every option is in the README's `run` rows (the live run's and the
    replay's): `--sensor` was missing once."""
    from tcf_hil.cli.run import run_cmd

    text = (ROOT / "README.md").read_text()
    rows = [line for line in text.splitlines() if line.startswith("| `tcf-hil run ")]
    assert len(rows) >= 2
    listed = set(re.findall(r"--[a-z][a-z-]*", " ".join(r.split(" | ")[0] for r in rows)))
    options = {o for p in run_cmd.params for o in p.opts if o.startswith("--")} - {"--help"}
    assert options - listed == set()
    assert "run` defaults to 2048x10" in text and "the demo uses 1024x10" in text
