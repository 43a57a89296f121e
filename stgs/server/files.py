"""File resolution: which file under ROOT a URL path names (never outside ROOT), its validators, openat2."""

from __future__ import annotations

import ctypes
import errno
import functools
import math
import os
import stat
import sys
import time
from pathlib import Path

from stgs.server.config import CONTENT_TYPES


def servable_parts(url_path: str) -> list[str] | None:
    """The path components of a URL path that may name a served file, or None: no NUL or backslash, no ".",
    ".." or hidden names, and a served extension. What the file system then says is the caller's part."""
    if "\x00" in url_path or "\\" in url_path:
        return None
    parts = url_path.split("/")[1:]  # an empty part: "//" or a trailing slash, which no file has
    if not parts or any(not p or p[0] == "." for p in parts):  # ".", ".." and hidden names
        return None
    if os.path.splitext(parts[-1])[1] not in CONTENT_TYPES:
        return None
    return parts


def resolve_path(root: Path, url_path: str) -> str | None:
    """The file under root that url_path names, or None (outside root, hidden, unknown type, missing).

    `root` must already be resolved. Without symlinks below root, one lstat per component decides; a symlink
    anywhere sends the path through realpath and a containment check. Plain strings, not pathlib: this
    runs for every request, and its Python is a measurable share of one.
    """
    parts = servable_parts(url_path)
    if parts is None:
        return None
    current = str(root).rstrip("/")
    for part in parts:
        current += "/" + part
        try:
            mode = os.lstat(current).st_mode
        except OSError:
            return None
        if stat.S_ISLNK(mode):
            return resolve_symlinked(root, root.joinpath(*parts))
    return current if stat.S_ISREG(mode) else None


def resolve_symlinked(root: Path, candidate: Path) -> str | None:
    try:
        real = candidate.resolve(strict=True)
    except (OSError, RuntimeError):
        return None
    if not real.is_relative_to(root) or not real.is_file() or real.suffix not in CONTENT_TYPES:
        return None  # a link may only lead to a servable file inside root
    return str(real)


def etag_of(size: int, mtime_ns: int) -> str:
    """A file version's entity tag, unquoted (aiohttp's FileResponse's form)."""
    return f"{mtime_ns:x}-{size:x}"


@functools.lru_cache(maxsize=4096)
def file_validators(size: int, mtime_ns: int, mtime: float) -> dict[str, str]:
    """Content-Length, ETag, Last-Modified and Accept-Ranges of a whole file, as aiohttp's FileResponse writes
    them (its property setters validate and format on every call; a segment's values repeat on every request)."""
    modified = time.strftime("%a, %d %b %Y %H:%M:%S GMT", time.gmtime(math.ceil(mtime)))
    return {"Content-Length": str(size), "ETag": f'"{etag_of(size, mtime_ns)}"', "Last-Modified": modified,
            "Accept-Ranges": "bytes"}


OPEN_FLAGS = os.O_RDONLY | os.O_CLOEXEC | os.O_NONBLOCK
"""O_NONBLOCK: opening a FIFO (or a device) put in the tree does not block; it is then refused as not regular.
Reads and sendfile of a regular file ignore the flag."""


def open_and_stat(path: str) -> tuple[int, os.stat_result]:
    """A descriptor and stat of the regular file at path; OSError (ENOENT) for anything else."""
    fd = os.open(path, OPEN_FLAGS)
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise FileNotFoundError(errno.ENOENT, "not a regular file", path)
        return fd, st
    except OSError:
        os.close(fd)
        raise


class BeneathOpener:
    """Opens files below one folder with openat2(2) and RESOLVE_BENEATH | RESOLVE_NO_SYMLINKS: one syscall in which
    the kernel refuses `..`, absolute paths and every symlink on the way (EXDEV, ELOOP). Nothing can swap a
    component for a symlink between a check and the open, as it could between resolve_path's lstats and a
    later open. Linux 5.6+; `for_root` gives None where the kernel (or a seccomp filter) lacks it."""

    SYS_OPENAT2 = 437  # one number on every Linux architecture
    RESOLVE = 0x02 | 0x04 | 0x08  # RESOLVE_NO_MAGICLINKS | RESOLVE_NO_SYMLINKS | RESOLVE_BENEATH

    class OpenHow(ctypes.Structure):
        _fields_ = [("flags", ctypes.c_uint64), ("mode", ctypes.c_uint64), ("resolve", ctypes.c_uint64)]

    def __init__(self, root_fd: int):
        libc = ctypes.CDLL(None, use_errno=True)
        self._syscall = libc.syscall
        self._syscall.restype = ctypes.c_long
        self._syscall.argtypes = [ctypes.c_long, ctypes.c_int, ctypes.c_char_p, ctypes.c_void_p, ctypes.c_size_t]
        self._how = self.OpenHow(OPEN_FLAGS, 0, self.RESOLVE)
        self._how_address = ctypes.addressof(self._how)
        self._how_size = ctypes.sizeof(self._how)
        self.root_fd = root_fd

    @classmethod
    def for_root(cls, root: Path) -> BeneathOpener | None:
        if not sys.platform.startswith("linux"):
            return None
        opener = cls(os.open(root, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC))
        try:
            os.close(opener.open("."))
        except OSError:  # ENOSYS: kernel before 5.6; EPERM: a seccomp profile that forbids it
            opener.close()
            return None
        return opener

    def open(self, relative: str) -> int:
        """A read-only descriptor of root/relative; OSError if missing, outside root or reached through a symlink."""
        fd = self._syscall(self.SYS_OPENAT2, self.root_fd, os.fsencode(relative), self._how_address, self._how_size)
        if fd < 0:
            err = ctypes.get_errno()
            raise OSError(err, os.strerror(err), relative)
        return fd

    def close(self) -> None:
        os.close(self.root_fd)
