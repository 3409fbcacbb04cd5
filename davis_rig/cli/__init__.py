"""cli: thin command-line front ends, one API call per command; nothing imports this package.

Commands: ``davis-record``, ``davis-label``, ``davis-eval``, ``davis-eval-dataset``, ``davis-train``,
``davis-make-dataset``, ``davis-attack`` (one module each). The option vocabulary they share (``--quiet``,
``--threads``, ``--detector``, ``--threshold``, ``--out``, ``--version``), the argument validators, the exit codes
and the error -> message handling live in :mod:`davis_rig.cli._common`.
"""
