"""Atomic file writes: write to a temporary sibling, then rename it over the target.

Stages communicate through files and later stages (and cached reruns) trust whatever file exists at a
path. A crash, a kill or a full disk in the middle of a write must therefore never leave a half-written
file under the final name: either the old file stays intact or the complete new one replaces it.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import os
import secrets
import shutil
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any


def _fsync_file(path: Path) -> None:
    """Flush a written file to disk so the rename never exposes a name whose data is still in cache."""
    with contextlib.suppress(OSError), open(path, "rb") as f:
        os.fsync(f.fileno())


def _fsync_dir(path: Path) -> None:
    """Persist the rename itself (a directory entry); best effort, not supported on every platform."""
    with contextlib.suppress(OSError):
        fd = os.open(path, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary path next to `path`; on clean exit move it onto `path`, on error delete it.

    The temporary name is `.<name>.tmp-<pid>-<random><suffix>`: hidden, unique per process and call, in
    the same directory (so `os.replace` is an atomic rename on the same filesystem) and with the same
    suffix (so libraries that pick the format from the extension still work). Parent directories are
    created. The caller writes the file at the yielded path by any means (a library, `open`, ...);
    writing nothing there is an error, not a silent no-op.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}-{secrets.token_hex(4)}{path.suffix}")
    try:
        yield tmp
        if not tmp.exists():
            raise FileNotFoundError(f"{path}: nothing was written to the temporary file {tmp.name}")
        _fsync_file(tmp)
        os.replace(tmp, path)
        _fsync_dir(path.parent)
    finally:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes) -> Path:
    """Write `data` to `path` atomically (see `atomic_path`); returns the final path."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def atomic_write_text(path: str | os.PathLike[str], text: str, encoding: str = "utf-8") -> Path:
    """Write `text` to `path` atomically (see `atomic_path`); returns the final path."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding=encoding)
    return Path(path)


@contextlib.contextmanager
def atomic_directory(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a fresh temporary sibling directory; on clean exit it replaces `path` whole.

    For stages that write many files at once (preprocessed shards): a crash leaves the previous
    complete output in place, and a rerun never mixes its files with stale ones from an earlier run.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}-{secrets.token_hex(4)}")
    old = path.with_name(f".{path.name}.old-{os.getpid()}-{secrets.token_hex(4)}")
    tmp.mkdir()
    try:
        yield tmp
        if path.exists():
            os.replace(path, old)
        os.replace(tmp, path)
        _fsync_dir(path.parent)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
        shutil.rmtree(old, ignore_errors=True)


def atomic_write_json(path: str | os.PathLike[str], obj) -> Path:
    """Write `obj` as indented JSON atomically (non-JSON leaves such as paths become strings)."""
    return atomic_write_text(path, json.dumps(obj, indent=1, default=str) + "\n")


def atomic_write_csv(
    path: str | os.PathLike[str], rows: Sequence[Mapping[str, Any]], columns: Sequence[str] | None = None
) -> Path:
    """Write dict rows as CSV (columns: `columns`, else the first row's keys), atomically."""
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=list(columns or rows[0]), lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    return atomic_write_text(path, buffer.getvalue())
