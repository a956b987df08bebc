"""The memory a render may take respects the limits the process is held to: its control group's and its address
space's, not only the machine's (a render in a container or under ``ulimit -v`` was planned for the host's memory and
died, or was refused, after allocating gigabytes)."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from bokehray import _memory


def _group(tmp_path, lines: str, files: dict[str, str]):
    membership = tmp_path / "cgroup"
    membership.write_text(lines)
    for rel, text in files.items():
        f = tmp_path / "fs" / rel
        f.parent.mkdir(parents=True, exist_ok=True)
        f.write_text(text)
    return tmp_path / "fs", membership


def test_a_v2_group_s_limit_less_its_usage(tmp_path):
    root, membership = _group(tmp_path, "0::/jobs/ci\n", {"jobs/ci/memory.max": "2147483648\n",
                                                         "jobs/ci/memory.current": "536870912\n"})
    assert _memory.cgroup_headroom(root, membership) == 1536 << 20


def test_a_v1_group_seen_as_the_namespace_s_root(tmp_path):
    root, membership = _group(tmp_path, "4:memory:/outer/job\n1:cpu:/\n",
                              {"memory/memory.limit_in_bytes": "1073741824", "memory/memory.usage_in_bytes": "1024"})
    assert _memory.cgroup_headroom(root, membership) == (1 << 30) - 1024


def test_no_limit_is_unlimited(tmp_path):
    for files in ({"memory.max": "max", "memory.current": "5"}, {}):
        root, membership = _group(tmp_path, "0::/\n", files)
        assert _memory.cgroup_headroom(root, membership) == _memory.UNLIMITED
    root, membership = _group(tmp_path, "4:memory:/\n", {"memory/memory.limit_in_bytes": "9223372036854771712",
                                                        "memory/memory.usage_in_bytes": "7"})
    assert _memory.cgroup_headroom(root, membership) == _memory.UNLIMITED
    assert _memory.cgroup_headroom(tmp_path / "none", tmp_path / "missing") == _memory.UNLIMITED


def test_an_address_space_limit_caps_what_is_available():
    code = ("import resource; resource.setrlimit(resource.RLIMIT_AS, (3 << 30, 3 << 30));"
            "from bokehray._memory import available_bytes, address_space_headroom;"
            "print(available_bytes() <= address_space_headroom() < 3 << 30)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.stdout.strip() == "True", r.stderr


_FRAGMENTED_HEAP = """
import os, sys
import numpy as np
import pytest

from bokehray import _memory

def rss():
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")

if sys.argv[1] == "bounded":
    assert _memory.bound_heap()
first = np.ones(8 << 17)  # 8 MB: mapped on its own; freed, glibc's moving threshold rises to 8 MB
del first
before = rss()
blocks, kept = [], []
for _ in range(10):
    blocks.append(np.ones(6 << 17))  # 6 MB of temporaries, each followed by a small block that stays
    kept.append(bytearray(200_000))
del blocks
print((rss() - before) >> 20)
"""


def _kept_mb(mode: str) -> int:
    p = subprocess.run([sys.executable, "-c", _FRAGMENTED_HEAP, mode], capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    return int(p.stdout.strip())


@pytest.mark.skipif(_memory._glibc() is None, reason="the C heap's threshold is glibc's")
def test_a_bounded_heap_hands_freed_temporaries_back():
    """60 MB of 6 MB temporaries freed between blocks still in use: with glibc's moving threshold (raised by an
    8 MB block freed before) they stay in the process (about 60 MB, what a render's estimate does not count); with
    the heap bounded (4 MB threshold) each was its own mapping and goes back."""
    assert _kept_mb("bounded") < 12


def test_bound_heap_does_nothing_without_glibc(monkeypatch):
    monkeypatch.setattr(_memory.platform, "libc_ver", lambda: ("", ""))
    assert _memory._glibc() is None
    assert _memory.bound_heap() is False


def test_small_pages_turns_numpys_huge_page_hint_off_unless_the_environment_chose(monkeypatch):
    """The command line asks NumPy for 4 KB pages (less CPU on the machines measured); NUMPY_MADVISE_HUGEPAGE, when set,
    is the user's choice and stands."""
    from numpy._core import multiarray

    before = multiarray._set_madvise_hugepage(True)
    try:
        monkeypatch.delenv("NUMPY_MADVISE_HUGEPAGE", raising=False)
        assert _memory.small_pages()
        assert multiarray._set_madvise_hugepage(True) is False  # it was turned off
        monkeypatch.setenv("NUMPY_MADVISE_HUGEPAGE", "1")
        assert not _memory.small_pages()
        assert multiarray._set_madvise_hugepage(True) is True  # left as it was
    finally:
        multiarray._set_madvise_hugepage(before)


def test_a_render_in_a_callers_process_leaves_numpys_huge_page_hint_alone(monkeypatch):
    """The hint is the process's: a library render changes it neither way (turned off, it slowed the caller's own
    NumPy work; turned back on after, the caller's next large array paid for compacting the freed pages)."""
    from numpy._core import multiarray

    import bokehray as br

    monkeypatch.delenv("NUMPY_MADVISE_HUGEPAGE", raising=False)
    before = multiarray._set_madvise_hugepage(True)
    try:
        for hint in (True, False):
            multiarray._set_madvise_hugepage(hint)
            br.render(np.zeros((8, 8, 3), np.float32), np.zeros((8, 8), np.float32), br.BlurParams(4.0, 0.5))
            assert multiarray._set_madvise_hugepage(hint) is hint
    finally:
        multiarray._set_madvise_hugepage(before)
