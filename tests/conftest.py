"""Settings for every test process, made before numpy loads."""

import os

# The commands run with one OpenBLAS thread unless the user says otherwise (stewart_calib/cli.py:
# their matrices are small, where a second thread only adds synchronisation), but the tests load
# numpy before they import the CLI, so without this every in-process command ran on all of
# OpenBLAS's threads: two xdist workers on two cores spinning four BLAS threads, where a command's
# small least squares waits for a thread the other worker holds. A test that compares thread counts
# sets them in its subprocess's environment (tests/test_sweep_dask.py).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
