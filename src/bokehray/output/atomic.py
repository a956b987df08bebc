"""Atomic writes: a file appears whole or not at all, whatever stops the writer.

The data goes to a hidden temporary sibling that replaces the target only once it is complete and synced; a write
killed outright leaves its temporary behind, and the next write to the same name removes it once its writer is
known to be dead.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import os
import shutil
import signal
import socket
import tempfile
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path

import psutil

from ..errors import BokehrayError, OutputError, OutputExistsError, ResourceError

__all__ = ["atomic_write", "is_zombie", "remove_made_folder_on_failure", "remove_stale_outputs",
           "remove_stale_temporaries", "temporary_prefix", "temporary_stem", "writer_alive"]

_TMP_TAG = ".tmp-"
"""Temporary siblings are named ``.<name>.tmp-<host>-<pid>-<random><suffix>`` (a long ``<name>`` shortened:
:func:`temporary_stem`): hidden, never read by any reader here, and recognisable as a dead writer's leftovers by the
next write to ``<name>``."""


_LONG_NAME_BYTES = 128
"""A target name longer than this (in bytes) is shortened in its temporary's name (:func:`temporary_stem`): the tag,
host, process id and random part add up to 60 bytes, and a 230-255 byte name's temporary passed the file system's
255-byte limit ("File name too long" after the whole render)."""


def temporary_stem(name: str) -> str:
    """How a temporary sibling names its target ``name``: the name itself, or, beyond :data:`_LONG_NAME_BYTES`, its
    first 100 bytes, ``~`` and 12 hex digits of its SHA-256 (the same for every writer of that name)."""
    raw = os.fsencode(name)
    if len(raw) <= _LONG_NAME_BYTES:
        return name
    return f"{os.fsdecode(raw[:100])}~{hashlib.sha256(raw).hexdigest()[:12]}"


def temporary_prefix(path: Path) -> str:
    """The name a write to ``path`` by this process gives its temporary sibling, up to its random part."""
    host = "".join(c if c.isalnum() else "_" for c in socket.gethostname())[:32] or "host"
    return f".{temporary_stem(path.name)}{_TMP_TAG}{host}-{os.getpid()}-"


def writer_alive(pid: int) -> bool:
    """Whether process ``pid`` of this host can still write (it exists and is not a zombie)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # e.g. EPERM: it exists, owned by someone else
        pass
    return not is_zombie(pid)


def is_zombie(pid: int) -> bool:
    """A killed process that its parent has not reaped yet (a pool or a Dask nanny restarting a worker): it still
    answers kill(pid, 0), but it writes nothing more."""
    try:
        return psutil.Process(pid).status() == psutil.STATUS_ZOMBIE
    except psutil.Error:
        return False


def remove_stale_temporaries(path: str | os.PathLike[str]) -> list[Path]:
    """Remove temporary files that an earlier, killed write to ``path`` left beside it.

    A write that is killed outright (SIGKILL, power loss) cannot clean up after itself; its
    hidden ``.<name>.tmp-<host>-<pid>-...`` file stays. Such a file is removed here when it was
    made on this host by a process that no longer exists; files of a live writer (a concurrent
    write to the same path) and of other hosts (a shared folder) are left alone. Returns the
    files removed. Called by every write; never raises.
    """
    p = Path(path)
    host_prefix = temporary_prefix(p).rsplit("-", 2)[0] + "-"  # ".<name>.tmp-<host>-"
    removed = []
    try:
        entries = list(os.scandir(p.parent))
    except OSError:
        return removed
    for e in entries:
        if not (e.name.startswith(host_prefix) and e.name.endswith(p.suffix)):
            continue
        pid_text = e.name[len(host_prefix):].split("-", 1)[0]
        if not pid_text.isdigit() or int(pid_text) == os.getpid() or writer_alive(int(pid_text)):
            continue
        with contextlib.suppress(OSError):
            os.unlink(e.path)
            removed.append(Path(e.path))
    return removed


@contextlib.contextmanager
def remove_made_folder_on_failure(folder: str | os.PathLike[str]) -> Iterator[list[Path]]:
    """For a command that writes several files into ``folder``: yields a list it appends each file it writes to.

    If the block raises (an error, a full disk, Ctrl-C, SIGTERM), the folders it made are removed: ``folder`` and
    each missing parent, those that did not exist on entry, with the listed files inside them (atomic writes have
    removed their own temporaries). A folder that was there already is the user's and stays, with the files
    written into it (each whole). A made folder that holds anything else (another writer's file) stays too. The
    exception always propagates.
    """
    made = []
    p = Path(folder).absolute()
    while not os.path.lexists(p) and p != p.parent:
        made.append(p)
        p = p.parent
    written: list[Path] = []
    try:
        yield written
    except BaseException:
        if made:
            top = made[-1]
            for f in written:
                if Path(f).absolute().is_relative_to(top):
                    with contextlib.suppress(OSError):
                        os.unlink(f)
            for d in made:  # deepest first; a folder not empty stays (rmdir refuses)
                with contextlib.suppress(OSError):
                    os.rmdir(d)
        raise


_WRITE_ERRNOS = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EROFS, errno.EACCES, errno.EPERM, errno.EIO,
                 errno.ENOENT, errno.ENOTDIR)


