"""Outputs: checked before the work starts, written under a temporary name and renamed into place, so a failed or
interrupted run leaves nothing half-written.

* :func:`check_output_file` / :func:`check_output_dir` refuse, before any computation, an output that cannot be
  written: a folder where a file is meant, a file where a folder is meant, a path under a file, a place where this
  process may not create files (the check creates and removes a probe file, so read-only mounts and permissions are
  caught whoever runs it, root included). The message names the option and the path.
* :func:`atomic_path` / :func:`write_text_atomic` write beside the target under a hidden ``.NAME.*.part`` name and
  rename on success; on any exception (Ctrl-C and SIGTERM included, see :mod:`magnav_ins.core.signals`) the
  temporary file is removed. Operating-system failures of the rename or the folder creation become
  :class:`~magnav_ins.core.errors.OutputError` naming the path.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path

from .errors import OutputError


def _label(path: Path, option: str | None) -> str:
    return f"{option} {path}" if option else str(path)


def _nearest_existing(path: Path) -> Path:
    """``path`` itself or its nearest existing ancestor (the current folder for a bare relative name)."""
    for p in (path, *path.parents):
        if p.exists():
            return p
    return Path(".")


def _probe_writable(folder: Path, label: str) -> None:
    try:
        with tempfile.TemporaryFile(dir=folder, prefix=".magnav-write-probe-"):
            pass
    except OSError as exc:
        raise OutputError(f"{label}: cannot create files in {folder} ({exc.strerror or exc})") from None


def _check_parents(path: Path, label: str) -> Path:
    """The nearest existing ancestor of ``path``, which must be a writable folder."""
    base = _nearest_existing(path.parent)
    if not base.is_dir():
        raise OutputError(f"{label}: {base} is a file, not a folder")
    _probe_writable(base, label)
    return base


def check_output_file(path: str | os.PathLike[str], option: str | None = "--out") -> Path:
    """Refuse an output *file* that cannot be written (see the module docstring); an existing file is fine (it is
    replaced at the end). ``option`` names the command-line option in the message. Returns ``Path(path)``."""
    path = Path(path)
    label = _label(path, option)
    if path.is_dir():
        raise OutputError(f"{label}: is a folder; expected a file name")
    if path.exists() and not path.is_file():
        raise OutputError(f"{label}: exists and is not a regular file")
    _check_parents(path, label)
    return path


def check_output_dir(path: str | os.PathLike[str], option: str | None = "--out") -> Path:
    """Refuse an output *folder* that cannot be written: an existing file, a path under a file, a read-only
    place. The folder need not exist (it is created when the outputs are written). Returns ``Path(path)``."""
    path = Path(path)
    label = _label(path, option)
    if path.exists():
        if not path.is_dir():
            raise OutputError(f"{label}: is a file; expected a folder")
        _probe_writable(path, label)
    else:
        _check_parents(path, label)
    return path


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success rename it to ``path``, on error delete it.

    Use for writers that want a file name (``xarray.to_netcdf``, ``savefig``)::

        with atomic_path(out) as tmp:
            fig.savefig(tmp, format="png")
    """
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".part", dir=path.parent)
    except OSError as exc:
        raise OutputError(f"{path}: cannot write here ({exc.strerror or exc})") from None
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        if tmp_path.exists():  # mkstemp makes 0600 files: give the output the usual umask-based mode
            umask = os.umask(0)
            os.umask(umask)
            os.chmod(tmp_path, 0o666 & ~umask)
        try:
            os.replace(tmp_path, path)
        except OSError as exc:
            raise OutputError(f"{path}: cannot be replaced ({exc.strerror or exc})") from None
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp_path.unlink()
        raise


def write_text_atomic(path: str | os.PathLike[str], text: str) -> None:
    """Write ``text`` to ``path`` atomically (UTF-8)."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
