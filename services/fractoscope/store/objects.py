"""Objects in an S3-compatible bucket under a key prefix, with the conditional writes that
publishing and leases rest on (If-Match, If-None-Match: *).

`open_objects("s3://bucket/prefix")` reads the endpoint and credentials from the standard
AWS_ENDPOINT_URL, AWS_ACCESS_KEY_ID, AWS_SECRET_ACCESS_KEY and AWS_REGION (boto3 reads them),
so the same flag points at AWS S3, MinIO, Ceph RGW or SeaweedFS. An unreachable server is
UnavailableError (gRPC UNAVAILABLE, HTTP 503): callers retry.

Every wait is bounded: a connection within CONNECT_TIMEOUT_S, each read within READ_TIMEOUT_S,
ATTEMPTS tries in all; a server that did not answer so is held out of reach for OUTAGE_HOLD_S, its
calls failing at once meanwhile (the first after it tries again), so that a frozen server costs
a request one bounded wait, not one per object it reads.
"""

from __future__ import annotations

import contextlib
import os
import time
from collections.abc import Iterator
from pathlib import Path
from typing import NamedTuple
from urllib.parse import urlparse

import boto3
import botocore.config
import botocore.exceptions

from fractoscope.errors import InvalidInputError, UnavailableError

CONNECT_TIMEOUT_S = 2.0
READ_TIMEOUT_S = float(os.environ.get("FRACTO_S3_READ_TIMEOUT_S", "3"))
ATTEMPTS = 2
OUTAGE_HOLD_S = 5.0
# Codes S3 servers answer a failed condition with: 412, or 409 for a concurrent conditional write.
_PRECONDITION_CODES = {"PreconditionFailed", "ConditionalRequestConflict", "412", "409"}
_MISSING_CODES = {"NoSuchKey", "404", "NotFound"}


class ObjectMissing(FileNotFoundError):
    """No object under that key (a FileNotFoundError, as a missing file of the folder store)."""


class PreconditionFailed(Exception):
    """A conditional write whose condition failed: the object changed, or exists, meanwhile."""


class Stored(NamedTuple):
    data: bytes
    etag: str


class Listed(NamedTuple):
    key: str  # relative to the prefix
    modified_s: float  # last modified, Unix seconds


