"""The executor seam: local pool and Dask give the same results, failures are reported, killed workers retried."""

from __future__ import annotations

import logging
import subprocess
import sys
import time

import numpy as np
import pytest
from executor_tasks import always_die, digest, fail_on_odd, write_or_die
from tolerances import HANG_S

from bokehray.errors import InputError
from bokehray.executor import Outcome, make_executor
from bokehray.output.atomic import remove_stale_outputs


def _run(ex, fn, tasks) -> list[Outcome]:
    with ex:
        return sorted(ex.map(fn, tasks), key=lambda o: o.index)


@pytest.fixture(scope="module")
def dask_scheduler():
    """A LocalCluster of 2 single-threaded worker processes on 127.0.0.1, started by the test itself."""
    pytest.importorskip("distributed")
    import dask
    from distributed import LocalCluster

    with dask.config.set({"distributed.scheduler.allowed-failures": 2}):
        cluster = LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                               dashboard_address="127.0.0.1:0", silence_logs=logging.ERROR)
    try:
        yield cluster.scheduler_address
    finally:
        cluster.close()


def test_local_pool_inline_and_dask_give_the_same_results(dask_scheduler):
    tasks = [(7, i) for i in range(12)]
    want = [digest(t) for t in tasks]
    for ex in (make_executor("local", workers=1), make_executor("local", workers=2),
               make_executor("dask", scheduler=dask_scheduler)):
        got = _run(ex, digest, tasks)
        assert [o.index for o in got] == list(range(12))
        assert [o.value for o in got] == want, ex.describe()
    assert dask_scheduler.startswith("tcp://127.0.0.1:")


@pytest.mark.parametrize("kind", ["inline", "local", "dask"])
def test_a_failing_task_is_reported_and_never_retried(kind, request):
    ex = (make_executor("local", workers=1) if kind == "inline" else make_executor("local", workers=2)
          if kind == "local" else make_executor("dask", scheduler=request.getfixturevalue("dask_scheduler")))
    got = _run(ex, fail_on_odd, list(range(6)))
    assert [o.ok for o in got] == [True, False] * 3
    assert got[1].error == "task 1: bad input" and got[1].attempts == 1
    assert [o.value for o in got if o.ok] == [0, 2, 4]


@pytest.mark.parametrize("kind", ["local", "dask"])
def test_a_killed_worker_leaves_nothing_half_written_and_its_task_is_retried(kind, tmp_path, request):
    ex = (make_executor("local", workers=2) if kind == "local"
          else make_executor("dask", scheduler=request.getfixturevalue("dask_scheduler")))
    tasks = [(str(tmp_path), i, i == 2) for i in range(5)]
    t0 = time.perf_counter()
    got = _run(ex, write_or_die, tasks)
    assert time.perf_counter() - t0 < HANG_S
    assert all(o.ok for o in got), [o.error for o in got]
    if kind == "local":
        assert got[2].attempts == 2  # the dead worker's task ran again (and any task sharing its broken pool)
    for i in range(5):  # every output is whole: the killed attempt never reached the final name
        assert (tmp_path / f"out_{i}.bin").read_bytes() == bytes([i]) * 65536
    # the killed attempt's half-written temporary is gone: the retry's atomic write removed the temporaries of
    # dead processes of this host beside its output (bokehray.output.atomic); remove_stale_temporaries covers what a worker
    # on another host left, and finds nothing more here
    assert not [p.name for p in tmp_path.iterdir() if p.name.startswith(".out_2.bin.")]
    assert remove_stale_outputs(tmp_path, [f"out_{i}.bin" for i in range(5)]) == 0
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_a_task_that_always_kills_its_worker_fails_after_the_retries():
    got = _run(make_executor("local", workers=2, retries=1), always_die, [0])
    assert not got[0].ok and "died 2 times" in got[0].error and got[0].attempts == 2


def test_dask_cluster_started_by_the_executor_on_localhost():
    pytest.importorskip("distributed")
    with make_executor("dask", workers=2) as ex:
        assert ex.address.startswith("tcp://127.0.0.1:") and ex.workers == 2
        assert "local cluster" in ex.describe()
        got = sorted(ex.map(digest, [(1, i) for i in range(4)]), key=lambda o: o.index)
    assert [o.value for o in got] == [digest((1, i)) for i in range(4)]


