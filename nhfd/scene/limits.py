"""Bounds on what a scene file can make the loaders read, decompress and allocate (issue 32).

A scene file is untrusted input: the daemon loads what a client names, and a few kilobytes can
declare billions of Gaussians, inflate to gigabytes or point at `/dev/zero`. Every reader in
`nhfd.scene` therefore:

* refuses a declared Gaussian count above `max_gaussians` (`check_count`; the default,
  `MAX_GAUSSIANS`, is the default of `[daemon.paths] max_gaussians`) before it allocates anything
  sized by that count;
* reads only regular files (`open_regular`: a FIFO would block `open()` forever, `/dev/zero`
  never ends, a directory is not data), and reads them with a byte cap (`read_capped`);
* reads and decompresses at most what the declared count needs plus a small margin
  (`GzipStream`, `read_zstd`): a bomb is cut off after that, not inflated;
* resolves the files a scene names (glTF buffer URIs, SOG image names) inside the scene file's
  own folder (`contained`), symlinks included: a reference that leaves it is refused by name.
"""

from __future__ import annotations

import os
import stat
import zlib
from pathlib import Path
from typing import BinaryIO

from nhfd.scene.gaussians import SceneFileError

__all__ = [
    "MARGIN_BYTES",
    "MAX_GAUSSIANS",
    "MAX_GAUSSIANS_LIMIT",
    "MAX_JSON_BYTES",
    "GzipStream",
    "check_count",
    "check_max_gaussians",
    "contained",
    "open_regular",
    "read_capped",
    "read_zstd",
]

# The default maximum number of Gaussians a file may declare: the default of the daemon's
# `[daemon.paths] max_gaussians` (nhfd.config.DaemonSettings), so a file `nhfd scene info` reads is
# one the daemon, left at its defaults, reads too.
MAX_GAUSSIANS = 20_000_000
# The largest value `max_gaussians` may be given (the setting's own upper bound).
MAX_GAUSSIANS_LIMIT = 1_000_000_000
# Slack over the bytes a declared count needs: headers, padding, a format's small extras.
MARGIN_BYTES = 1 << 16
# A glTF document, a SOG meta.json or a .glb JSON chunk: real ones are a few kilobytes (a
# glTF with data: URIs holds its buffers too, so this also bounds those).
MAX_JSON_BYTES = 64 << 20
# Compressed input is read in pieces of this size, so a bomb's input is never held whole.
_READ_CHUNK = 1 << 20


def check_max_gaussians(max_gaussians: int) -> int:
    """`max_gaussians` itself, checked: an int in [1, MAX_GAUSSIANS_LIMIT], else ValueError."""
    if (isinstance(max_gaussians, bool) or not isinstance(max_gaussians, int)
            or not 1 <= max_gaussians <= MAX_GAUSSIANS_LIMIT):
        raise ValueError(f"max_gaussians = {max_gaussians!r}; allowed: an integer in "
                         f"[1, {MAX_GAUSSIANS_LIMIT:,}]")
    return max_gaussians


def check_count(path: Path | str, what: str, count: object, max_gaussians: int,
                unit: str = "Gaussians") -> int:
    """`count` (what the file declares, described by `what`, counting `unit`) if it is an int
    in [0, max_gaussians]; otherwise SceneFileError naming the file, the count and the limit."""
    if isinstance(count, bool) or not isinstance(count, int) or count < 0:
        raise SceneFileError(f"{path}: {what} is {count!r}, not a count of {unit} "
                             f"(allowed: 0 to {max_gaussians:,})")
    if count > max_gaussians:
        raise SceneFileError(
            f"{path}: {what} declares {count:,} {unit}, more than the limit of "
            f"{max_gaussians:,} Gaussians (max_gaussians; the daemon's [daemon.paths] "
            "max_gaussians)"
        )
    return count


def _kind(mode: int) -> str:
    for test, name in ((stat.S_ISDIR, "directory"), (stat.S_ISFIFO, "FIFO"),
                       (stat.S_ISCHR, "character device"), (stat.S_ISBLK, "block device"),
                       (stat.S_ISSOCK, "socket")):
        if test(mode):
            return name
    return "special file"


def _require_regular(scene: Path | str, what: str, target: Path, mode: int) -> None:
    if not stat.S_ISREG(mode):
        named = what if Path(target) == Path(scene) else f"{what} ({target})"
        raise SceneFileError(f"{scene}: {named} is a {_kind(mode)}, not a regular file; only "
                             "regular files are read")