class S3Objects:
    """The objects of `bucket` under `prefix` (keys here are relative to it). Thread-safe: boto3
    clients are. `max_pool` bounds the connections kept to the server."""

    def __init__(self, bucket: str, prefix: str = "", *, max_pool: int = 32):
        self.bucket = bucket
        self.prefix = prefix.strip("/") + "/" if prefix.strip("/") else ""
        config = botocore.config.Config(
            max_pool_connections=max_pool,
            retries={"total_max_attempts": ATTEMPTS, "mode": "standard"},
            connect_timeout=CONNECT_TIMEOUT_S,
            read_timeout=READ_TIMEOUT_S,
            s3={"addressing_style": "path"},
        )
        region = os.environ.get("AWS_REGION") or os.environ.get("AWS_DEFAULT_REGION") or "us-east-1"
        self._client = boto3.session.Session().client("s3", config=config, region_name=region)
        self._out_of_reach: tuple[float, str] | None = None  # (until, monotonic s; why)

    @property
    def outage(self) -> str | None:
        """Why the server is held out of reach now (see the module docstring), None when it is not."""
        held = self._out_of_reach
        return held[1] if held is not None and time.monotonic() < held[0] else None

    def check(self) -> None:
        """One bounded call (the bucket's first key): UnavailableError when the server does not
        answer or refuses the bucket."""
        with self._calling(""):
            self._client.list_objects_v2(Bucket=self.bucket, Prefix=self.prefix, MaxKeys=1)

    @property
    def url(self) -> str:
        return f"s3://{self.bucket}/{self.prefix}"

    def get(self, key: str) -> Stored:
        """The object's bytes and ETag; ObjectMissing when there is none."""
        with self._calling(key):
            answer = self._client.get_object(Bucket=self.bucket, Key=self.prefix + key)
            return Stored(answer["Body"].read(), answer["ETag"])

    def put(self, key: str, data: bytes, *, if_match: str | None = None, if_absent: bool = False) -> str:
        """Writes an object, only if its ETag is still `if_match` or, with `if_absent`, if there is
        none; returns its ETag. PreconditionFailed when the condition fails."""
        options = {"IfMatch": if_match} if if_match else {"IfNoneMatch": "*"} if if_absent else {}
        with self._calling(key):
            return self._client.put_object(Bucket=self.bucket, Key=self.prefix + key, Body=data, **options)["ETag"]

    def put_file(self, key: str, path: Path) -> None:
        """Writes a file's content (in parts when large, never all in memory)."""
        with self._calling(key):
            self._client.upload_file(str(path), self.bucket, self.prefix + key)

    def get_file(self, key: str, path: Path) -> None:
        """Reads an object into a file; ObjectMissing when there is none."""
        with self._calling(key):
            self._client.download_file(self.bucket, self.prefix + key, str(path))

    def delete(self, key: str) -> None:
        """Removes an object; one that is not there is no error (S3's own rule)."""
        with self._calling(key):
            self._client.delete_object(Bucket=self.bucket, Key=self.prefix + key)

    def delete_many(self, keys: list[str]) -> None:
        for start in range(0, len(keys), 1000):  # the most one DeleteObjects takes
            batch = [{"Key": self.prefix + key} for key in keys[start : start + 1000]]
            with self._calling(keys[start]):
                self._client.delete_objects(Bucket=self.bucket, Delete={"Objects": batch, "Quiet": True})

    def list(self, prefix: str = "") -> Iterator[Listed]:
        """The objects whose keys start with `prefix`, in key order."""
        pages = self._client.get_paginator("list_objects_v2").paginate(Bucket=self.bucket, Prefix=self.prefix + prefix)
        with self._calling(prefix):
            for page in pages:
                for item in page.get("Contents", []):
                    yield Listed(item["Key"][len(self.prefix) :], item["LastModified"].timestamp())

    @contextlib.contextmanager
    def _calling(self, key: str) -> Iterator[None]:
        """S3's answers as this module's errors; a server out of reach as UnavailableError, at once
        while it is held so (see the module docstring)."""
        if (outage := self.outage) is not None:
            raise UnavailableError(f"{outage}; retry in a few seconds")
        try:
            yield
        except botocore.exceptions.ClientError as error:
            code = str(error.response.get("Error", {}).get("Code", ""))
            if code in _MISSING_CODES:
                raise ObjectMissing(f"no object {key!r} in {self.url}") from None
            if code in _PRECONDITION_CODES:
                raise PreconditionFailed(f"{key!r} in {self.url} changed meanwhile") from None
            if code in ("NoSuchBucket", "AccessDenied", "InvalidAccessKeyId", "SignatureDoesNotMatch"):
                raise UnavailableError(f"the object store {self.url} refused {key!r}: {code}") from None
            raise
        except (botocore.exceptions.ConnectionError, botocore.exceptions.HTTPClientError) as error:
            # Refused, timed out connecting or reading, or cut off: a server not there or not answering.
            why = f"the object store {self.url} cannot be reached ({type(error).__name__}: {error})"
            self._out_of_reach = (time.monotonic() + OUTAGE_HOLD_S, why)
            raise UnavailableError(why) from None
        self._out_of_reach = None


def open_objects(url: str) -> S3Objects:
    """The objects at `s3://bucket/prefix` (InvalidInputError naming `store` for another form)."""
    parsed = urlparse(url)
    if parsed.scheme != "s3" or not parsed.netloc:
        raise InvalidInputError("store", f"{url!r} is not s3://BUCKET[/PREFIX]")
    return S3Objects(parsed.netloc, parsed.path)
