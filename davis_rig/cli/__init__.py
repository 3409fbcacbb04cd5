"""cli: thin command-line front ends, one API call per command; nothing imports this package.

Commands: ``davis-record`` (:mod:`davis_rig.cli.record`). Shared error -> exit-code handling lives in
:mod:`davis_rig.cli._common`.
"""