def open_regular(target: Path, scene: Path | str, what: str) -> BinaryIO:
    """`target` opened for reading if it is a regular file (symlinks followed); otherwise
    SceneFileError naming `scene` and `what`. A missing or unreadable file raises OSError as
    open() words it.

    The kind is checked with stat before opening, because opening a FIFO blocks until a writer
    comes; the open is non-blocking and checks the kind again on the descriptor, so a file
    swapped for a FIFO or a device in between is refused too."""
    _require_regular(scene, what, target, os.stat(target).st_mode)
    fd = os.open(target, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    try:
        _require_regular(scene, what, target, os.fstat(fd).st_mode)
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def read_capped(target: Path, scene: Path | str, what: str, cap_bytes: int,
                why: str = "") -> bytes:
    """The whole of the regular file `target`, if it holds at most `cap_bytes` bytes; otherwise
    SceneFileError naming the size and the cap (`why` says where the cap comes from). Reads at
    most cap_bytes + 1 bytes even if the file grows meanwhile."""
    with open_regular(target, scene, what) as f:
        size = os.fstat(f.fileno()).st_size
        data = f.read(cap_bytes + 1) if size <= cap_bytes else b""
    if size > cap_bytes or len(data) > cap_bytes:
        raise SceneFileError(f"{scene}: {what} is {max(size, len(data)):,} bytes, more than the "
                             f"{cap_bytes:,} bytes allowed{f' ({why})' if why else ''}")
    return data


def contained(folder: Path, ref: str, scene: Path | str, what: str) -> Path:
    """The file that `ref` (a relative name from a scene file) names in `folder`, resolved,
    symlinks included; SceneFileError naming the reference when it resolves outside `folder`
    (`../`, an absolute path, a symlink out) or cannot be resolved. Only a name inside the
    scene's own folder is read: the daemon checks the scene's path against daemon.paths.scene_dirs,
    and a reference must not reach past that check."""
    try:
        base = folder.resolve()
        target = (folder / ref).resolve()
    except (OSError, ValueError, RuntimeError) as e:  # NUL in the name, a symlink loop
        raise SceneFileError(f"{scene}: {what} {ref!r} cannot be resolved ({e})") from e
    if not target.is_relative_to(base):
        raise SceneFileError(f"{scene}: {what} {ref!r} resolves to {target}, outside the "
                             f"scene's folder {base}; only files inside it are read")
    return target


class GzipStream:
    """A gzip file inflated in pieces, never more output than asked for: `take(n)` returns the
    next n bytes (fewer only where the stream ends). Concatenated members are read as one
    stream, as `gzip.decompress` does. At most `max_input` compressed bytes are read (raise it
    once the header says how much data to expect), so a stream of empty blocks ends too.

    Raises EOFError where the compressed data ends before its end-of-stream marker, zlib.error
    where it is corrupt (a wrong CRC included) and SceneFileError past `max_input`."""

    def __init__(self, f: BinaryIO, scene: Path | str, max_input: int = MARGIN_BYTES) -> None:
        self.f, self.scene, self.max_input = f, scene, max_input
        self.read_bytes = 0
        self._d = zlib.decompressobj(wbits=16 + zlib.MAX_WBITS)  # gzip header and trailer
        self._in = b""

    def _read(self) -> bytes:
        if self.read_bytes >= self.max_input:
            more = self.f.read(1)
            if more:
                raise SceneFileError(
                    f"{self.scene}: the compressed data is longer than the {self.max_input:,} "
                    "bytes its header's Gaussians can need")
            return b""
        data = self.f.read(min(_READ_CHUNK, self.max_input - self.read_bytes))
        self.read_bytes += len(data)
        return data

    def take(self, n: int) -> bytearray:
        """The next `n` inflated bytes (fewer only where the stream ends); EOFError where the
        data ends before the end-of-stream marker."""
        out = bytearray()
        while len(out) < n:
            if self._d.eof:  # a member ended: another may follow, or the stream ends here
                more = self._d.unused_data or self._read()
                if not more:
                    break
                self._d = zlib.decompressobj(wbits=16 + zlib.MAX_WBITS)
                self._in = more
            elif not self._in:
                self._in = self._read()
                if not self._in:
                    raise EOFError("compressed data ended before the end-of-stream marker "
                                   "was reached")
            out += self._d.decompress(self._in, n - len(out))  # max_length > 0: capped
            self._in = self._d.unconsumed_tail
        return out  # not copied to bytes: a block of a large scene is hundreds of MB


def read_zstd(data: bytes | memoryview, size: int) -> bytes:
    """One zstd frame of `data` inflated to at most size + 1 bytes (the caller compares the
    length with `size`). Streamed: `ZstdDecompressor.decompress` would allocate whatever the
    frame's header claims, whatever its `max_output_size`."""
    import zstandard  # only .spz v4 needs it: loaded when one is read, not on import

    reader = zstandard.ZstdDecompressor().stream_reader(data)
    out = bytearray()
    while len(out) <= size:
        piece = reader.read(min(size + 1 - len(out), _READ_CHUNK * 16))
        if not piece:
            break
        out += piece
    return bytes(out)
