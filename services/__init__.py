"""The services: processes on Zenoh around the pure estimation code of ``fusion``.

Every process here does linear algebra on many small matrices (3×3 to 9×9, one track
at a time or stacked), where a threaded BLAS gains nothing and its threads, spinning
for work between calls, take the cores from the other processes of a deployment and
from each other: ``region-400`` with the IMM, 30 s, took 69 s of CPU with OpenBLAS's
default threads against 11 s with one, on two cores with other work running
(``benchmarks/README.md``, "BLAS threads"). So a process
that imports the services before NumPy runs its BLAS on one thread unless the user has
set the thread count; the processes a launcher starts inherit it."""

import os

for _name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_name, "1")
del _name
