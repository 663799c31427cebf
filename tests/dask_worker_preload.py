"""Preloaded by the `dask worker` of tests/test_dask_cluster.py (`--preload`): the worker
refuses to open any file under the driver's folder (DRAKE_GRASP_TEST_DRIVER_DIR), as a
worker on another machine could not, so the test fails if a trial reads the run's object
library or writes a record there instead of going through the driver."""

import builtins
import io
import os

_DRIVER = os.path.realpath(os.environ["DRAKE_GRASP_TEST_DRIVER_DIR"])
_open = io.open


def _guarded_open(file, *args, **kwargs):
    if isinstance(file, (str, bytes, os.PathLike)):
        path = os.path.realpath(os.fsdecode(file))
        if path == _DRIVER or path.startswith(_DRIVER + os.sep):
            raise PermissionError(f"dask worker opened {path}: the driver's folder is not "
                                  "on this worker's filesystem")
    return _open(file, *args, **kwargs)


builtins.open = io.open = _guarded_open
