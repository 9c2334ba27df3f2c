"""The data root: the one place every replica publishes its finished sessions' Parquet, named by a
URI (a shared folder, or an S3-compatible object store) and reached through pyarrow.fs.

    root = open_data_root("s3://jitdyn/prod", environ=os.environ)   # checked: reachable, writable
    uri = root.publish(local_file, "frames/model=m/date=d/<id>.parquet")  # "s3://jitdyn/prod/frames/..."
    filesystem, path = open_location(uri, data=Path("jitdyn-data"), environ=os.environ)

A root is `s3://BUCKET[/PREFIX]`, `file:///ABSOLUTE/PATH` or a plain path. S3 takes the usual AWS
settings from the environment: AWS_ENDPOINT_URL (or AWS_ENDPOINT_URL_S3; an http:// endpoint is
allowed), AWS_REGION (or AWS_DEFAULT_REGION), AWS_ACCESS_KEY_ID, AWS_SECRET_ACCESS_KEY,
AWS_SESSION_TOKEN, AWS_CA_BUNDLE (a PEM file of the CAs an https endpoint's certificate is checked
against, as the AWS CLI reads it; else the system's); without keys, pyarrow's default credential
chain. Every failure is one line
that says what is wrong. Why pyarrow.fs and publishing at finish: docs/decisions/0101-data-root.md.
"""

from __future__ import annotations

import contextlib
import functools
import uuid
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import Any, Final
from urllib.parse import urlsplit

import pyarrow.fs as pafs

from jitdyn.errors import FailedPrecondition, InvalidArgument, Unavailable
from jitdyn.storage.layout import make_dirs, session_of, write_durably

__all__ = [
    "SCHEMES",
    "DataRoot",
    "is_uri",
    "normalise_root_uri",
    "open_data_root",
    "open_location",
    "resolve_data_root",
]

SCHEMES: Final = ("file", "s3")
_COPY_CHUNK: Final = 1 << 20
# An object store that does not answer is given up on after about this long per request (seconds),
# so that a session's close waits boundedly before its Parquet is kept for a later publish.
_CONNECT_TIMEOUT: Final = 3.0
_REQUEST_TIMEOUT: Final = 30.0
_ATTEMPTS: Final = 2


def _one_line(error: BaseException) -> str:
    return " ".join(str(error).split()) or type(error).__name__


def is_uri(location: str) -> bool:
    """Whether a stored location is a URI on a data root (rather than relative to a data folder)."""
    return "://" in location


def normalise_root_uri(text: str) -> str:
    """The canonical form of a data root: `s3://bucket/prefix` or `file:///absolute/path`, with no
    trailing slash. A plain path is made absolute. Raises InvalidArgument saying what is wrong."""
    text = text.strip()
    if not text:
        raise InvalidArgument(
            "--data-root must be a URI (s3://bucket/prefix, file:///path) or a path, got ''"
        )
    if "://" not in text:
        return _file_uri(str(Path(text).expanduser().absolute()))
    parts = urlsplit(text)
    scheme = parts.scheme.lower()
    if scheme not in SCHEMES:
        raise InvalidArgument(
            f"--data-root scheme {parts.scheme!r} is not supported; use s3://bucket/prefix, "
            f"file:///path or a path, got {text!r}"
        )
    if parts.query or parts.fragment:
        raise InvalidArgument(
            f"--data-root takes no ?query or #fragment (the S3 endpoint comes from AWS_ENDPOINT_URL), got {text!r}"
        )
    if scheme == "s3":
        if not parts.netloc:
            raise InvalidArgument(f"--data-root {text!r} names no bucket; write s3://BUCKET/PREFIX")
        if "@" in parts.netloc or ":" in parts.netloc:
            raise InvalidArgument(
                f"--data-root {text!r}: the bucket must be a plain name (keys and endpoint come from "
                "the AWS_* environment variables)"
            )
        prefix = "/".join(p for p in parts.path.split("/") if p)
        return f"s3://{parts.netloc}" + (f"/{prefix}" if prefix else "")
    if parts.netloc not in ("", "localhost"):
        raise InvalidArgument(f"--data-root {text!r} names a host; a file URI is file:///ABSOLUTE/PATH")
    return _file_uri(parts.path)


def _file_uri(path: str) -> str:
    # Not percent-encoded: the URI is read back only by `_filesystem`, which takes the path as is.
    return "file://" + str(PurePosixPath("/" + path.lstrip("/")))


