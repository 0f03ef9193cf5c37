"""Writing output files so that a failure never leaves a half-written file behind.

Every file a command writes goes through :class:`Outputs`: each file is first written under a
temporary name in its own directory, flushed and fsynced, and only when every file of the set
is complete are they put in place (:meth:`Outputs.commit`). A full disk, a permission problem
or an exception half-way leaves what was there before and no temporary file; the ``OSError``
becomes one :class:`~fbgforce.errors.InputError` line naming the file (exit status 2 in the
CLI).

The commit of a set of files is not one atomic step: ``os.replace`` swaps one file at a time.
So that a process killed between two renames never leaves files of two sets side by side
(an old ``model.json`` with new ``weights.npz`` would load as a model nobody trained), a set
of several files first removes every old file it replaces, in the reverse of the order it
renames them (so a model's ``model.json``, written last, goes first), and only then renames
the new files in, in order. A reader therefore sees, at every moment: the complete old set;
an incomplete set (a file missing, which every loader refuses naming it); or the complete new
set. A killed commit can leave the incomplete set (and temporary files, which no command
reads) for good: the command is run again. One file alone is replaced by one ``os.replace``:
old or new, never missing (docs/cli.md, "What a reader sees during a commit").

:func:`check_output_dir` and :func:`check_output_file` try the location before long work
starts (training, reports), so that a read-only or impossible ``--out`` fails at once rather
than after minutes of computing.
"""
from __future__ import annotations

import contextlib
import errno
import hashlib
import os
import tempfile
from pathlib import Path
from typing import IO, Any, Callable, Iterator

from fbgforce.errors import InputError

#: Prefix of temporary files; a crash between write and rename (power loss) leaves files with
#: this prefix, which no command reads.
TMP_PREFIX = ".fbgforce-tmp-"
#: The process's umask (read once: os.umask can only be read by setting it), so that renamed
#: files get the permissions a plain open() would have given them, not mkstemp's 0600.
_UMASK = os.umask(0o022)
os.umask(_UMASK)


def write_error(exc: OSError, path: str | Path, flag: str | None = None) -> InputError:
    """The one-line error of a failed write (``exc``) to ``path``."""
    reason = exc.strerror or str(exc)
    if exc.errno == errno.ENOSPC:
        reason = "no space left on device; nothing was written, the previous file is kept"
    elif exc.errno in (errno.EACCES, errno.EPERM, errno.EROFS):
        reason = f"cannot write ({reason}); choose a writable location"
    elif exc.errno == errno.ENOTDIR:
        reason = "a path component is a file, not a directory"
    elif exc.errno == errno.EISDIR:
        reason = "is a directory; give a file name"
    else:
        reason = f"cannot write: {reason}"
    return InputError(reason, path=str(path), column=flag)


def _mkdir(directory: Path, flag: str | None) -> None:
    try:
        directory.mkdir(parents=True, exist_ok=True)
    except FileExistsError:
        raise InputError("is a file, not a directory", path=str(directory), column=flag) from None
    except OSError as exc:
        raise write_error(exc, directory, flag) from None


class Outputs:
    """A set of files written all or nothing.

    Use as a context manager; files are opened with :meth:`open` (or written with
    :meth:`write_bytes`, :meth:`write_text`) and appear under their names only when the
    ``with`` block ends without an exception::

        with Outputs(flag="--out") as out:
            out.write_text(root / "model.json", text)
            with out.open(root / "weights.npz", "wb") as fh:
                np.savez(fh, **arrays)

    Parameters
    ----------
    flag
        The command-line option that named the location, for the error message.
    """

    def __init__(self, flag: str | None = None) -> None:
        self.flag = flag
        self._pending: list[tuple[str, Path]] = []

    def __enter__(self) -> "Outputs":
        return self

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> None:
        if exc_type is not None:
            self.discard()
            if isinstance(exc, OSError) and getattr(exc, "filename", None):
                raise write_error(exc, exc.filename, self.flag) from None
            return
        self.commit()

    @contextlib.contextmanager
    def open(self, path: str | Path, mode: str = "w", **kw: Any) -> Iterator[IO[Any]]:
        """A file object writing ``path``'s temporary stand-in (``mode`` "w" or "wb")."""
        if mode not in ("w", "wb"):
            raise ValueError(f"mode must be 'w' or 'wb', not {mode!r}")
        final = Path(path)
        _mkdir(final.parent, self.flag)
        if final.is_dir():
            raise InputError("is a directory; give a file name", path=str(final), column=self.flag)
        try:
            fd, tmp = tempfile.mkstemp(prefix=TMP_PREFIX, suffix=final.suffix, dir=final.parent)
        except OSError as exc:
            raise write_error(exc, final, self.flag) from None
        self._pending.append((tmp, final))
        try:
            with os.fdopen(fd, mode, **kw) as fh:
                yield fh
                fh.flush()
                os.fsync(fh.fileno())
        except OSError as exc:
            raise write_error(exc, final, self.flag) from None

    def write_bytes(self, path: str | Path, data: bytes) -> None:
        with self.open(path, "wb") as fh:
            fh.write(data)

    def write_text(self, path: str | Path, text: str) -> None:
        with self.open(path, "w", encoding="utf-8", newline="\n") as fh:
            fh.write(text)

    def write_with(self, path: str | Path, writer: Callable[[IO[bytes]], Any]) -> None:
        """Let ``writer`` (``np.savez``, ``onnx.save``, ``Figure.savefig``...) fill the file."""
        with self.open(path, "wb") as fh:
            writer(fh)

    def commit(self) -> None:
        """Put every finished file in place (module docstring): one file by ``os.replace``;
        several by removing the old files they replace, the last to be renamed first, and
        then renaming them in, in the order they were opened. The directories are fsynced
        after each phase, so that a power loss keeps the order too."""
        pending, self._pending = self._pending, []
        done = 0
        final = pending[0][1] if pending else Path()
        try:
            for tmp, final in pending:
                os.chmod(tmp, 0o666 & ~_UMASK)
            if len(pending) > 1:
                for _, final in reversed(pending):
                    with contextlib.suppress(FileNotFoundError):
                        os.unlink(final)
                _fsync_dirs(pending)
            for tmp, final in pending:
                os.replace(tmp, final)
                done += 1
            _fsync_dirs(pending)
        except OSError as exc:
            for rest, _ in pending[done:]:
                _unlink(rest)
            raise write_error(exc, final, self.flag) from None

    def discard(self) -> None:
        """Remove every temporary file (the final names keep what they held)."""
        for tmp, _ in self._pending:
            _unlink(tmp)
        self._pending = []


