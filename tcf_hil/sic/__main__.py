"""``python -m tcf_hil.sic``: the reference onboard SIC (see :mod:`tcf_hil.sic._online`)."""

from tcf_hil.sic import sic_command

if __name__ == "__main__":
    sic_command(prog_name="python -m tcf_hil.sic")
