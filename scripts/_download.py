"""Shared download helper for the dataset scripts: mirrors, resume, checksums, extraction.

A :class:`Resource` names one file and the mirrors it can come from, with whatever integrity
information is published for it (sha256 / md5 of the archive, its size, or md5 sums of files
inside it). :func:`fetch` tries the mirrors in order, resumes a partial ``<name>.part`` file
with an HTTP ``Range`` request, verifies the result and only then renames it into place.
When every mirror fails the error tells the user exactly which file to download by hand and
where to put it; the scripts then pick it up from there (a file already present and valid is
never downloaded again).

Only the standard library is used (urllib), plus tqdm for progress bars.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import tarfile
import urllib.error
import urllib.request
import zipfile
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath

from tqdm import tqdm

CHUNK_BYTES = 1 << 20
USER_AGENT = "linereg-dataset-download/1.0"


class DownloadError(RuntimeError):
    """No mirror delivered a valid file; the message says how to get it by hand."""


class IntegrityError(ValueError):
    """A file does not match its published size or checksum."""


@dataclass(frozen=True)
class Resource:
    """One downloadable file.

    Attributes:
        name: file name on disk.
        urls: mirrors, tried in order.
        sha256: published SHA-256 of the file, if any.
        md5: published MD5 of the file, if any.
        size: expected size in bytes, if known.
        member_md5: MD5 sums of files inside the archive (checked after extraction).
        note: provenance of the checksums / anything the user should know.
    """

    name: str
    urls: tuple[str, ...]
    sha256: str | None = None
    md5: str | None = None
    size: int | None = None
    member_md5: dict[str, str] = field(default_factory=dict)
    note: str = ""

    def has_checksum(self) -> bool:
        """Whether the archive itself has a published digest (sha256 or md5)."""
        return bool(self.sha256 or self.md5)

    def integrity(self) -> str:
        """Human-readable description of how the file is verified."""
        checks = [f"sha256 {self.sha256}" if self.sha256 else "", f"md5 {self.md5}" if self.md5 else ""]
        checks.append(f"size {self.size} bytes" if self.size else "")
        if self.member_md5:
            checks.append(f"md5 of {len(self.member_md5)} extracted files")
        described = ", ".join(c for c in checks if c)
        return described or "none published (only archive readability is checked)"


def file_digest(path: Path, algorithm: str) -> str:
    """Hex digest of a file (``"sha256"`` or ``"md5"``), read in 1 MiB chunks."""
    digest = hashlib.new(algorithm)
    with path.open("rb") as stream:
        for chunk in iter(lambda: stream.read(CHUNK_BYTES), b""):
            digest.update(chunk)
    return digest.hexdigest()


def verify(path: Path, resource: Resource) -> None:
    """Raise :class:`IntegrityError` unless ``path`` matches the resource's size and checksums."""
    size = path.stat().st_size
    if resource.size is not None and size != resource.size:
        raise IntegrityError(f"{path}: size {size} bytes, expected {resource.size}")
    for algorithm in ("sha256", "md5"):
        expected = getattr(resource, algorithm)
        if expected is not None:
            actual = file_digest(path, algorithm)
            if actual != expected.lower():
                raise IntegrityError(f"{path}: {algorithm} {actual}, expected {expected}")


def verify_members(directory: Path, member_md5: dict[str, str]) -> None:
    """Raise :class:`IntegrityError` unless extracted files match their published MD5 sums."""
    for relative, expected in member_md5.items():
        path = directory / relative
        if not path.is_file():
            raise IntegrityError(f"{path}: missing after extraction")
        actual = file_digest(path, "md5")
        if actual != expected:
            raise IntegrityError(f"{path}: md5 {actual}, expected {expected}")


def download(url: str, destination: Path, *, timeout: float = 60.0, progress: bool = True) -> Path:
    """Download ``url`` to ``destination``, resuming ``<destination>.part`` when present.

    A partial file is continued with ``Range: bytes=<size>-``; a server answering 200 instead
    of 206 (no range support) restarts the file from scratch, and 416 (range not satisfiable)
    means the partial file is already complete.

    Returns:
        ``destination`` (written atomically by renaming the ``.part`` file).

    Raises:
        urllib.error.URLError / OSError: network or HTTP failure (the ``.part`` file is kept).
    """
    destination.parent.mkdir(parents=True, exist_ok=True)
    partial = destination.with_name(destination.name + ".part")
    offset = partial.stat().st_size if partial.exists() else 0
    request = urllib.request.Request(url, headers={"User-Agent": USER_AGENT})
    if offset:
        request.add_header("Range", f"bytes={offset}-")
    try:
        response = urllib.request.urlopen(request, timeout=timeout)
    except urllib.error.HTTPError as error:
        if error.code != 416 or not offset:
            raise
        partial.replace(destination)
        return destination
    with response:
        if offset and response.status != 206:
            offset = 0
        length = response.headers.get("Content-Length")
        total = offset + int(length) if length is not None else None
        with (
            partial.open("ab" if offset else "wb") as stream,
            tqdm(
                total=total,
                initial=offset,
                unit="B",
                unit_scale=True,
                desc=destination.name,
                disable=not progress,
            ) as bar,
        ):
            for chunk in iter(lambda: response.read(CHUNK_BYTES), b""):
                stream.write(chunk)
                bar.update(len(chunk))
    if total is not None and partial.stat().st_size != total:
        raise OSError(f"{url}: connection closed after {partial.stat().st_size} of {total} bytes")
    partial.replace(destination)
    return destination


