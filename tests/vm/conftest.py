"""tests/vm holds scripts that run inside the VM (.ci/vcan-vm.sh), not pytest tests.

They need a kernel vcan0 and write into $VM_OUT; pytest must neither collect nor import them.
"""

collect_ignore_glob = ["*"]
