"""The SIC's library code raises SicError (a TcfHilError), never SystemExit; its command
turns one into the message alone on stderr and exit status 1."""

from __future__ import annotations

import os
import socket
import subprocess
import sys

import pytest

from tcf_hil.errors import SicError, TcfHilError
from tcf_hil.sic._online import SicConfig, load_metadata

NO_METADATA = ("sic: no metadata: set TCF_METADATA or TCF_SENSOR_URL "
               "(--metadata / --sensor-url)")


def test_missing_metadata_is_a_sic_error() -> None:
    assert issubclass(SicError, TcfHilError) and not issubclass(SicError, SystemExit)
    with pytest.raises(SicError) as err:
        load_metadata(SicConfig())
    assert str(err.value) == NO_METADATA


def test_a_sensor_that_does_not_answer_is_a_sic_error() -> None:
    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    url = f"http://127.0.0.1:{port}"
    with pytest.raises(SicError, match=f"^sic: cannot read the metadata from {url}/api/v1/"
                                       "sensor/metadata: "):
        load_metadata(SicConfig(sensor_url=url), timeout_s=0.2)


def test_the_command_ends_with_the_message_and_status_1() -> None:
    env = {k: v for k, v in os.environ.items() if k not in ("TCF_METADATA", "TCF_SENSOR_URL")}
    p = subprocess.run([sys.executable, "-m", "tcf_hil.sic"], capture_output=True, text=True,
                       env=env, timeout=120)
    assert p.returncode == 1 and p.stdout == "" and p.stderr == NO_METADATA + "\n"
