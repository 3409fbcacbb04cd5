"""cli: thin command-line front ends, one API call per command; no library module imports this package.

Commands: ``davis-record``, ``davis-label``, ``davis-eval``, ``davis-eval-dataset``, ``davis-train``,
``davis-make-dataset``, ``davis-attack``, ``davis-info``, ``davis-export``, ``davis-view`` (one module each). The
option vocabulary they share (``--quiet``, ``--threads``, ``--detector``, ``--threshold``, ``--out``, ``--version``,
and the attack's ``--parts``, ``--scales``, ``--device``), the argument validators, the exit codes and the
error -> message handling live in :mod:`davis_rig.cli.common`, which the scripts in ``tools/`` use too.

Every command runs with OpenMP's passive wait policy unless the user set ``OMP_WAIT_POLICY``: with the default
spin-waiting, eager torch on a loaded 2-core machine stalled for seconds per RVT step (2.2-2.5 s median against
66-118 ms passive, benchmarks/README.md). It must be set before torch loads OpenMP, hence here, where every
console script starts.
"""

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
