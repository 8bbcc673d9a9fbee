"""Atomic file writes: a file is written to a temp sibling, fsynced and renamed onto its name, so
a reader sees the old file or the new one, never a half-written one."""

from __future__ import annotations

import os
import secrets
import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import polars as pl

__all__ = ["atomic_path", "write_parquet_atomic", "write_text_atomic", "temp_sibling", "remove_path"]


def temp_sibling(path: Path) -> Path:
    """A fresh temp name in ``path``'s directory: ``<name>.tmp-<pid>-<random>``."""
    return path.with_name(f"{path.name}.tmp-{os.getpid()}-{secrets.token_hex(6)}")


def _fsync_file(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _fsync_dir(path: Path) -> None:
    if os.name != "posix":  # pragma: no cover - directories cannot be opened on Windows
        return
    _fsync_file(path)


def remove_path(path: Path) -> None:
    """Remove a file or directory if present; never raise for a missing one."""
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        path.unlink(missing_ok=True)


@contextmanager
def atomic_path(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temp path next to ``path``; on success fsync and rename it onto ``path``.

    On an exception the temp file is removed and ``path`` is left untouched.
    The parent directory is created if missing.
    """
    final = Path(path)
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = temp_sibling(final)
    try:
        yield tmp
        _fsync_file(tmp)
        os.replace(tmp, final)
    except BaseException:
        remove_path(tmp)
        raise
    _fsync_dir(final.parent)


def write_parquet_atomic(frame: pl.DataFrame, path: str | os.PathLike[str], **kwargs: Any) -> Path:
    """Write ``frame`` to ``path`` as Parquet atomically; kwargs go to ``write_parquet``."""
    with atomic_path(path) as tmp:
        frame.write_parquet(tmp, **kwargs)
    return Path(path)


def write_text_atomic(path: str | os.PathLike[str], text: str, encoding: str = "utf-8") -> Path:
    """Write ``text`` to ``path`` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding=encoding)
    return Path(path)