def test_bad_executor_arguments():
    with pytest.raises(InputError, match="--executor: expected one of local, dask"):
        make_executor("ray")
    with pytest.raises(InputError, match="--scheduler needs --executor dask"):
        make_executor("local", scheduler="tcp://127.0.0.1:1")
    with pytest.raises(InputError, match="--workers: expected at least 1"):
        make_executor("local", workers=0)
    assert make_executor("local", workers=8, tasks=3).workers == 3


BAD_SCHEDULERS = ["notaurl", "inproc://x", "tls://127.0.0.1:1", "ucx://127.0.0.1:1", "tcp://127.0.0.1:8786/../x",
                  "", "tcp://127.0.0.1:0", "tcp://127.0.0.1:70000", "tcp://:8786"]


@pytest.mark.parametrize("address", BAD_SCHEDULERS)
def test_a_malformed_scheduler_address_is_refused_before_dask_sees_it(address):
    """Issue: these gave tracebacks from inside Dask, and '' silently started a local cluster."""
    with pytest.raises(InputError, match=r"--scheduler: expected a Dask scheduler address tcp://HOST:PORT"):
        make_executor("dask", scheduler=address)
    with pytest.raises(InputError, match=r"--scheduler: expected a Dask scheduler address"):
        make_executor("local", scheduler=address)  # the address is wrong whatever the executor


@pytest.mark.parametrize("command", ["render", "synth"])
@pytest.mark.parametrize("address", ["notaurl", "", "tcp://127.0.0.1:8786/../x"])
def test_cli_refuses_a_malformed_scheduler_before_writing(tmp_path, capsys, command, address):
    import bokehray as br
    from bokehray.app.cli import main

    img = br.write_image(tmp_path / "p.png", np.full((8, 8, 3), 0.5, np.float32))
    disp = br.write_disparity(tmp_path / "d.png", np.full((8, 8), 0.5, np.float32))
    args = (["render", str(img), "--disparity", str(disp), "--blur", "2", "--focus", "0.2,0.4"] if command == "render"
            else ["synth", "-n", "1", "--size", "16"])
    code = main([*args, "-o", str(tmp_path / "out"), "--executor", "dask", f"--scheduler={address}"])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and f"got {address!r}" in err, err
    assert not (tmp_path / "out").exists()


def test_remove_stale_outputs_touches_only_the_named_outputs(tmp_path):
    names = ["a.png", "scene_00001"]
    for n in [".a.png.x1y2.png", ".scene_00001.tmp-12-abc", ".a.pngx", ".b.png.q.png", "a.png", ".scene_000010.tmp-1"]:
        (tmp_path / n).mkdir() if "scene" in n else (tmp_path / n).write_bytes(b"x")
    (tmp_path / ".scene_00001.tmp-12-abc" / "image.exr").write_bytes(b"x")
    (tmp_path / ".scene_00001.old-abc").mkdir()  # an overwrite interrupted mid-swap: the old scene, kept
    assert remove_stale_outputs(tmp_path, names) == 2
    left = sorted(p.name for p in tmp_path.iterdir())
    assert left == [".a.pngx", ".b.png.q.png", ".scene_00001.old-abc", ".scene_000010.tmp-1", "a.png"]


def test_bench_split_and_synth_cli_go_through_the_seam(tmp_path, capsys):
    from bokehray.app.bench.run import SynthSplit, synth_cases
    from bokehray.app.cli import build_parser

    split = SynthSplit(scenes=2, size=40, blur_levels=(5.0,), max_spp=4, seed=11)
    cases, root = synth_cases(split, tmp_path, workers=2, executor="local", progress=False, log=lambda s: None)
    assert len(cases) == 2 * 2 and (root / "COMPLETE").is_file()
    assert not [p for p in root.iterdir() if p.name.startswith(".")]
    for cmd in (["bench"], ["synth", "-o", "x"]):
        args = build_parser().parse_args([*cmd, "--executor", "dask", "--scheduler", "tcp://127.0.0.1:8786"])
        assert args.executor == "dask" and args.scheduler == "tcp://127.0.0.1:8786"


def test_dask_missing_is_one_clear_line(monkeypatch):
    monkeypatch.setitem(sys.modules, "distributed", None)  # as if the extra were not installed
    with pytest.raises(InputError, match=r"--executor dask needs its extra: pip install 'bokehray\[distributed\]'"):
        make_executor("dask", workers=1)


@pytest.mark.slow
def test_import_bokehray_imports_no_dask():
    code = ("import sys, bokehray, bokehray.app.batch, bokehray.executor, bokehray.app.cli; bokehray.app.cli.build_parser(); "
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('dask', 'distributed')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"
