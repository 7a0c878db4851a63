"""The sweep's guard: a study larger than this many tasks, or than this much CPU, starts only
with ``--yes``. A grid multiplies out faster than anyone reads it (1 000 × 1 000 values × 1 000
seeds is 10⁹ tasks), and that mistake should cost a second, not a day. Kept apart from the
runner so the command line can name them without importing Dask.
"""

MAX_TASKS = 100_000
MAX_CPU_HOURS = 24.0
