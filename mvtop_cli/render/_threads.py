"""Threading setup for the numba kernels; imported before any of them runs.

numba's OpenMP worker threads spin while waiting for work by default. On a small machine
shared with other processes (2 cores here) a spinning worker and the caller compete for a
core, and each parallel call stalls for a scheduler quantum: 8-15 ms per call measured,
against 0.8 ms with passive waiting. libgomp reads the policy once, when numba first loads
it, so an explicit ``OMP_WAIT_POLICY`` set by the user still wins.
"""

import os

os.environ.setdefault("OMP_WAIT_POLICY", "passive")