def manual_instructions(resource: Resource, directory: Path) -> str:
    """What to do by hand when no mirror works."""
    mirrors = "\n".join(f"  - {url}" for url in resource.urls)
    return (
        f"Download {resource.name} by hand from one of:\n{mirrors}\n"
        f"(or any other copy of it) and put it at\n  {directory / resource.name}\n"
        f"then run this script again: it verifies the file ({resource.integrity()}) and "
        "extracts it."
    )


def fetch(resource: Resource, directory: Path, *, timeout: float = 60.0, progress: bool = True) -> Path:
    """A verified local copy of ``resource`` in ``directory`` (downloaded when missing).

    Plain-``http://`` mirrors are used only when the resource has a sha256 or md5 to verify the
    file against; otherwise they are skipped (and listed in the error).

    Raises:
        IntegrityError: a file already present (e.g. placed by hand) fails verification.
        DownloadError: every mirror failed or delivered a corrupt file; the message lists
            each failure and the manual instructions.
    """
    destination = directory / resource.name
    if destination.is_file():
        verify(destination, resource)
        return destination
    failures = []
    for url in resource.urls:
        if url.startswith("http://") and not resource.has_checksum():
            failures.append(
                f"{url}: skipped, plain http without a published checksum (a corrupted or tampered file could not "
                "be detected); fetch it by hand only if you trust the connection"
            )
            continue
        try:
            download(url, destination, timeout=timeout, progress=progress)
            verify(destination, resource)
            return destination
        except IntegrityError as error:
            destination.unlink(missing_ok=True)
            failures.append(f"{url}: {error}")
        except (urllib.error.URLError, OSError, ValueError) as error:
            failures.append(f"{url}: {error}")
    tried = "\n".join(f"  * {failure}" for failure in failures)
    raise DownloadError(f"could not download {resource.name}:\n{tried}\n\n{manual_instructions(resource, directory)}")


def _safe_target(directory: Path, member: str) -> Path:
    """Extraction path of an archive member.

    Raises:
        ValueError: the path would escape ``directory`` (absolute, ``..``), or passes through or
            ends at a symbolic link already inside ``directory`` (which could point anywhere).
    """
    relative = PurePosixPath(member)
    if relative.is_absolute() or ".." in relative.parts:
        raise ValueError(f"refusing to extract {member!r}: it points outside {directory}")
    target = directory
    for part in relative.parts:
        target = target / part
        if target.is_symlink():
            raise ValueError(
                f"refusing to extract {member!r}: {target} is a symbolic link inside {directory}, which "
                "extraction would follow; remove it or extract into an empty folder"
            )
    return target


def _write_member(source, target: Path) -> None:
    """Copy an archive member's stream to ``target``, never through a symbolic link there."""
    target.parent.mkdir(parents=True, exist_ok=True)
    descriptor = os.open(target, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | getattr(os, "O_NOFOLLOW", 0), 0o644)
    with os.fdopen(descriptor, "wb") as sink:
        shutil.copyfileobj(source, sink)


def extract(archive: Path, directory: Path) -> list[Path]:
    """Extract a ``.zip`` / ``.tar`` / ``.tar.gz`` / ``.tgz`` archive into ``directory``.

    Members with absolute paths or ``..`` components, and members whose path runs through a
    symbolic link already inside ``directory``, are rejected before anything is written; links
    stored in a tar archive are not extracted.

    Returns:
        The extracted regular files.

    Raises:
        ValueError: unknown archive type, unsafe member path, or a corrupt archive.
    """
    directory.mkdir(parents=True, exist_ok=True)
    written = []
    try:
        if zipfile.is_zipfile(archive):
            with zipfile.ZipFile(archive) as bundle:
                members = [m for m in bundle.infolist() if not m.is_dir()]
                targets = [_safe_target(directory, m.filename) for m in members]
                for member, target in zip(members, targets, strict=True):
                    with bundle.open(member) as source:
                        _write_member(source, target)
                    written.append(target)
        elif tarfile.is_tarfile(archive):
            with tarfile.open(archive) as bundle:
                members = [m for m in bundle.getmembers() if m.isfile()]
                targets = [_safe_target(directory, m.name) for m in members]
                for member, target in zip(members, targets, strict=True):
                    with bundle.extractfile(member) as source:
                        _write_member(source, target)
                    written.append(target)
        else:
            raise ValueError(f"{archive}: not a zip or tar archive")
    except (zipfile.BadZipFile, tarfile.TarError, EOFError) as error:
        raise ValueError(f"{archive}: corrupt archive ({error}); delete it and download again") from error
    return written


def fetch_and_extract(resource: Resource, download_dir: Path, extract_dir: Path, *, progress: bool = True) -> Path:
    """Fetch an archive, extract it once (a ``.<name>.extracted`` marker records it), verify members."""
    marker = extract_dir / f".{resource.name}.extracted"
    if marker.is_file():
        return extract_dir
    archive = fetch(resource, download_dir, progress=progress)
    extract(archive, extract_dir)
    verify_members(extract_dir, resource.member_md5)
    marker.write_text(f"{archive}\n")
    return extract_dir
