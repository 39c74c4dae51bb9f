"""What crossed the wire, kept and read back: the run directory and its files (:mod:`.rundir`:
``RunDir`` and the one check that a directory holds what a reader needs), a recording's
reader (:mod:`.reader`: a tcf-hil run directory or a field recording, on one time line),
stems documents read and validated
(:mod:`.stems_json`) and field inventories as ground truth (:mod:`.inventory`).

May import :mod:`protocols`, :mod:`emulators` (the bus specs and routes) and the small shared
helpers only: everything above reads recordings through this package.
"""
