"""The process pool's workers start from lodbuilder's forkserver with the workers' glibc tunables
(lodbuilder.build.executors.WORKER_TUNABLES: large arrays on transparent huge pages, a page fault
per 2 MiB), and the caller's environment is left as it was."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import pytest

from lodbuilder.build.executors import worker_tunables

#: run as a script file: the forkserver start method needs a main module it can import
SCRIPT = textwrap.dedent('''
    import json, os

    def probe():
        import os
        with open(f"/proc/{os.getppid()}/environ", "rb") as f:
            server = [e.decode() for e in f.read().split(b"\\0") if e.startswith(b"GLIBC_TUNABLES=")]
        return {"server": server, "worker": os.environ.get("GLIBC_TUNABLES")}

    if __name__ == "__main__":
        from lodbuilder.build.executors import make_executor

        before = os.environ.get("GLIBC_TUNABLES")
        with make_executor(workers=1) as (ex, _):
            got = ex.submit(probe).result()
        print(json.dumps({"got": got, "before": before, "after": os.environ.get("GLIBC_TUNABLES")}))
''')


def test_worker_tunables_keep_the_callers_own():
    assert worker_tunables(None) == "glibc.malloc.hugetlb=1"
    assert worker_tunables("") == "glibc.malloc.hugetlb=1"
    assert worker_tunables("glibc.malloc.arena_max=2") == "glibc.malloc.arena_max=2:glibc.malloc.hugetlb=1"
    # a setting the caller gave is the caller's
    assert worker_tunables("glibc.malloc.hugetlb=0:glibc.malloc.arena_max=2") == (
        "glibc.malloc.hugetlb=0:glibc.malloc.arena_max=2")


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
@pytest.mark.parametrize("callers", [None, "glibc.malloc.arena_max=2"])
def test_pool_workers_start_with_the_worker_tunables_and_the_caller_keeps_its_own(tmp_path, callers):
    script = tmp_path / "probe.py"
    script.write_text(SCRIPT)
    env = {k: v for k, v in os.environ.items() if k != "GLIBC_TUNABLES"}
    if callers is not None:
        env["GLIBC_TUNABLES"] = callers
    run = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=300,
                         cwd=tmp_path, env=env)
    assert run.returncode == 0, run.stderr[-3000:]
    out = json.loads(run.stdout.strip().splitlines()[-1])
    want = worker_tunables(callers)
    # (the server's /proc/PID/environ shows the string as glibc left it after parsing: the worker's
    # copy of its environment is what the server was started with)
    assert out["got"]["worker"] == want and len(out["got"]["server"]) == 1
    assert out["before"] == out["after"] == callers
