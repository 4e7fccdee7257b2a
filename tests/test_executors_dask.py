"""A Dask LocalCluster's workers start as the process pool's do (issue 19: Dask within 1.2 x of the
pool): forked warm from lodbuilder's forkserver, in the caller's environment, and the caller's
environment is left as it was (distributed's nanny used to set MALLOC_TRIM_THRESHOLD_ and
OMP_NUM_THREADS in it, for good, and every worker forked after that had glibc's allocator map and
unmap every array over 128 KiB), and without the Dask worker's profiler and its frequent health
checks (lodbuilder.build.executors.DASK_LOCAL_CONFIG)."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap

import pytest

pytest.importorskip("dask.distributed")

#: run as a script file: the forkserver start method needs a main module it can import
SCRIPT = textwrap.dedent('''
    import json, os, sys

    KEYS = ("distributed.worker.profile.enabled", "distributed.admin.tick.interval",
            "distributed.admin.system-monitor.interval", "distributed.worker.memory.monitor-interval")

    def probe():
        import os, sys
        with open(f"/proc/{os.getppid()}/environ", "rb") as f:
            server_env = [e.decode() for e in f.read().split(b"\\0") if e]
        settings = {}
        if "distributed" in sys.modules:  # (a Dask worker: the settings it runs with)
            import dask
            settings = {k: dask.config.get(k) for k in KEYS}
        return {"warm": "lodbuilder.build._warm" in sys.modules, "settings": settings,
                "trim": os.environ.get("MALLOC_TRIM_THRESHOLD_"),
                "server_trim": [e for e in server_env if e.startswith("MALLOC_TRIM_THRESHOLD_")],
                "server_tunables": [e for e in server_env if e.startswith("GLIBC_TUNABLES=")]}

    if __name__ == "__main__":
        from lodbuilder.build.executors import make_executor

        before = {k: os.environ.get(k) for k in ("MALLOC_TRIM_THRESHOLD_", "OMP_NUM_THREADS", "GLIBC_TUNABLES")}
        with make_executor(dask_local=1) as (ex, _):
            dask = ex.submit(probe).result()
        after = {k: os.environ.get(k) for k in before}
        with make_executor(workers=1) as (ex, _):  # a pool after the cluster, in the same process
            pool = ex.submit(probe).result()
        print(json.dumps({"dask": dask, "pool": pool, "before": before, "after": after}))
''')


@pytest.mark.dask
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_dask_local_workers_start_warm_in_the_callers_environment(tmp_path):
    script = tmp_path / "probe.py"
    script.write_text(SCRIPT)
    env_clear = {k: v for k, v in __import__("os").environ.items()
                 if k not in ("MALLOC_TRIM_THRESHOLD_", "OMP_NUM_THREADS", "GLIBC_TUNABLES")}
    run = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=300,
                         cwd=tmp_path, env=env_clear)
    assert run.returncode == 0, run.stderr[-3000:]
    got = json.loads(run.stdout.strip().splitlines()[-1])
    # forked from the server that preloaded lodbuilder (kernels loaded once, not in each worker)
    assert got["dask"]["warm"] is True
    # glibc's allocator as in a pool worker: no fixed trim threshold, in the worker nor its server
    assert got["dask"]["trim"] is None and got["dask"]["server_trim"] == []
    # the caller's environment as it was
    assert got["after"] == got["before"] == {"MALLOC_TRIM_THRESHOLD_": None, "OMP_NUM_THREADS": None,
                                             "GLIBC_TUNABLES": None}
    # the server (and so every worker) with the workers' glibc tunables (WORKER_TUNABLES)
    assert got["dask"]["server_tunables"] == got["pool"]["server_tunables"] == ["GLIBC_TUNABLES=glibc.malloc.hugetlb=1"]
    # and a process pool started after the cluster works, forked warm from the same server
    assert {k: got["pool"][k] for k in ("warm", "trim", "server_trim")} == {"warm": True, "trim": None,
                                                                          "server_trim": []}
    # the worker runs without the profiler and with slower health checks (see DASK_LOCAL_CONFIG)
    assert got["dask"]["settings"] == {"distributed.worker.profile.enabled": False,
                                       "distributed.admin.tick.interval": "1s",
                                       "distributed.admin.system-monitor.interval": "2s",
                                       "distributed.worker.memory.monitor-interval": "1s"}


def test_the_readme_gives_a_real_cluster_the_local_clusters_settings():
    """The Dask configuration the README gives a real cluster's workers is the LocalCluster's."""
    import re
    from pathlib import Path

    import dask
    import yaml
    from distributed.nanny import _get_env_variables

    from lodbuilder.build.executors import DASK_LOCAL_CONFIG

    text = (Path(__file__).parents[1] / "README.md").read_text()
    (block,) = re.findall(r"^```yaml\n(.*?)^```", text, re.M | re.S)
    with dask.config.set(yaml.safe_load(block)):
        assert "MALLOC_TRIM_THRESHOLD_" not in _get_env_variables("distributed.nanny.pre-spawn-environ")
        for key, value in DASK_LOCAL_CONFIG.items():
            if key != "distributed.nanny.pre-spawn-environ":
                assert dask.config.get(key) == value, key


def test_the_rounds_warm_up_is_preloaded_only_when_rounds_are_on():
    """The forkserver runs the resumable engine's warm-up only for builds with radius rounds (it
    cost every pool build about 0.4 CPU-s before its workers could fork)."""
    from lodbuilder.build import executors

    assert executors.preload() == executors.PRELOAD
    assert executors.preload(rounds=True) == [*executors.PRELOAD, "lodbuilder.build._warm_rounds"]
