"""Threading setup for the numba kernels; imported before any of them runs.

numba's OpenMP worker threads spin while waiting for work by default. On a small machine
shared with other processes (2 cores here) a spinning worker and the caller compete for a
core, and each parallel call stalls for a scheduler quantum: 8-15 ms per call measured,
against 0.8 ms with passive waiting. libgomp reads the policy once, when numba first loads
it, so an explicit ``OMP_WAIT_POLICY`` set by the user still wins.
"""

import os
import warnings

os.environ.setdefault("OMP_WAIT_POLICY", "passive")

# numba tries Intel TBB first and, when the TBB in the process is older than it supports (the
# libtbb that open3d bundles, loaded by the optional CHSEL baseline: interface 12050, numba
# needs 12060), warns on stderr at the first parallel kernel before falling back to OpenMP.
# The fallback is the layer mvtop is tuned for (above), so the warning says nothing the user
# can act on. numba raises it as a NumbaWarning, a direct subclass of Warning.
warnings.filterwarnings("ignore", message="The TBB threading layer requires TBB version", category=Warning)
