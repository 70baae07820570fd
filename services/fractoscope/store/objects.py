"""Objects in an S3-compatible bucket under a key prefix, with the conditional writes that
publishing and leases rest on (If-Match, If-None-Match: *).

`open_objects("s3://bucket/prefix")` reads the endpoint and credentials from the standard
AWS_ENDPOINT_URL, AWS_ACCESS_KEY_ID, AWS_SECRET_ACCESS_KEY and AWS_REGION (boto3 reads them),
so the same flag points at AWS S3, MinIO, Ceph RGW or SeaweedFS. An unreachable server is
UnavailableError (gRPC UNAVAILABLE, HTTP 503): callers retry.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path
from typing import NamedTuple
from urllib.parse import urlparse

import boto3
import botocore.config
import botocore.exceptions

from fractoscope.errors import InvalidInputError, UnavailableError

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
            retries={"max_attempts": 3, "mode": "standard"},
            connect_timeout=5,
            read_timeout=60,
            s3={"addressing_style": "path"},
        )
        region = os.environ.get("AWS_REGION") or os.environ.get("AWS_DEFAULT_REGION") or "us-east-1"
        self._client = boto3.session.Session().client("s3", config=config, region_name=region)

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
        """S3's answers as this module's errors; a server out of reach as UnavailableError."""
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
        except (botocore.exceptions.EndpointConnectionError, botocore.exceptions.ConnectionError) as error:
            raise UnavailableError(f"the object store {self.url} cannot be reached: {error}") from None


def open_objects(url: str) -> S3Objects:
    """The objects at `s3://bucket/prefix` (InvalidInputError naming `store` for another form)."""
    parsed = urlparse(url)
    if parsed.scheme != "s3" or not parsed.netloc:
        raise InvalidInputError("store", f"{url!r} is not s3://BUCKET[/PREFIX]")
    return S3Objects(parsed.netloc, parsed.path)
