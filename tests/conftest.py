import atexit
import os
import shutil
import tempfile

import numpy as np
import pytest

from app.blas_threads import limit_blas_threads

# as `procam` does (app/blas_threads.py): four test workers share two cores, and a spinning BLAS thread
# would slow every calibration computed in a test process
limit_blas_threads()

# the detection cache's signing key (calib.detection.cache): one private to this test run, never the
# user's own (subprocesses inherit it)
if "PROCAM_CACHE_KEY_FILE" not in os.environ:
    _key_dir = tempfile.mkdtemp(prefix="procam-key-")
    atexit.register(shutil.rmtree, _key_dir, True)
    os.environ["PROCAM_CACHE_KEY_FILE"] = os.path.join(_key_dir, "cache.key")


@pytest.fixture
def rng():
    return np.random.default_rng(1234)