def _unlink(path: str) -> None:
    with contextlib.suppress(OSError):
        os.unlink(path)


def _fsync_dirs(pending: list[tuple[str, Path]]) -> None:
    """fsync the directories of ``pending``'s files (their entries: removals and renames);
    a file system that cannot fsync a directory is left as it is."""
    for directory in dict.fromkeys(final.parent for _, final in pending):
        try:
            fd = os.open(directory, os.O_RDONLY)
        except OSError:
            continue
        try:
            os.fsync(fd)
        except OSError:
            pass
        finally:
            os.close(fd)


def write_text(path: str | Path, text: str, flag: str | None = None) -> None:
    """Write one text file atomically (see :class:`Outputs`)."""
    with Outputs(flag) as out:
        out.write_text(path, text)


def write_bytes(path: str | Path, data: bytes, flag: str | None = None) -> None:
    """Write one binary file atomically (see :class:`Outputs`)."""
    with Outputs(flag) as out:
        out.write_bytes(path, data)


def write_with(path: str | Path, writer: Callable[[IO[bytes]], Any], flag: str | None = None) -> None:
    """Write one file atomically through ``writer(file_object)`` (see :class:`Outputs`)."""
    with Outputs(flag) as out:
        out.write_with(path, writer)


def _nearest_existing(path: Path) -> Path:
    p = path.absolute()
    while not p.exists() and p != p.parent:
        p = p.parent
    return p


def check_output_dir(directory: str | Path, flag: str | None = None) -> None:
    """Refuse now a directory that files could not be written into later.

    The directory need not exist; its nearest existing ancestor must be a directory in which a
    file can be created (tried with a temporary file, removed again), so a read-only
    location, a full disk or a path below a file fails before any long work.
    """
    d = Path(directory)
    if d.exists() and not d.is_dir():
        raise InputError("is a file, not a directory", path=str(d), column=flag)
    base = _nearest_existing(d)
    if not base.is_dir():
        raise InputError(f"cannot be created: {base} is a file, not a directory", path=str(d),
                         column=flag)
    try:
        fd, tmp = tempfile.mkstemp(prefix=TMP_PREFIX, dir=base)
    except OSError as exc:
        raise write_error(exc, d, flag) from None
    os.close(fd)
    _unlink(tmp)


def check_input_file(path: str | Path, flag: str | None = None) -> None:
    """Refuse a file to read that is missing or is a directory, saying which."""
    p = Path(path)
    if p.is_dir():
        raise InputError("is a directory, not a file", path=str(p), column=flag)
    if not p.is_file():
        raise InputError("no such file", path=str(p), column=flag)


def check_output_file(path: str | Path, flag: str | None = None) -> None:
    """:func:`check_output_dir` for the directory of a file to be written; the file itself
    must not be a directory."""
    p = Path(path)
    if p.is_dir():
        raise InputError("is a directory; give a file name", path=str(p), column=flag)
    check_output_dir(p.parent, flag)


def file_sha256(path: str | Path) -> str:
    """SHA-256 of a file's bytes (read in pieces of 1 MiB), as hex."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()
