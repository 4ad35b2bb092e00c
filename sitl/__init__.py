"""The SITL harness: simulator, autopilots, base station, scenarios, benchmarks."""
# companion first: it sets OPENBLAS_NUM_THREADS=1, which works only before numpy's first import
# (sitl.faults imported numpy first: a second BLAS thread then spun through every RTK epoch and
# python -m sitl bench's RTK load read 24.8k IMU samples per CPU-second at 35.8k per wall second)
import companion  # noqa: F401