def _why(exc: BaseException, tmp: str | None) -> str:
    """The reason a write failed, in the system's words, without the temporary file's name.

    OpenEXR raises ``RuntimeError('Failed to write pixel data to image file "<tmp>". No space
    left on device.')``: a system reason found in such a message is given alone.
    """
    if isinstance(exc, OSError) and exc.errno is not None and exc.strerror:
        return exc.strerror
    text = str(exc) or type(exc).__name__
    for code in _WRITE_ERRNOS:
        if os.strerror(code) in text:
            return os.strerror(code)
    if tmp:
        text = text.replace(f'"{tmp}"', "the file").replace(tmp, "the file")
    return text.strip().rstrip(".")


def atomic_write(path: Path, encode: Callable[[str], None], exclusive: bool = False,
                 next_name: Callable[[Path], Path | None] | None = None) -> Path:
    """Run ``encode(tmp_name)`` on a temporary sibling of ``path``, then move it onto ``path``.

    With ``exclusive``, an existing ``path`` is never replaced, even one another process made
    after the caller chose the name: the finished file is hard-linked to ``path``, which fails
    when the name is taken, raising :class:`OutputExistsError` (on a file system without hard
    links, a check just before the move). ``next_name(taken)`` then gives another name in the same folder to
    publish the same encoded file under (it is not encoded again; same folder and extension), or None to give
    up; the path published is returned.

    Any failure of the encoder or of the file system (disk full, permissions, a folder that
    cannot be made) raises :class:`OutputError` naming ``path``; the temporary file is removed
    and an existing ``path`` is untouched. An interrupt (KeyboardInterrupt, or SIGTERM turned
    into one by the CLI) removes the temporary file too and propagates. Stale temporaries of
    killed earlier writes to ``path`` are removed first (:func:`remove_stale_temporaries`).
    """
    path = Path(path)
    tmp = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        remove_stale_temporaries(path)
        # a signal between creating the file and knowing its name would leak it: hold signals meanwhile
        blocked = _block_signals()
        try:
            fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=temporary_prefix(path), suffix=path.suffix)
        finally:
            _unblock_signals(blocked)
        os.close(fd)
        encode(tmp)
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        if path.exists():
            mode = path.stat().st_mode & 0o7777
        else:
            umask = os.umask(0o022)
            os.umask(umask)
            mode = 0o666 & ~umask
        os.chmod(tmp, mode)
        if exclusive:
            path = _publish_under_a_free_name(tmp, path, next_name)
        else:
            os.replace(tmp, path)
    except BaseException as exc:
        if tmp is not None:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
        if isinstance(exc, (BokehrayError, KeyboardInterrupt, SystemExit, GeneratorExit)):
            raise
        if isinstance(exc, MemoryError):
            raise ResourceError(f"cannot write {path}: ran out of memory while encoding it") from None
        if isinstance(exc, Exception):
            raise OutputError(f"cannot write {path}: {_why(exc, tmp)}") from exc
        raise
    return path


def _publish_under_a_free_name(tmp: str, path: Path, next_name: Callable[[Path], Path | None] | None) -> Path:
    """:func:`_publish_new` under ``path``, or where it is taken under ``next_name(path)`` and so on; the path used."""
    while True:
        try:
            _publish_new(tmp, path)
            return path
        except OutputExistsError:
            other = None if next_name is None else next_name(path)
            if other is None:
                raise
            if Path(other).parent != path.parent or Path(other).suffix != path.suffix:
                raise OutputError(f"cannot write {other}: the file was encoded as {path.suffix} in "
                                  f"{path.parent}") from None
            path = Path(other)


def _publish_new(tmp: str, path: Path) -> None:
    """Move ``tmp`` onto ``path`` only if nothing is there, not even a dangling link (atomically where the file system
    has hard links; elsewhere a check just before the move)."""
    taken = OutputExistsError(f"cannot write {path}: a file of that name was made meanwhile")
    try:
        os.link(tmp, path)
    except FileExistsError:
        raise taken from None
    except OSError:  # no hard links here (FAT, some FUSE and network file systems: EPERM, ENOTSUP, EINVAL, ENOSYS)
        if os.path.lexists(path):
            raise taken from None
        os.replace(tmp, path)
        return
    with contextlib.suppress(OSError):  # the file is published; at worst its hidden second name stays
        os.unlink(tmp)


def _block_signals() -> set[int] | None:
    if not hasattr(signal, "pthread_sigmask"):
        return None
    return signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT, signal.SIGTERM, signal.SIGHUP})


def _unblock_signals(previous: set[int] | None) -> None:
    if previous is not None:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)


def remove_stale_outputs(folder: Path, names: Iterable[str]) -> int:
    """Remove what a worker killed mid-write left next to the outputs ``names`` of ``folder``.

    :func:`atomic_write` writes ``.<name>.tmp-...<ext>`` (a long name shortened: :func:`temporary_stem`) and the BLB writer ``.<name>.tmp-<pid>-...``
    before renaming onto ``<name>``; a killed process leaves them. Call this when no task of the run is in flight.
    Returns how many were removed.
    """
    if not folder.is_dir():
        return 0
    wanted = {temporary_stem(n): n for n in names} | {n: n for n in names}
    removed = 0
    for entry in folder.iterdir():
        if not entry.name.startswith("."):
            continue
        parts = entry.name[1:].split(".")  # ".<name>.<rest>": <name> may hold dots itself
        name = next((wanted[n] for n in (".".join(parts[:k]) for k in range(1, len(parts))) if n in wanted), None)
        if name is not None:
            if ".old-" in entry.name and not (folder / name).exists():
                continue  # the previous version, moved aside by an overwrite that did not finish: keep it
            if entry.is_dir() and not entry.is_symlink():
                shutil.rmtree(entry, ignore_errors=True)
            else:
                entry.unlink(missing_ok=True)
            removed += 1
    return removed