def _endpoint(environ: Mapping[str, str]) -> tuple[str | None, str]:
    """(host[:port] or None, scheme) of the S3 endpoint the environment names."""
    url = environ.get("AWS_ENDPOINT_URL_S3") or environ.get("AWS_ENDPOINT_URL")
    if not url:
        return None, "https"
    parts = urlsplit(url if "://" in url else f"https://{url}")
    if parts.scheme not in ("http", "https") or not parts.netloc:
        raise InvalidArgument(f"AWS_ENDPOINT_URL must be http(s)://HOST[:PORT], got {url!r}")
    return parts.netloc, parts.scheme


@functools.lru_cache(maxsize=16)
def _s3(
    endpoint: str | None,
    scheme: str,
    region: str | None,
    keys: tuple[str, str, str] | None,
    ca_bundle: str | None = None,
) -> Any:
    options: dict[str, Any] = {
        "scheme": scheme,
        "connect_timeout": _CONNECT_TIMEOUT,
        "request_timeout": _REQUEST_TIMEOUT,
        "retry_strategy": pafs.AwsStandardS3RetryStrategy(max_attempts=_ATTEMPTS),
    }
    if endpoint is not None:
        options["endpoint_override"] = endpoint
    if region is not None:
        options["region"] = region
    if ca_bundle is not None:
        options["tls_ca_file_path"] = ca_bundle
    if keys is not None:
        options["access_key"], options["secret_key"] = keys[0], keys[1]
        if keys[2]:
            options["session_token"] = keys[2]
    return pafs.S3FileSystem(**options)


def _s3_for(bucket: str, environ: Mapping[str, str]) -> Any:
    endpoint, scheme = _endpoint(environ)
    region = environ.get("AWS_REGION") or environ.get("AWS_DEFAULT_REGION")
    if region is None and endpoint is None:
        try:
            region = pafs.resolve_s3_region(bucket)  # AWS itself: the bucket's own region
        except OSError as error:
            raise Unavailable(
                f"the region of bucket {bucket!r} cannot be found: {_one_line(error)}"
            ) from None
    elif region is None:
        region = "us-east-1"  # what S3-compatible servers answer to unless told otherwise
    key, secret = environ.get("AWS_ACCESS_KEY_ID"), environ.get("AWS_SECRET_ACCESS_KEY")
    keys = (key, secret, environ.get("AWS_SESSION_TOKEN", "")) if key and secret else None
    return _s3(endpoint, scheme, region, keys, environ.get("AWS_CA_BUNDLE") or None)


def _filesystem(uri: str, environ: Mapping[str, str]) -> tuple[Any, str]:
    """The file system and its path of a normalised URI (of a root, or of a file on one)."""
    parts = urlsplit(uri)
    if parts.scheme == "s3":
        return _s3_for(parts.netloc, environ), f"{parts.netloc}{parts.path}".rstrip("/")
    return pafs.LocalFileSystem(), uri.removeprefix("file://")


