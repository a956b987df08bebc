"""The memory a render may take respects the limits the process is held to: its control group's and its address
space's, not only the machine's (a render in a container or under ``ulimit -v`` was planned for the host's memory and
died, or was refused, after allocating gigabytes)."""

from __future__ import annotations

import subprocess
import sys

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
