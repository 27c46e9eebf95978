"""Download a file into a cache with resume, atomic rename and integrity checks."""

from __future__ import annotations

import hashlib
import os
import shutil
import urllib.error
import urllib.request
from collections.abc import Callable
from pathlib import Path

from tqdm.auto import tqdm

from spoil_torchrl.data.episodes import DatasetError

CHUNK = 1 << 20


def sha256_of(path: str | os.PathLike) -> str:
    """Hex SHA-256 of a file, read in 1 MiB chunks.

    Examples:
        >>> import tempfile
        >>> path = Path(tempfile.mkdtemp()) / "data.bin"
        >>> _ = path.write_bytes(b"abc")
        >>> sha256_of(path)
        'ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad'
    """
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(CHUNK), b""):
            digest.update(block)
    return digest.hexdigest()


def _total_size(response, start: int) -> int | None:
    content_range = response.headers.get("Content-Range")
    if content_range and "/" in content_range:
        total = content_range.rsplit("/", 1)[1]
        return int(total) if total.isdigit() else None
    length = response.headers.get("Content-Length")
    return int(length) + start if length is not None and length.isdigit() else None


def download(
    url: str,
    destination: str | os.PathLike,
    *,
    sha256: str | None = None,
    validate: Callable[[Path], None] | None = None,
    timeout: float = 60.0,
    progress: bool = True,
) -> Path:
    """Fetch ``url`` to ``destination``, resuming a previous partial download.

    Bytes go to ``<destination>.part``; an interrupted download is continued from its length with an HTTP
    ``Range`` request (and restarted if the server ignores it). Once complete, the size is checked against the
    server's, then ``sha256`` (when given) and ``validate(part_path)`` (e.g. "opens as HDF5"); only then is the
    file renamed into place, so ``destination`` never holds a partial or corrupt file. A failed integrity check
    deletes the partial file. Network failures raise :class:`~spoil_torchrl.data.DatasetError` naming the URL and
    the path where the file can be placed by hand.

    Examples:
        A ``file://`` URL stands in for a server here; a second call finds the file and fetches nothing:

        >>> import tempfile
        >>> folder = Path(tempfile.mkdtemp())
        >>> source = folder / "remote.hdf5"
        >>> _ = source.write_bytes(b"dataset bytes")
        >>> url, digest = source.as_uri(), sha256_of(source)
        >>> path = download(url, folder / "cache" / "data.hdf5", sha256=digest, progress=False)
        >>> path.relative_to(folder).as_posix(), path.read_bytes()
        ('cache/data.hdf5', b'dataset bytes')
        >>> download(url, path, sha256=digest, progress=False) == path
        True
        >>> download(url, folder / "other.hdf5", sha256="0" * 64, progress=False)
        Traceback (most recent call last):
        ...
        spoil_torchrl.data.episodes.DatasetError: file://.../remote.hdf5: SHA-256 mismatch; the download was \
deleted, run again to fetch it anew
    """
    destination = Path(destination)
    if destination.exists():
        return destination
    destination.parent.mkdir(parents=True, exist_ok=True)
    part = destination.with_name(destination.name + ".part")
    start = part.stat().st_size if part.exists() else 0
    request = urllib.request.Request(url, headers={"Range": f"bytes={start}-"} if start else {})
    try:
        response = urllib.request.urlopen(request, timeout=timeout)
    except urllib.error.HTTPError as err:
        if err.code == 416 and start:  # the partial file is already complete
            response = None
        else:
            raise DatasetError(
                f"cannot download {url} (HTTP {err.code}); place the file at {destination} by hand"
            ) from err
    except (urllib.error.URLError, TimeoutError, OSError) as err:
        raise DatasetError(
            f"cannot download {url} ({getattr(err, 'reason', err)}); without network access, download it elsewhere "
            f"and place it at {destination}"
        ) from err
    total = None
    if response is not None:
        with response:
            resumed = start > 0 and response.status == 206
            if not resumed:
                start = 0
            total = _total_size(response, start)
            with (
                open(part, "ab" if resumed else "wb") as f,
                tqdm(
                    total=total,
                    initial=start,
                    unit="B",
                    unit_scale=True,
                    desc=destination.name,
                    disable=not progress,
                ) as bar,
            ):
                try:
                    shutil.copyfileobj(_Progress(response, bar), f, CHUNK)
                except (OSError, TimeoutError) as err:
                    raise DatasetError(
                        f"download of {url} broke off after {part.stat().st_size} bytes ({err}); "
                        f"run again to resume from {part}"
                    ) from err
    size = part.stat().st_size
    if total is not None and size < total:
        raise DatasetError(f"{url}: got {size} of {total} bytes; run again to resume from {part}")
    try:
        if total is not None and size > total:
            raise DatasetError(f"{url}: got {size} bytes, more than the {total} the server announced")
        if sha256 is not None and sha256_of(part) != sha256:
            raise DatasetError(f"{url}: SHA-256 mismatch")
        if validate is not None:
            validate(part)
    except DatasetError as err:
        part.unlink()
        raise DatasetError(f"{err}; the download was deleted, run again to fetch it anew") from err
    os.replace(part, destination)
    return destination


class _Progress:
    """A file-like wrapper that advances a tqdm bar as ``shutil.copyfileobj`` reads."""

    def __init__(self, raw, bar) -> None:
        self.raw, self.bar = raw, bar

    def read(self, n: int = -1) -> bytes:
        block = self.raw.read(n)
        self.bar.update(len(block))
        return block