@dataclass(frozen=True)
class DataRoot:
    """A data root, resolved: its URI, its pyarrow file system, and its base path on it."""

    uri: str
    filesystem: Any  # pyarrow.fs.FileSystem
    base: str

    @property
    def local(self) -> bool:
        """A folder of this machine's (a shared mount), written with fsync; otherwise an object store."""
        return isinstance(self.filesystem, pafs.LocalFileSystem)

    def uri_of(self, relative: str) -> str:
        return f"{self.uri}/{relative}"

    def path_of(self, relative: str) -> str:
        return f"{self.base}/{relative}"

    def publish(self, source: Path, relative: str) -> str:
        """Copy the file `source` to `relative` under the root, whole or not at all; its URI.

        Raises OSError (or pyarrow's ArrowException) when the root cannot take it; the caller keeps
        `source` and tries again later."""
        if self.local:
            self._publish_local(source, relative)
        else:
            self._publish_object(source, relative)
        return self.uri_of(relative)

    def _publish_local(self, source: Path, relative: str) -> None:
        # A shared folder: a temporary file beside the target, fsync, rename, fsync of the folder,
        # so that the copy is durable before the caller deletes its own.
        base = Path(self.base)
        folder = make_dirs(base, str(PurePosixPath(relative).parent))
        target = folder / PurePosixPath(relative).name
        with source.open("rb") as src:
            write_durably(target, iter(lambda: src.read(_COPY_CHUNK), b""))

    def _publish_object(self, source: Path, relative: str) -> None:
        # An object appears whole when its upload completes, or not at all.
        path = self.path_of(relative)
        size = source.stat().st_size
        with source.open("rb") as src, self.filesystem.open_output_stream(path) as out:
            while chunk := src.read(_COPY_CHUNK):
                out.write(chunk)
        stored = self.filesystem.get_file_info(path)
        if stored.type != pafs.FileType.File or stored.size != size:
            raise OSError(f"{self.uri_of(relative)} holds {stored.size} bytes after the upload of {size}")

    def delete(self, relative: str) -> None:
        """Remove the file at `relative`; one that is not there is no error."""
        with contextlib.suppress(FileNotFoundError):
            self.filesystem.delete_file(self.path_of(relative))

    def drop_other_copies(self, relative: str) -> list[str]:
        """Remove every other stored copy of the session whose file is `relative` (another epoch's:
        a stale finisher's, or one published before a take-over); the names removed."""
        folder = PurePosixPath(relative).parent
        keep = PurePosixPath(relative).name
        session = session_of(keep)
        selector = pafs.FileSelector(self.path_of(str(folder)), allow_not_found=True)
        removed = []
        for info in self.filesystem.get_file_info(selector):
            name = PurePosixPath(info.path).name
            if name != keep and name.endswith(".parquet") and session_of(name) == session:
                self.delete(f"{folder}/{name}")
                removed.append(name)
        return removed

    def exists(self, relative: str) -> bool:
        return bool(self.filesystem.get_file_info(self.path_of(relative)).type == pafs.FileType.File)

    def check(self) -> None:
        """Prove the root reachable and writable: write and delete a small object.

        Raises FailedPrecondition (no such bucket or folder) or Unavailable (with the reason)."""
        if self.local:
            if not Path(self.base).is_dir():
                raise FailedPrecondition(
                    f"the data root {self.uri} is not a folder; create it, or mount the shared folder there"
                )
        else:
            bucket = self.base.split("/", 1)[0]
            try:
                info = self.filesystem.get_file_info(bucket)
            except OSError as error:
                raise Unavailable(f"the data root {self.uri} cannot be reached: {_one_line(error)}") from None
            if info.type == pafs.FileType.NotFound:
                raise FailedPrecondition(
                    f"the data root {self.uri}: bucket {bucket!r} does not exist at the S3 endpoint; "
                    "create it first (jitdyn creates no buckets)"
                )
        probe = f".write-test-{uuid.uuid4().hex[:12]}"
        try:
            with self.filesystem.open_output_stream(self.path_of(probe)) as out:
                out.write(b"jitdyn")
            self.filesystem.delete_file(self.path_of(probe))
        except OSError as error:
            raise Unavailable(f"the data root {self.uri} cannot be written: {_one_line(error)}") from None


def resolve_data_root(text: str, *, environ: Mapping[str, str]) -> DataRoot:
    """The data root `text` names, not yet checked (no request is made, unless AWS itself must
    tell the bucket's region). Raises InvalidArgument for a bad URI or endpoint."""
    uri = normalise_root_uri(text)
    filesystem, base = _filesystem(uri, environ)
    return DataRoot(uri=uri, filesystem=filesystem, base=base)


def open_data_root(text: str, *, environ: Mapping[str, str]) -> DataRoot:
    """The data root `text` names, checked reachable and writable (see `DataRoot.check`).

    Raises InvalidArgument (a bad URI or endpoint), FailedPrecondition (no such bucket or folder)
    or Unavailable (the store does not answer, or refuses to be written), each in one line."""
    root = resolve_data_root(text, environ=environ)
    root.check()
    return root


def open_location(location: str, *, data: Path, environ: Mapping[str, str]) -> tuple[Any, str]:
    """The file system and path of a session's stored location: a URI on a data root, or a path
    relative to the data folder `data` (a session stored without a data root, or not yet published).

    Raises InvalidArgument for a URI of a scheme jitdyn does not write."""
    if not is_uri(location):
        return pafs.LocalFileSystem(), str((data / location).absolute())
    scheme = urlsplit(location).scheme.lower()
    if scheme not in SCHEMES:
        raise InvalidArgument(f"the stored location {location!r} is not on a file or s3 data root")
    return _filesystem(location, environ)
