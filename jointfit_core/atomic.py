"""Files written so that a reader (or a crash) never sees half of one.

:func:`write_atomic` writes to a temporary file in the target's directory,
flushes it to disk, and renames it over the target in one step
(``os.replace``, atomic on POSIX and Windows for files on one file system). At
every instant the target is the complete old or the complete new file, also
when the process is killed (SIGKILL) or the machine stops in between. The
optional backup is made with a hard link (a copy where links are not
supported) before the rename, so the target never disappears.
"""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import tempfile
import time
from pathlib import Path

__all__ = ["write_atomic", "write_all_or_nothing", "remove_stale_temporaries", "STALE_TEMPORARY_S"]

#: A temporary file of :func:`write_atomic` older than this (s) belongs to a write that died.
STALE_TEMPORARY_S = 5.0


def _fsync_dir(directory: Path) -> None:
    """Make a rename in ``directory`` durable (no-op where directories cannot be opened)."""
    with contextlib.suppress(OSError):
        fd = os.open(directory, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def _temporary_sibling(target: Path, suffix: str) -> Path:
    fd, name = tempfile.mkstemp(prefix=f".{target.name}.", suffix=suffix, dir=target.parent)
    os.close(fd)
    return Path(name)


def write_atomic(path: str | os.PathLike[str], content: bytes | str, *, keep_backup: bool = False) -> Path:
    """Replace a file's content atomically.

    Parameters
    ----------
    path : str or os.PathLike
        The target; its directory is created when missing. A symbolic link is written
        through: the file it points to is replaced (and backed up beside it), the link
        stays (a calibration kept in a shared place and linked into a workspace).
    content : bytes or str
        The new content (str is written as UTF-8).
    keep_backup : bool
        Keep the previous file, if any, as ``<path>.bak`` (replacing an older backup).

    Returns
    -------
    Path
        The written path (the link's target for a symbolic link).

    Raises
    ------
    OSError
        The directory or the file cannot be written; the target is then
        unchanged and no temporary file is left behind.
    """
    target = Path(os.path.realpath(path)) if os.path.islink(path) else Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    data = content.encode("utf-8") if isinstance(content, str) else bytes(content)
    tmp = _temporary_sibling(target, ".tmp")
    try:
        # mkstemp makes the file 0600: give it the old file's mode, or the usual umask-based one.
        try:
            mode = target.stat().st_mode & 0o7777
        except OSError:
            umask = os.umask(0)
            os.umask(umask)
            mode = 0o666 & ~umask
        os.chmod(tmp, mode)
        with open(tmp, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        if keep_backup and target.exists():
            bak_tmp = _temporary_sibling(target, ".bak.tmp")
            try:
                bak_tmp.unlink()
                try:
                    os.link(target, bak_tmp)
                except OSError:
                    shutil.copy2(target, bak_tmp)
                os.replace(bak_tmp, target.with_name(target.name + ".bak"))
            finally:
                bak_tmp.unlink(missing_ok=True)
        os.replace(tmp, target)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    _fsync_dir(target.parent)
    return target


def remove_stale_temporaries(path: str | os.PathLike[str], older_than_s: float = STALE_TEMPORARY_S) -> list[Path]:
    """Delete the temporary files that writes of ``path`` killed mid-way left beside it; return them.

    Only :func:`write_atomic`'s own names for this target
    (``.<name>.XXXXXXXX.tmp`` and ``.<name>.XXXXXXXX.bak.tmp``, from
    :func:`tempfile.mkstemp`), only in its directory, and only those not
    modified for ``older_than_s`` seconds (a write under way elsewhere keeps
    its file). A SIGKILL during a write never leaves a partial target, but it
    leaves such a file, and they accumulate.
    """
    target = Path(path)
    pattern = re.compile(rf"^\.{re.escape(target.name)}\.[A-Za-z0-9_]{{8}}(\.bak)?\.tmp$")
    removed: list[Path] = []
    try:
        entries = list(os.scandir(target.parent))
    except OSError:
        return removed
    now = time.time()
    for entry in entries:
        if not pattern.match(entry.name):
            continue
        try:
            if entry.is_file(follow_symlinks=False) and now - entry.stat(follow_symlinks=False).st_mtime > older_than_s:
                os.unlink(entry.path)
                removed.append(Path(entry.path))
        except OSError:
            continue
    return removed


def write_all_or_nothing(directory: str | os.PathLike[str], files: dict[str, bytes | str]) -> Path:
    """Write several files into ``directory`` so that a failure or an interrupt leaves none of them.

    Everything is written (and flushed to disk) into a hidden temporary
    directory beside ``directory`` first. A new ``directory`` is then that
    temporary directory, renamed in one step: all the files or none. Into an
    existing ``directory`` (other files of the user's are kept) each file is
    moved with :func:`os.replace` once all are complete, so a full disk or
    Ctrl-C while writing leaves the old files as they were.

    Parameters
    ----------
    directory : str or os.PathLike
    files : dict of str to bytes or str
        File name (no directories) to content (str as UTF-8).

    Returns
    -------
    Path
        ``directory``.

    Raises
    ------
    OSError
        Nothing was written then (the temporary directory is removed).
    """
    target = Path(directory)
    target.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{target.name}.", suffix=".partial", dir=target.parent))
    try:
        for name, content in files.items():
            if Path(name).name != name:
                raise ValueError(f"write_all_or_nothing: {name!r} is not a plain file name")
            data = content.encode("utf-8") if isinstance(content, str) else bytes(content)
            with open(staging / name, "wb") as fh:
                fh.write(data)
                fh.flush()
                os.fsync(fh.fileno())
        os.chmod(staging, 0o777 & ~_umask())
        if not target.exists():
            os.rename(staging, target)
        else:
            for name in files:
                os.replace(staging / name, target / name)
            staging.rmdir()
        _fsync_dir(target.parent)
        return target
    finally:
        if staging.exists():
            shutil.rmtree(staging, ignore_errors=True)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask
