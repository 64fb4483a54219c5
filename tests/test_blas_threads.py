"""One BLAS thread per process (app/blas_threads.py): set by `procam` for every OpenBLAS copy, those
loaded before and after, and left alone when the user chose a number."""

import json
import os
import subprocess
import sys

PROBE = """
import json, sys
import numpy, cv2                       # two OpenBLAS copies loaded before the limit
{before}
import scipy.linalg                     # and one loaded after
from threadpoolctl import threadpool_info
print(json.dumps({{"limited": limited, "env": __import__("os").environ.get("OPENBLAS_NUM_THREADS"),
                   "blas": [(i["filepath"], i["num_threads"]) for i in threadpool_info() if i["user_api"] == "blas"]}}))
"""


def _probe(before: str, **env_extra) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS")}
    env.update(env_extra)
    out = subprocess.run([sys.executable, "-c", PROBE.format(before=before)], capture_output=True, text=True,
                         env=env, timeout=120)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_every_openblas_gets_one_thread():
    got = _probe("from app.blas_threads import limit_blas_threads\nlimited = limit_blas_threads()")
    assert got["limited"] is True and got["env"] == "1"
    libs = {p for p, _ in got["blas"]}
    assert len(libs) >= 3, libs  # NumPy's, OpenCV's and SciPy's own copies
    assert all(n == 1 for _, n in got["blas"]), got["blas"]


def test_procam_sets_the_limit_before_its_command_runs():
    got = _probe("from app.cli import main\ntry:\n    main(['--version'])\nexcept SystemExit:\n    pass\nlimited = None")
    assert got["env"] == "1"
    assert all(n == 1 for _, n in got["blas"]), got["blas"]


def test_a_users_own_setting_is_kept():
    got = _probe("from app.blas_threads import limit_blas_threads\nlimited = limit_blas_threads()",
                 OPENBLAS_NUM_THREADS="2")
    assert got["limited"] is False and got["env"] == "2"
    if (os.cpu_count() or 1) >= 2:
        assert all(n == 2 for _, n in got["blas"]), got["blas"]
