"""The core's parallel jobs, by the old name: each part has its module, re-exported here for the files that still
import them from the runner (other engineers' files, being edited now; new code imports the part's module).

- envisat_pose/pools.py: `run_tasks(fn, tasks, RunnerConfig)` in this process, on a local process pool or on a
  Dask cluster; `thread_env`, `cpu_share` (the workers' thread shares).
- envisat_pose/out_dirs.py: the one output-folder rule (`check_out_dir`, `make_out_dir`, `check_out_file`,
  `make_out_file_dir(s)`).
- envisat_pose/resumable.py: the one manifest protocol of outputs written unit by unit (`ResumableJob`).
- envisat_pose/realtime.py: the real-time factor of a job over camera frames.
"""

from envisat_pose.out_dirs import (  # noqa: F401
    PARTIAL_PREFIX,
    check_out_dir,
    check_out_file,
    make_out_dir,
    make_out_file_dir,
    make_out_file_dirs,
)
from envisat_pose.pools import (  # noqa: F401
    BLAS_THREADS,
    RASTERIZER_THREADS,
    Backend,
    RunnerConfig,
    cpu_share,
    run_tasks,
    thread_env,
)
from envisat_pose.realtime import real_time_factor  # noqa: F401
from envisat_pose.resumable import MANIFEST, ResumableJob, remove_partial_files  # noqa: F401
