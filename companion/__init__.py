"""companion: tightly coupled GNSS/INS navigation for drone companion computers."""
import os as _os

# The filter's matrices are small: a second BLAS thread only waits for a core and, spinning,
# doubles the CPU of an RTK epoch and puts 100-ms stalls into the IMU path (python -m sitl bench:
# latency of a sample carrying an RTK epoch p99 105 ms -> 9 ms).  Effective only before numpy's
# first import; a user's own setting wins.
_os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

__version__ = "0.1.0"      # the one place the version is written (pyproject.toml reads it)
